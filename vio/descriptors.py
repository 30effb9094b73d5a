"""Binary feature descriptors as two stages share them: the frontend computes them (frontend/descriptors.py), the
backend's landmark atlas compares them (backend/atlas.py). ORB's rotated BRIEF: 256 bits in 32 bytes."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

DESCRIPTOR_BYTES = 32
_POPCOUNT = np.unpackbits(np.arange(256, dtype=np.uint8)[:, None], axis=1).sum(axis=1).astype(np.int32)

# describe(uv_px distorted (N, 2), angle_deg (N,)) -> ((N, 32) uint8 descriptors, (N,) bool described).
# The angle is each point's reference direction in the image, measured like OpenCV's `KeyPoint.angle`.
Describe = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


def hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Bit distances between descriptor sets (N, 32) and (M, 32) uint8 -> (N, M) int32."""
    a = np.asarray(a, np.uint8).reshape(-1, DESCRIPTOR_BYTES)
    b = np.asarray(b, np.uint8).reshape(-1, DESCRIPTOR_BYTES)
    return _POPCOUNT[a[:, None, :] ^ b[None, :, :]].sum(axis=2)
