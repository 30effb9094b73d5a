"""`vio track` as a user runs it: a subprocess on a small capture, and one-line errors for bad input."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.conftest import ROOT
from vio.records import CameraCalib
from vio.writers.asl import AslWriter

STEP_PX = np.array([1.5, 0.75])  # image motion per frame
N_FRAMES = 8
T0_NS = 1_700_000_000_000_000_000


def run_vio(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "vio.cli", *args], cwd=ROOT, capture_output=True, text=True, timeout=120
    )


@pytest.fixture(scope="module")
def shifting_capture(tmp_path_factory) -> Path:
    """An ASL capture of a blurred-noise texture sliding by STEP_PX per frame at 20 Hz (undistorted camera)."""
    root = tmp_path_factory.mktemp("trackcli") / "cap"
    rng = np.random.default_rng(3)
    tex = cv2.GaussianBlur(rng.uniform(0, 255, (600, 800)).astype(np.float32), (0, 0), 2.0)
    tex = (tex - tex.min()) / (tex.max() - tex.min()) * 255.0
    cam = CameraCalib(640, 480, 500.0, 500.0, 319.5, 239.5, np.zeros(4), np.eye(4), 20.0)
    with AslWriter(root) as w:
        w.write_camera(cam)
        for k in range(N_FRAMES):
            dx, dy = k * STEP_PX
            M = np.array([[1.0, 0.0, 60.0 - dx], [0.0, 1.0, 60.0 - dy]])
            img = cv2.warpAffine(tex, M, (640, 480), flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP)
            w.add_frame(T0_NS + k * 50_000_000, np.clip(img, 0, 255).astype(np.uint8))
    return root


def test_vio_track_writes_tracks_that_follow_the_motion(shifting_capture, tmp_path):
    out = tmp_path / "tracks.csv"
    res = run_vio("track", str(shifting_capture), "--out", str(out))
    assert res.returncode == 0, res.stderr
    lines = out.read_text().splitlines()
    assert lines[0] == "t_ns,track_id,u,v"
    rows = [line.split(",") for line in lines[1:]]
    t_ns = np.array([int(r[0]) for r in rows])
    ids = np.array([int(r[1]) for r in rows])
    uv = np.array([[float(r[2]), float(r[3])] for r in rows])
    frames = np.unique(t_ns)
    assert np.array_equal(frames, T0_NS + np.arange(N_FRAMES) * 50_000_000)
    assert all(np.count_nonzero(t_ns == t) >= 140 for t in frames)
    uv_first = {int(i): xy for i, xy in zip(ids[t_ns == frames[0]], uv[t_ns == frames[0]], strict=True)}
    for k, t in enumerate(frames[1:], start=1):
        sel = (t_ns == t) & np.isin(ids, list(uv_first))
        assert np.count_nonzero(sel) >= 130
        expected = np.array([uv_first[int(i)] for i in ids[sel]]) + k * STEP_PX
        assert np.median(np.linalg.norm(uv[sel] - expected, axis=1)) < 0.05


def test_vio_track_bad_path_is_one_clear_line(tmp_path):
    out = tmp_path / "tracks.csv"
    res = run_vio("track", str(tmp_path / "no_such_capture"), "--out", str(out))
    assert res.returncode == 2
    err = res.stderr.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in res.stderr
    assert err[0].startswith("vio track: error:") and "no_such_capture" in err[0] and "not found" in err[0]
    assert not out.exists()


def test_vio_track_undecodable_image_leaves_no_partial_csv(shifting_capture, tmp_path):
    import shutil

    cap = tmp_path / "broken"
    shutil.copytree(shifting_capture, cap)
    victim = sorted((cap / "mav0" / "cam0" / "data").glob("*.png"))[4]
    victim.write_bytes(b"not a png")
    out = tmp_path / "tracks.csv"
    res = run_vio("track", str(cap), "--out", str(out))
    assert res.returncode == 2
    err = res.stderr.strip().splitlines()
    assert len(err) == 1 and victim.name in err[0] and "decoded" in err[0]
    assert not out.exists() and not list(tmp_path.glob(".tracks.csv*"))


def test_vio_track_bad_tracker_setting_is_one_clear_line(shifting_capture, tmp_path):
    res = run_vio(
        "track", str(shifting_capture), "--out", str(tmp_path / "t.csv"), "--set", "tracker.essential_method=x"
    )
    assert res.returncode == 2
    err = res.stderr.strip().splitlines()
    assert len(err) == 1 and "tracker.essential_method" in err[0]
