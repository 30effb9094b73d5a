"""The tracking frontend over a capture's frames, shared by `vio run`'s two ways of running it (in its own process,
or in `vio.track_worker` beside the estimator): decode and check each image, track, measure the tracks' image
velocities, and sample each new track's colour."""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from frontend.track_velocity import TrackVelocity
from vio.capture import Capture
from vio.config import Config
from vio.errors import CaptureError
from vio.records import FeatureTracks, Frame


def image_of(cap: Capture, i: int) -> np.ndarray:
    """Frame i's image, checked against the calibration's size (CaptureError when it cannot be used)."""
    image = cap.load_image(i)
    cam = cap.camera
    if cam is not None and image.shape[:2] != (cam.height, cam.width):
        h, w = image.shape[:2]
        raise CaptureError(f"frame {i} is {w}x{h}, the calibration is for {cam.width}x{cam.height}", cap.root)
    return image


def tracked_frames(cap: Capture, cfg: Config, stop: int, prefetch: int = 0) -> Iterator[tuple[str, Any]]:
    """The OpenCV tracker over frames 0..stop-1: ("frame", (frame, tracks, track ages in frames, the new tracks'
    colours (ids, RGB), whether the frame is a keyframe)) per frame (the tracker picks the keyframes:
    `frontend.keyframes` on its tracks), or ("skip", (t_ns, frame index, reason)) for a frame whose image fails to
    decode (or has the wrong size). With `prefetch` > 0 a thread decodes the images up to that many frames ahead and
    computes what corner detection needs from the image alone (`frontend.detection.corner_response`), the same
    numbers the tracker would compute (`ahead`); only for a capture that nothing else reads meanwhile (the
    tracker's own process)."""
    from frontend.detection import corner_response
    from frontend.tracker import FeatureTracker, to_gray

    velocity = TrackVelocity()  # each track's image velocity (the estimator's rolling-shutter and offset terms)
    tracker = FeatureTracker(cap.camera, cfg.tracker, cfg.keyframes)
    colours = TrackColours()

    def load(i: int) -> tuple[np.ndarray, Any]:  # what does not depend on the tracks, ahead in the thread
        image = image_of(cap, i)
        try:
            return image, corner_response(to_gray(image), cfg.tracker)
        except Exception:  # noqa: BLE001 - the tracker meets the same problem at its frame and reports it there
            return image, None

    items = images(cap, stop) if prefetch <= 0 else ahead(load, stop, prefetch)
    for i, item in enumerate(items):
        t_ns = int(cap.frame_t_ns[i])
        if isinstance(item, CaptureError):
            yield "skip", (t_ns, i, str(item))
            continue
        image, response = (item, None) if prefetch <= 0 else item
        frame = Frame(t_ns, 0, image)
        tracks = velocity.add(tracker.track(frame, response))
        yield "frame", (frame, tracks, tracker.ages(), colours.see(frame, tracks), bool(tracker.keyframe))


def images(cap: Capture, stop: int, prefetch: int = 0) -> Iterator[np.ndarray | CaptureError]:
    """Frame images 0..stop-1 in order (`image_of`), the CaptureError in place of one that cannot be used; with
    `prefetch` > 0 decoded ahead in a thread (`ahead`)."""
    return ahead(lambda i: image_of(cap, i), stop, prefetch)


def ahead(load: Callable[[int], Any], stop: int, prefetch: int = 0) -> Iterator[Any]:
    """`load(i)` for i in 0..stop-1, in order, the CaptureError in place of an item that raised one. With `prefetch`
    > 0 a thread computes them up to `prefetch` items ahead: OpenCV releases the GIL in its decoders and filters, so
    that work uses a core the tracker leaves idle (the estimator's, while it waits for tracks). Any other error is
    raised here, at its item."""
    if prefetch <= 0:
        for i in range(stop):
            try:
                yield load(i)
            except CaptureError as exc:
                yield exc
        return
    ready: queue.Queue[Any] = queue.Queue(maxsize=prefetch)
    stopped = threading.Event()

    def decode() -> None:
        for i in range(stop):
            try:
                item: Any = load(i)
            except CaptureError as exc:
                item = exc
            except BaseException as exc:  # noqa: BLE001 - handed to the consumer, raised there
                item = _Failed(exc)
            while not stopped.is_set():
                try:
                    ready.put(item, timeout=0.1)
                    break
                except queue.Full:
                    continue
            if stopped.is_set() or isinstance(item, _Failed):
                return

    threading.Thread(target=decode, name="vio-ahead", daemon=True).start()
    try:
        for _ in range(stop):
            item = ready.get()
            if isinstance(item, _Failed):
                raise item.error
            yield item
    finally:
        stopped.set()


