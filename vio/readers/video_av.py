"""Lazy video decoding through PyAV (FFmpeg's own decoders: H.264 and HEVC as phones write them).

Frames come out in the sensor's orientation, as the camera calibration describes them: the display rotation a
phone stores for portrait video (the MP4 display matrix) is read (`rotation_deg`) but not applied, unlike OpenCV's
reader, which turns portrait video upright and so no longer matches the calibration.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from vio.errors import CaptureError

log = logging.getLogger(__name__)


class AvVideoFrames:
    """Decode frame `i` (presentation order) of a video file as (H, W) uint8 grayscale, keeping the decoder open.

    The same interface as `vio.readers.video.VideoFrames`: sequential reads cost one decode each; going backwards
    reopens the file; jumping forward decodes the frames in between.
    """

    def __init__(self, path: Path) -> None:
        import av

        self.path = Path(path)
        if not self.path.is_file():
            raise CaptureError("video file not found", self.path)
        try:
            with av.open(str(self.path)) as container:
                if not container.streams.video:
                    raise CaptureError("file holds no video stream", self.path)
                stream = container.streams.video[0]
                self.codec = stream.codec_context.name
                self.width, self.height = int(stream.codec_context.width), int(stream.codec_context.height)
                self.frame_count = int(stream.frames)
                self.fps = float(stream.average_rate or 0.0)
                self.rotation_deg = _rotation(container)
        except av.FFmpegError as exc:
            raise CaptureError(f"video cannot be opened ({exc})", self.path) from None
        self._container = None
        self._frames: Iterator | None = None
        self._next = 0

    def _open(self) -> None:
        import av

        self.close()
        try:
            self._container = av.open(str(self.path))
        except av.FFmpegError as exc:
            raise CaptureError(f"video cannot be opened ({exc})", self.path) from None
        self._frames = self._container.decode(video=0)
        self._next = 0

    def _decode_next(self, i: int):
        import av

        try:
            frame = next(self._frames)
        except StopIteration:
            raise CaptureError(f"video ends before frame {i} (only {self._next} frames decode)", self.path) from None
        except av.FFmpegError as exc:
            raise CaptureError(f"frame {self._next} cannot be decoded ({exc})", self.path) from None
        self._next += 1
        return frame

    def __call__(self, i: int) -> np.ndarray:
        if self._frames is None or i < self._next:
            self._open()
        while self._next < i:
            self._decode_next(i)
        frame = self._decode_next(i)
        return np.ascontiguousarray(frame.to_ndarray(format="gray"))

    def close(self) -> None:
        if self._container is not None:
            self._container.close()
        self._container = None
        self._frames = None


def _rotation(container) -> int:
    """Display rotation of the first video stream, degrees counter-clockwise (0 when none is stored)."""
    for frame in container.decode(video=0):
        return int(round(frame.rotation or 0))
    return 0


def av_available() -> bool:
    try:
        import av  # noqa: F401
    except ImportError:
        return False
    return True
