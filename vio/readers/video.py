"""Lazy video decoding through OpenCV: frames are decoded on demand, sequential access is the fast path."""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np

from vio.errors import CaptureError

log = logging.getLogger(__name__)

VIDEO_SUFFIXES = (".mp4", ".mov", ".mkv", ".avi", ".m4v", ".3gp", ".webm")


def to_gray(img: np.ndarray) -> np.ndarray:
    """(H, W) uint8 grayscale from a decoded BGR/BGRA/gray image."""
    if img.ndim == 2:
        return img
    if img.shape[2] == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY)
    return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)


class VideoFrames:
    """Decode frame `i` of a video file as (H, W) uint8 grayscale; keeps the decoder open between calls.

    Sequential reads cost one decode each. Going backwards reopens the file; jumping forward grabs the frames in
    between (exact for every codec, unlike container seeking).
    """

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise CaptureError("video file not found", self.path)
        cap = cv2.VideoCapture(str(self.path))
        if not cap.isOpened():
            raise CaptureError("video cannot be opened (unknown container or codec)", self.path)
        self.frame_count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        self.fps = float(cap.get(cv2.CAP_PROP_FPS))
        self.width = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH))
        self.height = int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        cap.release()
        self._cap: cv2.VideoCapture | None = None
        self._next = 0

    def _open(self) -> cv2.VideoCapture:
        cap = cv2.VideoCapture(str(self.path))
        if not cap.isOpened():
            raise CaptureError("video cannot be opened", self.path)
        self._next = 0
        return cap

    def __call__(self, i: int) -> np.ndarray:
        if self._cap is None or i < self._next:
            if self._cap is not None:
                self._cap.release()
            self._cap = self._open()
        while self._next < i:
            if not self._cap.grab():
                raise CaptureError(f"video ends before frame {i} (only {self._next} frames decode)", self.path)
            self._next += 1
        ok, img = self._cap.read()
        if not ok or img is None:
            raise CaptureError(f"frame {i} cannot be decoded (video truncated or corrupt)", self.path)
        self._next += 1
        return to_gray(img)

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None


def find_video(folder: Path, stem: str | None = None) -> Path | None:
    """The video in `folder` (with the given stem, if any); None when there is none."""
    cands = [p for p in sorted(Path(folder).iterdir()) if p.suffix.lower() in VIDEO_SUFFIXES and p.is_file()]
    if stem is not None:
        cands = [p for p in cands if p.stem == stem]
    return cands[0] if cands else None


def match_frame_count(video: VideoFrames, n_times: int, times_path: Path, warnings: list[str]) -> int:
    """Number of usable frames when a timestamp list and a video disagree (the shorter wins, with a warning)."""
    if video.frame_count <= 0:
        return n_times
    if video.frame_count != n_times:
        n = min(video.frame_count, n_times)
        msg = (
            f"{times_path}: {n_times} frame timestamps but the video {video.path.name} has {video.frame_count} "
            f"frames; using the first {n}"
        )
        warnings.append(msg)
        log.warning(msg)
        return n
    return n_times