class _Failed:
    """An unexpected error in the thread of `ahead`, carried to the consumer."""

    def __init__(self, error: BaseException) -> None:
        self.error = error


class TrackColours:
    """The image colour of each track where it was first seen (grey images give grey), for landmarks.ply.

    Bounded memory: a tracker numbers its tracks 0, 1, 2, ..., so the colours sit in one array indexed by track
    id (RGB and a "seen" byte, 4 bytes a track; a dict of arrays took about 75); ids outside `_ARRAY_IDS` (tracks
    read from a file) go to a dict."""

    _ARRAY_IDS = 1 << 24

    def __init__(self) -> None:
        self._table = np.zeros((0, 4), np.uint8)  # track id -> R, G, B, seen
        self._rgb: dict[int, np.ndarray] = {}  # ids outside the table's range

    def _known(self, ids: np.ndarray) -> np.ndarray:
        ids = np.asarray(ids, np.int64)
        inside = (ids >= 0) & (ids < min(len(self._table), self._ARRAY_IDS))
        known = np.zeros(ids.shape, bool)
        known[inside] = self._table[ids[inside], 3] > 0
        for i in np.flatnonzero(~inside).tolist():
            known[i] = int(ids[i]) in self._rgb
        return known

    def see(self, frame: Frame, tracks: FeatureTracks) -> tuple[np.ndarray, np.ndarray]:
        """Sample the new tracks' colours in `frame`; returns them: (ids (M,), RGB (M, 3) uint8)."""
        new = np.flatnonzero(~self._known(tracks.ids))
        if not new.size:
            return np.zeros(0, np.int64), np.zeros((0, 3), np.uint8)
        image, uv = frame.image, tracks.uv[new]
        h, w = image.shape[:2]
        u = np.clip(np.rint(uv[:, 0]).astype(int), 0, w - 1)
        v = np.clip(np.rint(uv[:, 1]).astype(int), 0, h - 1)
        px = image[v, u]
        rgb = np.repeat(px[:, None], 3, axis=1) if px.ndim == 1 else px[:, ::-1]
        ids = tracks.ids[new]
        self.add(ids, rgb)
        return ids, np.asarray(rgb, np.uint8)

    def add(self, ids: np.ndarray, rgb: np.ndarray) -> None:
        """Colours sampled by `see` (in the tracker's process, when it runs apart); a track keeps its first."""
        ids, rgb = np.asarray(ids, np.int64).reshape(-1), np.asarray(rgb, np.uint8).reshape(-1, 3)
        fresh = ~self._known(ids)
        fresh[fresh] = _first_of_each(ids[fresh])  # a track twice in one call keeps its first colour
        inside = (ids >= 0) & (ids < self._ARRAY_IDS)
        put = fresh & inside
        if put.any():
            top = int(ids[put].max()) + 1
            if top > len(self._table):
                grown = np.zeros((min(max(top, 2 * len(self._table), 1024), self._ARRAY_IDS), 4), np.uint8)
                grown[: len(self._table)] = self._table
                self._table = grown
            self._table[ids[put], :3] = rgb[put]
            self._table[ids[put], 3] = 1
        for i in np.flatnonzero(fresh & ~inside).tolist():
            self._rgb[int(ids[i])] = rgb[i].copy()

    def of(self, track_ids: np.ndarray) -> np.ndarray:
        """(M, 3) uint8 RGB of tracks (light grey for tracks never seen in an image)."""
        ids = np.asarray(track_ids, np.int64).reshape(-1)
        out = np.full((ids.size, 3), 200, np.uint8)
        known = self._known(ids)
        inside = known & (ids >= 0) & (ids < len(self._table))
        out[inside] = self._table[ids[inside], :3]
        for i in np.flatnonzero(known & ~inside).tolist():
            out[i] = self._rgb[int(ids[i])]
        return out


def _first_of_each(ids: np.ndarray) -> np.ndarray:
    """(N,) True at the first occurrence of each id."""
    first = np.zeros(ids.size, bool)
    first[np.unique(ids, return_index=True)[1]] = True
    return first
