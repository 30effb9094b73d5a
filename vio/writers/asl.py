"""Writes a capture in the EuRoC/ASL layout (the layout `vio.readers` reads back): images, IMU, ground truth and
Kalibr sensor YAMLs, built in a temporary folder and renamed into place."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import cv2
import numpy as np

from vio.atomic import write_text
from vio.errors import CaptureError
from vio.kalibr import camera_yaml_text, imu_yaml_text
from vio.records import CameraCalib, GroundTruth, ImuCalib, ImuSeries

IMU_HEADER = (
    "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
    "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]"
)
GT_HEADER = (
    "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
    "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], "
    "b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]"
)


def encode_png(image: np.ndarray) -> bytes:
    """Lossless PNG bytes of an image (parameters fixed, so the bytes are reproducible).

    Huffman-only deflate: on noisy camera images it is faster and smaller than LZ77 matching at level 1.
    """
    params = [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY]
    ok, buf = cv2.imencode(".png", image, params)
    if not ok:
        raise CaptureError("PNG encoding failed")
    return buf.tobytes()


class AslWriter:
    """Writes an ASL capture into a temporary folder and renames it into place on `close()`.

    A capture that fails half-way never appears under the target name.
    """

    def __init__(self, root: str | os.PathLike[str], overwrite: bool = False) -> None:
        self.root = Path(root)
        if self.root.exists() and not overwrite and any(self.root.iterdir()):
            raise CaptureError("output folder exists and is not empty (use --force to replace it)", self.root)
        self.root.parent.mkdir(parents=True, exist_ok=True)
        self.tmp = Path(tempfile.mkdtemp(prefix=f".{self.root.name}.", dir=self.root.parent))
        self.mav0 = self.tmp / "mav0"
        (self.mav0 / "cam0" / "data").mkdir(parents=True)
        (self.mav0 / "imu0").mkdir(parents=True)
        self._frames: dict[int, list[int]] = {0: []}  # camera id -> frame times written, ns
        self._closed = False

    @property
    def scene_dir(self) -> Path:
        d = self.tmp / "scene"
        d.mkdir(exist_ok=True)
        return d

    def _cam_dir(self, cam_id: int) -> Path:
        """`mav0/camN/` with its `data/` folder (cam0: the tracking video; cam1: full-resolution stills)."""
        d = self.mav0 / f"cam{int(cam_id)}"
        (d / "data").mkdir(parents=True, exist_ok=True)
        self._frames.setdefault(int(cam_id), [])
        return d

    def write_camera(self, cam: CameraCalib, comment: str = "vio camera", cam_id: int = 0) -> None:
        write_text(self._cam_dir(cam_id) / "sensor.yaml", camera_yaml_text(cam, comment))

    def write_imu(self, calib: ImuCalib, imu: ImuSeries, comment: str = "vio imu") -> None:
        write_text(self.mav0 / "imu0" / "sensor.yaml", imu_yaml_text(calib, comment))
        lines = [IMU_HEADER]
        for t, w, a in zip(imu.t_ns, imu.gyro, imu.acc, strict=True):
            lines.append(f"{int(t)}," + ",".join(f"{x:.9g}" for x in (*w, *a)))
        write_text(self.mav0 / "imu0" / "data.csv", "\n".join(lines) + "\n")

    def add_frame(self, t_ns: int, image: np.ndarray, cam_id: int = 0) -> None:
        """Write one image as `camN/data/<t_ns>.png` (lossless; PNG compression level fixed for determinism)."""
        self.add_png(t_ns, encode_png(image), cam_id)

    def add_png(self, t_ns: int, png: bytes, cam_id: int = 0) -> None:
        """Write one already encoded PNG image as `camN/data/<t_ns>.png` (e.g. encoded in a worker process)."""
        d, frames = self._cam_dir(cam_id), self._frames[int(cam_id)]
        if frames and t_ns <= frames[-1]:
            raise CaptureError(f"cam{cam_id} frame times must increase ({t_ns} after {frames[-1]})", self.root)
        (d / "data" / f"{int(t_ns)}.png").write_bytes(png)
        frames.append(int(t_ns))

    def write_groundtruth(self, gt: GroundTruth) -> None:
        d = self.mav0 / "state_groundtruth_estimate0"
        d.mkdir(exist_ok=True)
        lines = [GT_HEADER]
        for i in range(len(gt)):
            vals = (*gt.p_world[i], *gt.q_wxyz[i], *gt.v_world[i], *gt.b_w[i], *gt.b_a[i])
            lines.append(f"{int(gt.t_ns[i])}," + ",".join(f"{x:.12g}" for x in vals))
        write_text(d / "data.csv", "\n".join(lines) + "\n")
        write_text(d / "sensor.yaml", "%YAML:1.0\nsensor_type: visual-inertial\ncomment: ground truth\n")

    def close(self) -> Path:
        for cam_id, frames in self._frames.items():
            lines = ["#timestamp [ns],filename"] + [f"{t},{t}.png" for t in frames]
            write_text(self.mav0 / f"cam{cam_id}" / "data.csv", "\n".join(lines) + "\n")
        if self.root.exists():
            shutil.rmtree(self.root)
        os.replace(self.tmp, self.root)
        self._closed = True
        return self.root

    def abort(self) -> None:
        if not self._closed:
            shutil.rmtree(self.tmp, ignore_errors=True)

    def __enter__(self) -> AslWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()
