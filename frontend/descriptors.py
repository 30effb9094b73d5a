"""Oriented binary descriptors at given pixels, for re-identifying map landmarks when a place is seen again.

A KLT track ends when its patch changes too much or leaves the image; when the camera comes back (the next ring
of an orbit, the same corner of a room) the same surface point is detected again as a new track. The backend
re-identifies such a track with the landmark already in the map by comparing these descriptors (ORB's rotated
BRIEF, 256 bits) near where the landmark projects.

The caller supplies each keypoint's orientation: the image direction of gravity at that pixel. Roll and pitch
are well determined in visual-inertial odometry, so gravity-aligned descriptors do not depend on how the phone is
rolled, and they stay more distinctive than ORB's own intensity-centroid orientation (which is noisy on weak
corners). Only the base image is used (one pyramid level); the backend only compares views from similar distances.
"""

from __future__ import annotations

import cv2
import numpy as np

from frontend.tracker import to_gray
from vio.descriptors import DESCRIPTOR_BYTES

PATCH_PX = 31  # ORB's sampling pattern diameter, px


class KeyframeDescriber:
    """Describes points of one keyframe image: `describe(uv_px, angle_deg) -> (descriptors, ok)`."""

    def __init__(self, image: np.ndarray) -> None:
        self.gray = to_gray(image)
        self._orb = cv2.ORB_create(nlevels=1, edgeThreshold=PATCH_PX // 2 + 2, patchSize=PATCH_PX)

    def describe(self, uv_px: np.ndarray, angle_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 32) uint8 descriptors of the points (N, 2) (distorted pixels) at orientations (N,) deg, measured
        like OpenCV's `KeyPoint.angle` (atan2(dv, du) of the reference direction, v down); and (N,) bool, False
        where a point is too close to the border to be described (its row is zeros)."""
        uv_px = np.asarray(uv_px, float).reshape(-1, 2)
        desc = np.zeros((len(uv_px), DESCRIPTOR_BYTES), np.uint8)
        ok = np.zeros(len(uv_px), bool)
        if not len(uv_px):
            return desc, ok
        kps = [
            cv2.KeyPoint(float(u), float(v), float(PATCH_PX), float(a) % 360.0, 0.0, 0, i)
            for i, ((u, v), a) in enumerate(zip(uv_px, np.asarray(angle_deg, float), strict=True))
        ]
        kept, out = self._orb.compute(self.gray, kps)
        if out is not None and len(kept):
            rows = np.array([kp.class_id for kp in kept], np.int64)
            desc[rows], ok[rows] = out, True
        return desc, ok
