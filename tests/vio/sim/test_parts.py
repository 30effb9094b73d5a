"""The part solids (vio.sim.parts, vio.sim.part_shapes): closed, outward, non-degenerate and reproducible meshes
whose features measure what they were defined to be; STL round trips, units, placement and bad input."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest
import trimesh

from vio.errors import PartError, SimulationError
from vio.sim.part_shapes import CUBE_FEATURES_MM, FREEFORM_MM, freeform_top_z
from vio.sim.parts import PART_NAMES, Part, build_part, read_stl_mesh, write_stl

S = 76.2
_PARTS = {name: build_part(name) for name in PART_NAMES}


def _mesh(part: Part) -> trimesh.Trimesh:
    return trimesh.Trimesh(part.vertices_mm, part.faces, process=False)


@pytest.mark.parametrize("name", PART_NAMES)
def test_built_in_is_closed_outward_and_clean(name):
    part, mesh = _PARTS[name], _mesh(_PARTS[name])
    assert part.name == name and part.description and part.dimensions_mm
    assert part.vertices_mm.dtype == np.float64 and part.faces.dtype == np.int64
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert part.volume_mm3() > 0 and part.volume_mm3() == pytest.approx(mesh.volume, rel=1e-12)
    # outward normals: just outside every face (along its normal) is outside the solid, just inside is inside
    centres, normals = mesh.triangles_center, mesh.face_normals
    assert not mesh.contains(centres + 0.01 * normals).any()
    assert mesh.contains(centres - 0.01 * normals).all()
    # no degenerate faces: three distinct vertices, area and smallest height well above float noise
    f = part.faces
    assert ((f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])).all()
    longest = np.linalg.norm(mesh.triangles - np.roll(mesh.triangles, 1, axis=1), axis=2).max(axis=1)
    assert mesh.area_faces.min() > 1e-4 and (2 * mesh.area_faces / longest).min() > 1e-4  # mm^2, mm
    # stands on z = 0, centred on its footprint
    lo, hi = part.bounds_mm()
    assert lo[2] == 0.0 and np.allclose((lo[:2] + hi[:2]) / 2, 0.0, atol=1e-9)


@pytest.mark.parametrize("name", PART_NAMES)
def test_built_in_is_the_same_bytes_every_build(name, tmp_path):
    again = build_part(name)
    header = f"vio part {name}"
    write_stl(tmp_path / "a.stl", _PARTS[name].vertices_mm, _PARTS[name].faces, header)
    write_stl(tmp_path / "b.stl", again.vertices_mm, again.faces, header)
    assert (tmp_path / "a.stl").read_bytes() == (tmp_path / "b.stl").read_bytes()


def test_cube_is_twelve_triangles_of_the_study_cube():
    part = _PARTS["cube"]
    assert part.faces.shape == (12, 3) and part.vertices_mm.shape == (8, 3)
    assert part.volume_mm3() == pytest.approx(S**3, rel=1e-9)
    assert np.allclose(part.bounds_mm(), [[-S / 2, -S / 2, 0], [S / 2, S / 2, S]], rtol=1e-6, atol=0)
    assert part.dimensions_mm == {"x": S, "y": S, "z": S}


@pytest.mark.parametrize("hole", ["hole_through", "hole_blind"])
def test_countersink_angle_and_diameters_measured_on_the_mesh(hole):
    d, v = CUBE_FEATURES_MM, _PARTS["cube_features"].vertices_mm
    r, r_cs = d[f"{hole}_diameter"] / 2, d[f"{hole}_countersink_diameter"] / 2
    rho = np.hypot(v[:, 0] - d[f"{hole}_x"], v[:, 1] - d[f"{hole}_y"])
    near = (rho < r_cs + 0.01) & (v[:, 2] > S - (r_cs - r) - 0.5)  # the rim ring and the cone-to-bore ring
    slope = np.polyfit(v[near, 2], rho[near], 1)[0]
    assert 2 * np.degrees(np.arctan(slope)) == pytest.approx(d["countersink_angle_deg"], abs=0.01)
    assert rho[near].max() == pytest.approx(r_cs, abs=1e-6) and rho[near].min() == pytest.approx(r, abs=1e-6)
    bottom = (rho < r + 0.01) & (v[:, 2] < S - (r_cs - r) - 0.5)
    assert rho[bottom] == pytest.approx(np.full(bottom.sum(), r), abs=1e-6)
    assert v[bottom, 2].min() == pytest.approx(S - d.get(f"{hole}_depth", S), abs=1e-9)


def test_groove_radius_measured_on_the_mesh():
    d, v = CUBE_FEATURES_MM, _PARTS["cube_features"].vertices_mm
    on = (v[:, 0] < S / 2 - 1e-6) & (v[:, 0] > S / 2 - d["groove_radius"] - 0.01) & (np.abs(v[:, 1]) < 6.01)
    rho = np.hypot(v[on, 0] - S / 2, v[on, 1] - d["groove_y"])
    assert on.sum() >= 90 and rho == pytest.approx(np.full(on.sum(), d["groove_radius"]), abs=1e-6)


def test_pocket_and_undercut_slot_are_where_defined():
    d, mesh = CUBE_FEATURES_MM, _mesh(_PARTS["cube_features"])
    px, py = d["pocket_x"], d["pocket_y"]
    slot_y, slot_z = -S / 2 + d["slot_depth_y"] / 2, d["slot_bottom_z"] + d["slot_height_z"] / 2
    probes = [
        ((px, py, S - d["pocket_depth"] + 0.1), False),  # pocket floor
        ((px, py, S - d["pocket_depth"] - 0.1), True),
        ((0.0, slot_y, slot_z), False),  # the slot, under the lip
        ((0.0, slot_y, d["slot_bottom_z"] + d["slot_height_z"] + 0.1), True),  # the lip above it
        ((0.0, slot_y, d["slot_bottom_z"] - 0.1), True),
    ]
    assert mesh.contains([p for p, _ in probes]).tolist() == [inside for _, inside in probes]
    # the overhang self-occludes: looking straight down on the slot floor, the lip is hit first
    hits, _, _ = mesh.ray.intersects_location([[0.0, slot_y, 200.0]], [[0.0, 0.0, -1.0]], multiple_hits=False)
    assert hits[0, 2] == pytest.approx(S)


def test_freeform_top_is_within_0_05_mm_of_the_smooth_surface_and_the_fillet_is_round():
    part, d = _PARTS["freeform"], FREEFORM_MM
    v, tri = part.vertices_mm, part.vertices_mm[part.faces]
    on_top = np.abs(v[:, 2] - freeform_top_z(v[:, 0], v[:, 1])) < 1e-9
    top = tri[on_top[part.faces].all(axis=1)]
    assert len(top) > 4000
    for w in ([1 / 3, 1 / 3, 1 / 3], [0.5, 0.5, 0], [0, 0.5, 0.5], [0.5, 0, 0.5]):
        p = np.einsum("i,fij->fj", w, top)
        assert np.abs(p[:, 2] - freeform_top_z(p[:, 0], p[:, 1])).max() < 0.05
    x0, z0, r = d["step_x"], d["step_z"], d["fillet_radius"]
    fillet = (v[:, 0] > x0 + 1e-6) & (v[:, 0] < x0 + r - 1e-6) & (v[:, 2] > z0 + 1e-6) & (v[:, 2] < z0 + r - 1e-6)
    rho = np.hypot(v[fillet, 0] - (x0 + r), v[fillet, 2] - (z0 + r))
    assert fillet.sum() >= 40 and rho == pytest.approx(np.full(fillet.sum(), r), abs=1e-6)
    assert part.bounds_mm()[:, :2].tolist() == [[-45.0, -35.0], [45.0, 35.0]]


def test_stl_round_trip_binary_and_ascii(tmp_path):
    part = _PARTS["cube_features"]
    path = tmp_path / "p.stl"
    write_stl(path, part.vertices_mm, part.faces, "round trip")
    data = path.read_bytes()
    assert data[:10] == b"round trip" and len(data) == 84 + 50 * len(part.faces)
    records = np.frombuffer(data[84:], dtype=np.dtype([("normal", "<f4", (3,)), ("rest", "V38")]))
    normals = records["normal"]
    assert np.allclose(normals, _mesh(part).face_normals, atol=1e-6)  # stored normals follow the winding
    v, f = read_stl_mesh(path)
    assert v.dtype == np.float64 and f.dtype == np.int64 and f.shape == part.faces.shape
    assert np.array_equal(v[f], part.vertices_mm[part.faces].astype(np.float32))
    ascii_path = tmp_path / "p_ascii.stl"
    ascii_path.write_text(trimesh.Trimesh(part.vertices_mm, part.faces).export(file_type="stl_ascii"))
    v2, f2 = read_stl_mesh(ascii_path)
    assert len(f2) == len(f) and abs(_mesh(Part("a", v2, f2, "", {})).volume - part.volume_mm3()) < 1e-3


def test_user_stl_in_metres_and_in_mm_come_out_the_same_placed_on_its_base(tmp_path):
    part = _PARTS["cube_features"]
    offset_mm = np.array([120.0, -40.0, 300.0])
    write_stl(tmp_path / "bracket_m.stl", (part.vertices_mm + offset_mm) / 1000.0, part.faces, "metres")
    write_stl(tmp_path / "bracket_mm.stl", part.vertices_mm + offset_mm, part.faces, "millimetres")
    before = hashlib.sha256((tmp_path / "bracket_m.stl").read_bytes()).hexdigest()
    in_m = build_part(str(tmp_path / "bracket_m.stl"), units="m")
    in_mm = build_part(tmp_path / "bracket_mm.stl")
    assert hashlib.sha256((tmp_path / "bracket_m.stl").read_bytes()).hexdigest() == before  # file untouched
    assert in_m.name == "bracket_m" and in_mm.name == "bracket_mm"
    assert np.array_equal(in_m.faces, in_mm.faces)
    assert np.allclose(in_m.vertices_mm, in_mm.vertices_mm, atol=1e-3)
    assert np.allclose(in_mm.bounds_mm(), part.bounds_mm(), atol=1e-4)
    assert in_m.volume_mm3() == pytest.approx(part.volume_mm3(), rel=1e-5)


def test_inside_out_stl_is_turned_outward(tmp_path):
    cube = _PARTS["cube"]
    write_stl(tmp_path / "inv.stl", cube.vertices_mm, cube.faces[:, ::-1], "inside out")
    assert build_part(tmp_path / "inv.stl").volume_mm3() == pytest.approx(S**3, rel=1e-6)


def _bad_files(tmp_path):
    cube = _PARTS["cube"]
    (tmp_path / "notes.stl").write_text("these are my notes, not a mesh\n")
    (tmp_path / "empty.stl").write_bytes(b"binary header".ljust(80) + np.uint32(0).tobytes())
    (tmp_path / "empty_ascii.stl").write_text("solid nothing\nendsolid nothing\n")
    write_stl(tmp_path / "open.stl", cube.vertices_mm, cube.faces[:-1], "one triangle missing")
    return {
        "missing.stl": "not found",
        "notes.stl": "not an STL",
        "empty.stl": "no faces",
        "empty_ascii.stl": "no faces",
        "open.stl": "not watertight",
    }


def test_bad_stl_files_give_one_line_errors_naming_the_file(tmp_path):
    for name, problem in _bad_files(tmp_path).items():
        with pytest.raises(PartError) as err:
            build_part(str(tmp_path / name))
        message = str(err.value)
        assert name in message and problem in message and "\n" not in message, message
    with pytest.raises(SimulationError, match="unknown object units 'inch'"):
        build_part(str(tmp_path / "open.stl"), units="inch")
