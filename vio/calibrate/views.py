"""The views of a camera calibration: the board found in a list of images (or the images of a folder, or of an
ASL capture's `mav0/cam0/data/`), or in frames picked from a video.

From a video, every `stride`-th frame is searched for the board; frames whose board is blurred (sharpness below
half the median) are dropped. From a video or from more than `max_views` images, at most `max_views` views are
kept, picked greedily for coverage: each next view is the
one whose board position, size and tilt in the image differ most from those already picked.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vio.calibrate.board import BoardDetector, Detection
from vio.errors import CalibrationError

log = logging.getLogger(__name__)

VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".m4v", ".webm", ".3gp")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
MAX_VIDEO_CANDIDATES = 400  # frames searched for the board in a video (evenly spread)
BLUR_FRACTION = 0.5  # a video frame sharper than this fraction of the median detection is kept


@dataclass(frozen=True)
class View:
    """One image in which the board was found."""

    name: str  # file name, or `video.mp4#frame` for a video frame
    detection: Detection
    sharpness: float  # variance of the Laplacian over the board's bounding box, grey levels^2


@dataclass
class ViewSet:
    """The views found, the images rejected (with the reason), the image size and the video's frame rate."""

    views: list[View]
    rejected: list[tuple[str, str]] = field(default_factory=list)  # (name, reason)
    image_size: tuple[int, int] = (0, 0)  # (width, height) px
    rate_hz: float | None = None  # the video's frame rate; None for still images


def _sharpness(gray: np.ndarray, uv: np.ndarray) -> float:
    import cv2

    x0, y0 = np.floor(uv.min(axis=0)).astype(int)
    x1, y1 = np.ceil(uv.max(axis=0)).astype(int) + 1
    roi = gray[max(y0, 0) : max(y1, 1), max(x0, 0) : max(x1, 1)]
    return float(cv2.Laplacian(roi, cv2.CV_64F).var()) if roi.size else 0.0


def _image_frames(paths: Sequence[Path], rejected: list[tuple[str, str]]) -> Iterator[tuple[str, np.ndarray]]:
    import cv2

    for path in paths:
        if not path.is_file():
            raise CalibrationError(f"{path}: image not found")
        gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if gray is None:
            rejected.append((path.name, "not a readable image"))
            continue
        yield path.name, gray


def _video_frames(path: Path, stride: int | None) -> Iterator[tuple[str, np.ndarray]]:
    import cv2

    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise CalibrationError(f"{path}: cannot open the video (is OpenCV built with a decoder for it?)")
    n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
    step = stride or max(1, int(np.ceil(n / MAX_VIDEO_CANDIDATES)))
    k = 0
    try:
        while True:
            ok = cap.grab()
            if not ok:
                break
            if k % step == 0:
                ok, frame = cap.retrieve()
                if ok:
                    gray = frame if frame.ndim == 2 else cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
                    yield f"{path.name}#{k}", gray
            k += 1
    finally:
        cap.release()
    if k == 0:
        raise CalibrationError(f"{path}: the video has no readable frames")


def _pose_descriptor(uv: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Where the board is in the image (centre, scale) and how it is tilted (principal axes ratio)."""
    w, h = size
    centre = uv.mean(axis=0) / np.array([w, h])
    d = uv - uv.mean(axis=0)
    ev = np.sqrt(np.maximum(np.linalg.eigvalsh(d.T @ d / len(d)), 1e-9))
    scale = 2.0 * np.sqrt(ev.prod()) / np.sqrt(w * h)
    return np.array([centre[0], centre[1], scale, 0.5 * np.log(ev[1] / ev[0])])


def pick_for_coverage(views: list[View], size: tuple[int, int], max_views: int) -> list[View]:
    """At most `max_views` views: the sharpest first, then each the farthest (in pose) from those picked."""
    if len(views) <= max_views:
        return views
    desc = np.array([_pose_descriptor(v.detection.uv, size) for v in views])
    sharp = np.array([v.sharpness for v in views])
    chosen = [int(np.argmax(sharp))]
    dist = np.linalg.norm(desc - desc[chosen[0]], axis=1)
    while len(chosen) < max_views:
        i = int(np.argmax(dist + 1e-6 * sharp / sharp.max()))
        chosen.append(i)
        dist = np.minimum(dist, np.linalg.norm(desc - desc[i], axis=1))
        dist[chosen] = -1.0
    return [views[i] for i in sorted(chosen)]


def _expand(paths: list[Path]) -> list[Path]:
    """A folder stands for its images (an ASL capture folder for `mav0/cam0/data/`), sorted by name."""
    out: list[Path] = []
    for path in paths:
        if path.is_dir():
            for sub in (path / "mav0" / "cam0" / "data", path / "cam0" / "data", path / "data"):
                if sub.is_dir():
                    path = sub
                    break
            found = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
            if not found:
                raise CalibrationError(f"{path}: folder holds no images ({', '.join(IMAGE_SUFFIXES)})")
            out += found
        else:
            out.append(path)
    return out


def find_views(
    inputs: Sequence[str | Path], detector: BoardDetector, max_views: int = 40, stride: int | None = None
) -> ViewSet:
    """The board in each image of `inputs`, or in frames of one video (see the module docstring).

    CalibrationError when the images differ in size or the board is found in no image.
    """
    paths = _expand([Path(p) for p in inputs])
    if not paths:
        raise CalibrationError("no images given")
    rejected: list[tuple[str, str]] = []
    video = len(paths) == 1 and paths[0].suffix.lower() in VIDEO_SUFFIXES
    if video and not paths[0].is_file():
        raise CalibrationError(f"{paths[0]}: video not found")
    frames = _video_frames(paths[0], stride) if video else _image_frames(paths, rejected)
    views: list[View] = []
    size: tuple[int, int] | None = None
    n_frames = 0
    for name, gray in frames:
        n_frames += 1
        this = (int(gray.shape[1]), int(gray.shape[0]))
        if size is None:
            size = this
        elif this != size:
            raise CalibrationError(f"{name}: image is {this[0]}x{this[1]}, the first was {size[0]}x{size[1]}")
        det = detector.detect(gray)
        if det is None:
            rejected.append((name, "board not found"))
            continue
        views.append(View(name, det, _sharpness(gray, det.uv)))
    if not views:
        where = paths[0] if video else f"{len(paths)} image(s)"
        raise CalibrationError(f"{where}: no {detector.board.describe()} found in any of {n_frames} view(s)")
    rate_hz = None
    if video:
        import cv2

        cap = cv2.VideoCapture(str(paths[0]))
        rate_hz = float(cap.get(cv2.CAP_PROP_FPS)) or None
        cap.release()
        median = float(np.median([v.sharpness for v in views]))
        keep = [v for v in views if v.sharpness >= BLUR_FRACTION * median]
        rejected += [
            (v.name, f"blurred (sharpness {v.sharpness:.0f} < {BLUR_FRACTION:g} x median {median:.0f})")
            for v in views
            if v.sharpness < BLUR_FRACTION * median
        ]
        picked = pick_for_coverage(keep, size, max_views)
        names = {v.name for v in picked}
        rejected += [(v.name, "not needed for coverage") for v in keep if v.name not in names]
        views = picked
    elif len(views) > max_views:  # e.g. every frame of a capture: neighbours add little but time
        picked = pick_for_coverage(views, size, max_views)
        names = {v.name for v in picked}
        rejected += [(v.name, "not needed for coverage") for v in views if v.name not in names]
        views = picked
    log.info("board found in %d of %d view(s)", len(views), n_frames)
    return ViewSet(views, rejected, size, rate_hz)
