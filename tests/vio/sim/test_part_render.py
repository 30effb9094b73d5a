"""The parts as the simulator renders them: ray-cast depth against analytic depth, CAD edges against the rendered
full-resolution stills, the CAD files a capture carries, and stills in the capture."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from tests.vio.sim.test_sim_render import _edge_offsets
from vio.info import describe
from vio.readers import open_capture
from vio.sim import rig
from vio.sim.api import load_scenario, simulate
from vio.sim.parts import PART_NAMES, build_part, read_stl_mesh
from vio.sim.render import Renderer, camera_poses

STILLS_TEST_SIZE = (1008, 756)  # half the default stills size: the same geometry, 4x fewer rays


def _volume_mm3(v: np.ndarray, f: np.ndarray) -> float:
    t = v[f]
    return float(np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6.0)


def test_cube_ray_cast_depth_equals_the_analytic_depth():
    sc = load_scenario("orbit", seed=0)
    r = Renderer(sc.scene, sc.camera)
    lo, hi = sc.scene.object_corners_world()[[0, 7]]
    n_hit = 0
    for t_s in (5.0, 22.0, 41.0):
        world_T_cam = camera_poses(sc, np.array([sc.t0_ns + int(t_s * 1e9)]))[0]
        uv = np.stack(np.meshgrid(np.arange(0, 640, 4.0), np.arange(0, 480, 4.0)), -1).reshape(-1, 2)
        xy = sc.camera.undistort_to_normalized(uv)
        d = np.column_stack([xy, np.ones(len(xy))]) @ world_T_cam[:3, :3].T
        o = world_T_cam[:3, 3]
        t, sid, prim = r.trace(o, [d[:, 0].copy(), d[:, 1].copy(), d[:, 2].copy()])
        with np.errstate(divide="ignore"):
            t1 = (np.where(d > 0, lo, hi) - o) / d  # slab entry of the cube
        t_in = t1.max(axis=1)
        on = prim >= 0
        n_hit += int(on.sum())
        assert np.all(sid[on] == r.part_sid)
        depth_err = np.abs(t[on] - t_in[on]) * np.linalg.norm(d[on], axis=1)
        assert depth_err.max() < 2e-6, depth_err.max()  # metres; Embree works in float32 (~1e-7 relative)
    assert n_hit > 500


def _crease_edges(part, min_len_mm: float = 8.0) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Straight CAD edges where the surface turns by more than 30 deg: (a, b) endpoints mm and the two face normals."""
    v, f = part.vertices_mm, part.faces
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    faces_of: dict[tuple[int, int], list[int]] = {}
    for fi, tri in enumerate(f.tolist()):
        for a, b in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0])):
            faces_of.setdefault((min(a, b), max(a, b)), []).append(fi)
    out = []
    for (a, b), fs in faces_of.items():
        if len(fs) == 2 and n[fs[0]] @ n[fs[1]] < np.cos(np.radians(30)) and np.linalg.norm(v[a] - v[b]) >= min_len_mm:
            out.append((v[a], v[b], n[fs[0]], n[fs[1]]))
    return out


