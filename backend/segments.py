"""Track segments: one long KLT track may become several landmarks.

KLT tracks drift by pixels over seconds (measured on the eqvio tracks against the EuRoC ground truth: median
0.4 px within 10 frames, 3 px after 40). A new segment of a track, a new landmark, starts when a view disagrees
with the track's landmark (`split`) or, optionally, every `max_track_keyframes` views. Landmark ids encode
(track, segment) with `backend.keys.landmark_id`.
"""

from __future__ import annotations

import numpy as np

from backend.keys import landmark_id, segment_of


class TrackSegments:
    """The current segment of every track and the number of views in it."""

    def __init__(self, max_track_keyframes: int) -> None:
        self.max_views = max_track_keyframes  # 0: segments only end on drift
        self._segments: dict[int, tuple[int, int]] = {}  # track id -> (segment, views in the segment)
        self._older: dict[int, tuple[int, int]] = {}  # the same, of tracks not seen since the last `forget_unseen`
        self.num_splits = 0

    def _get(self, j: int) -> tuple[int, int] | None:
        entry = self._segments.get(j)
        if entry is None:
            entry = self._older.pop(j, None)
        return entry

    def forget_unseen(self) -> None:
        """Bounded memory: forget the tracks not seen since the previous call (a KLT track that is lost never
        comes back: its id is not reused). Call it less often than a live track is seen."""
        self._older, self._segments = self._segments, {}

    def landmark_ids(self, track_ids: np.ndarray) -> np.ndarray:
        """(N,) landmark ids of keyframe observations of the tracks `track_ids` (N,), counting one view each."""
        n = self.max_views
        out = np.asarray(track_ids, np.int64).copy()
        for i, j in enumerate(out.tolist()):
            seg, count = self._get(j) or (0, 0)
            if 0 < n <= count:
                seg, count = seg + 1, 0
            self._segments[j] = (seg, count + 1)
            out[i] = landmark_id(j, seg)
        return out

    def split(self, track_id: int, current: int) -> int:
        """Start a new segment of `track_id`, whose latest view belonged to landmark `current`; returns its id."""
        seg, _ = self._get(track_id) or (segment_of(current), 0)
        self._segments[track_id] = (seg + 1, 1)
        self.num_splits += 1
        return landmark_id(track_id, seg + 1)
