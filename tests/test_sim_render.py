"""Rendered images agree with the ground-truth geometry: cube corners measured on the image itself.

The three edges leaving the cube corner nearest the camera are located in the rendered (noisy, distorted) image
along normals to their predicted projections (where the profile crosses the mean of its two sides); straight-line
fits of the offsets, extrapolated to the corner, give the measured corner's displacement from the projection of
the true corner with the ground-truth pose and calibration.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vio.sim.api import load_scenario
from vio.sim.render import Renderer, camera_poses


def _edge_offsets(img: np.ndarray, cam, p0_cam: np.ndarray, p1_cam: np.ndarray) -> tuple[np.ndarray, ...]:
    """Offsets (px, along the predicted normal) of the image step edge at fractions f of a 3D edge."""
    f = np.linspace(0.08, 0.92, 60)
    pts = p0_cam + f[:, None] * (p1_cam - p0_cam)
    uv = cam.project(pts)
    tangent = cam.project(pts + 1e-4 * (p1_cam - p0_cam)) - uv
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    normal = np.column_stack([-tangent[:, 1], tangent[:, 0]])
    s = np.arange(-2.2, 2.2001, 0.05)
    xy = (uv[:, None, :] + s[None, :, None] * normal[:, None, :]).astype(np.float32)
    prof = cv2.remap(img.astype(np.float32), xy[..., 0], xy[..., 1], cv2.INTER_LINEAR)
    left = np.median(prof[:, (s < -0.9) & (s > -1.5)], axis=1)
    right = np.median(prof[:, (s > 0.9) & (s < 1.5)], axis=1)
    mid = 0.5 * (left + right)[:, None]
    sign = np.sign(prof - mid)
    cross_f, cross_off = [], []
    for i in range(len(f)):
        if abs(right[i] - left[i]) < 15.0:
            continue  # too little contrast across the edge here
        idx = np.flatnonzero(sign[i, :-1] * sign[i, 1:] < 0)
        if idx.size == 0:
            continue
        j = idx[np.argmin(np.abs(s[idx]))]
        y0, y1 = prof[i, j] - mid[i, 0], prof[i, j + 1] - mid[i, 0]
        cross_f.append(f[i])
        cross_off.append(s[j] + (s[j + 1] - s[j]) * y0 / (y0 - y1))
    return np.asarray(cross_f), np.asarray(cross_off), normal


def _fit_start(f: np.ndarray, off: np.ndarray) -> float:
    """Robust straight-line fit of the offsets over f, evaluated at the edge's start f = 0."""
    keep = np.ones(f.size, bool)
    for _ in range(3):
        assert keep.sum() >= 12, "too few edge samples with contrast"
        a, b = np.polyfit(f[keep], off[keep], 1)
        res = np.abs(off - (a * f + b))
        keep = res < max(3.0 * np.median(res[keep]), 0.1)
    return float(b)


@pytest.mark.parametrize("t_s", [22.0, 37.0, 47.0, 52.0])
def test_cube_corners_land_on_rendered_corners(t_s):
    """The cube corner nearest the camera (where three visible faces meet) from the three edges leaving it."""
    sc = load_scenario("orbit", seed=0)
    renderer = Renderer(sc.scene, sc.camera)
    world_T_cam = camera_poses(sc, np.array([sc.t0_ns + int(t_s * 1e9)]))[0]
    img = renderer.render(world_T_cam, np.random.default_rng(1))
    corners = sc.scene.object_corners_world()
    near = int(np.argmin(np.linalg.norm(corners - world_T_cam[:3, 3], axis=1)))
    lo, hi = corners[0], corners[7]
    o = world_T_cam[:3, 3]
    # The camera is outside the three face planes at that corner, so all three faces and edges are visible.
    assert all((o[k] > hi[k]) if (near >> k) & 1 else (o[k] < lo[k]) for k in range(3))
    cam_T_world = np.linalg.inv(world_T_cam)
    p_cam = corners @ cam_T_world[:3, :3].T + cam_T_world[:3, 3]
    rows, rhs = [], []
    for k in range(3):
        f, off, normal = _edge_offsets(img, sc.camera, p_cam[near], p_cam[near ^ (1 << k)])
        keep = f < 0.8
        rows.append(normal[0])
        rhs.append(_fit_start(f[keep], off[keep]))
    delta, *_ = np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)
    assert np.linalg.norm(delta) < 0.5, (delta, rhs)