@pytest.mark.parametrize("name", PART_NAMES)
def test_cad_edges_land_on_the_rendered_stills(name):
    """Every long straight crease of the CAD seen from a still (both faces turned to the camera, not occluded), is
    located on the rendered still (plain paint, no noise) by its step profile; its offset from the projection with
    the ground-truth pose and calibration is within 0.5 px."""
    sc = load_scenario("orbit", seed=0, part=name, surface="plain", stills_hz=2.0, stills_size=STILLS_TEST_SIZE)
    cam = sc.stills_camera
    r = Renderer(sc.scene, cam)
    T = sc.scene.part.world_T_part
    offsets = []
    for t_s in (21.0, 36.0):  # rings at 20 and 40 deg elevation
        world_T_cam = camera_poses(sc, np.array([sc.t0_ns + int(t_s * 1e9)]), cam)[0]
        img = r.render(world_T_cam, None)
        cam_T_world = np.linalg.inv(world_T_cam)
        c = world_T_cam[:3, 3]
        for a_mm, b_mm, n0, n1 in _crease_edges(sc.scene.part.part):
            a, b = (T[:3, :3] @ (p * 1e-3) + T[:3, 3] for p in (a_mm, b_mm))
            mid = 0.5 * (a + b)
            view = (c - mid) / np.linalg.norm(c - mid)
            if min(view @ (T[:3, :3] @ n0), view @ (T[:3, :3] @ n1)) < 0.25:
                continue  # a face along the edge is seen at a grazing angle, or from behind
            uv_mid = cam.project((cam_T_world[:3, :3] @ mid + cam_T_world[:3, 3])[None])
            seen, _ = r.surface_points(world_T_cam, uv_mid)
            if np.linalg.norm(seen[0] - mid) > 2e-4:
                continue  # occluded by another part of the part
            p0, p1 = (cam_T_world[:3, :3] @ p + cam_T_world[:3, 3] for p in (a, b))
            _, off, _ = _edge_offsets(img, cam, p0, p1)
            if off.size >= 10:
                offsets.append(float(np.median(off)))
    offsets = np.abs(np.asarray(offsets))
    assert offsets.size >= 4, f"only {offsets.size} edges measurable"
    assert np.max(offsets) < 0.5, np.round(np.sort(offsets)[-5:], 3)
    assert np.median(offsets) < 0.15, np.median(offsets)


def test_capture_carries_watertight_cad_and_stills(tmp_path):
    out = simulate("orbit", tmp_path / "c", duration_s=0.6, part="cube_features", stills_hz=2.0,
                   stills_size=STILLS_TEST_SIZE, workers=1)  # fmt: skip
    part = build_part("cube_features")
    v, f = read_stl_mesh(out / "scene" / "cad.stl")  # rejects a mesh that is not watertight
    assert abs(_volume_mm3(v, f) / part.volume_mm3() - 1.0) < 1e-6
    assert np.allclose(v.min(axis=0), part.bounds_mm()[0], atol=1e-4)
    assert np.allclose(v.max(axis=0), part.bounds_mm()[1], atol=1e-4)
    vw, fw = read_stl_mesh(out / "scene" / "object.stl")  # world, metres: outward normals, positive volume
    assert abs(_volume_mm3(vw * 1e3, fw) / part.volume_mm3() - 1.0) < 1e-5
    cap = open_capture(out)
    assert cap.stills is not None and len(cap.stills) == 2 and cap.stills.camera.width == STILLS_TEST_SIZE[0]
    assert cap.stills.t_ns[0] == cap.frame_t_ns[0] + rig.STILLS_OFFSET_NS
    assert cap.stills.load_image(1).shape == STILLS_TEST_SIZE[::-1]
    assert np.allclose(cap.stills.camera.body_T_cam, cap.camera.body_T_cam)
    assert any(line.startswith("stills: 2 images 1008x756") for line in describe(cap, offset=False))  # vio info


def test_cube_cad_is_the_cube():
    v, f = build_part("cube").vertices_mm, build_part("cube").faces
    assert abs(_volume_mm3(v, f) / 76.2**3 - 1.0) < 1e-6


def test_stills_are_deterministic(tmp_path):
    a = simulate("figure8", tmp_path / "a", seed=4, duration_s=0.6, stills_hz=2.0, stills_size=(800, 600), workers=1)
    b = simulate("figure8", tmp_path / "b", seed=4, duration_s=0.6, stills_hz=2.0, stills_size=(800, 600), workers=2)
    files = sorted(p.relative_to(a) for p in (a / "mav0" / "cam1").rglob("*") if p.is_file())
    assert len(files) == 2 + 2  # data.csv, sensor.yaml, two stills
    for rel in files:
        assert hashlib.sha256((a / rel).read_bytes()).digest() == hashlib.sha256((b / rel).read_bytes()).digest()
