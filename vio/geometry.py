"""Small rigid-body helpers on 4x4 matrices and quaternions (conversions happen only at file boundaries)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:  # noqa: N802
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def inv_T(T: np.ndarray) -> np.ndarray:  # noqa: N802
    R, t = T[:3, :3], T[:3, 3]
    return make_T(R.T, -R.T @ t)


def quat_wxyz_to_R(q_wxyz: np.ndarray) -> np.ndarray:  # noqa: N802
    q = np.asarray(q_wxyz, float)
    return Rotation.from_quat(q[..., [1, 2, 3, 0]]).as_matrix()


def R_to_quat_wxyz(R: np.ndarray) -> np.ndarray:  # noqa: N802
    """Rotation matrix (or stack) to unit quaternion(s) w-first with w >= 0."""
    q_xyzw = Rotation.from_matrix(R).as_quat()
    q = q_xyzw[..., [3, 0, 1, 2]]
    sign = np.where(q[..., :1] < 0, -1.0, 1.0)
    return q * sign


def skew(v: np.ndarray) -> np.ndarray:
    x, y, z = v
    return np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]], float)


def rotation_angle_deg(R: np.ndarray) -> float:
    c = (np.trace(R) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def sample_triangles(tri: np.ndarray, count: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """`count` points uniformly by area on triangles (F, 3, 3): (points (count, 3), face index (count,)).

    Draws, in order: the faces (`rng.choice` weighted by area), then the barycentric pairs (`rng.uniform`, folded
    into the triangle), so a seed gives the same points wherever this is used."""
    tri = np.asarray(tri, float)
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    face = rng.choice(len(tri), size=count, p=area / area.sum())
    a, b = rng.uniform(size=(2, count))
    fold = a + b > 1.0
    a[fold], b[fold] = 1.0 - a[fold], 1.0 - b[fold]
    t = tri[face]
    return t[:, 0] + a[:, None] * (t[:, 1] - t[:, 0]) + b[:, None] * (t[:, 2] - t[:, 0]), face


def parabolic_peak(y: np.ndarray, k: int) -> float:
    """Sub-sample position of the maximum of samples y at index k (the vertex of the parabola through y[k-1..k+1]),
    in samples from k; 0 at either end or where the three do not bend down."""
    if not 0 < k < len(y) - 1:
        return 0.0
    y0, y1, y2 = float(y[k - 1]), float(y[k]), float(y[k + 1])
    den = y0 - 2.0 * y1 + y2
    return 0.5 * (y0 - y2) / den if den < 0 else 0.0
