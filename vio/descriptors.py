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
    """Bit distances between descriptor sets (N, 32) and (M, 32) uint8 -> (N, M) int64 (four 64-bit words per
    descriptor, each word's bits counted by numpy: 5x faster than a byte table)."""
    a = np.ascontiguousarray(np.asarray(a, np.uint8).reshape(-1, DESCRIPTOR_BYTES))
    b = np.ascontiguousarray(np.asarray(b, np.uint8).reshape(-1, DESCRIPTOR_BYTES))
    if not hasattr(np, "bitwise_count"):  # numpy < 2.0: a table of the bits set in each byte
        return _POPCOUNT[a[:, None, :] ^ b[None, :, :]].sum(axis=2, dtype=np.int64)
    a, b = a.view(np.uint64), b.view(np.uint64)
    return np.bitwise_count(a[:, None, :] ^ b[None, :, :]).sum(axis=2, dtype=np.int64)
