"""`vio measure`: primitives fitted on the simulator's parts (sampled CAD + noise) give the nominal dimensions."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from vio.errors import ModelError
from vio.model.commands import measure_file
from vio.model.measure import measure
from vio.model.measure_report import Dimension, inspection_report, report_dict
from vio.model.primitives import sample_surface
from vio.sim.parts import build_part, write_stl

NOISE_MM = 0.05


def _scan(name: str, count: int, seed: int = 1, scale=(1.0, 1.0, 1.0)):
    """(points mm with NOISE_MM Gaussian noise per axis, exact outward normals, CAD mesh), all in the part frame."""
    part = build_part(name)
    cad = trimesh.Trimesh(part.vertices_mm, part.faces, process=False)
    rng = np.random.default_rng(seed)
    points, normals, _ = sample_surface(part.vertices_mm, part.faces, count, rng)
    return points * np.asarray(scale) + rng.normal(0.0, NOISE_MM, points.shape), normals, cad


def _find(dims: list[Dimension], name: str) -> Dimension:
    hits = [d for d in dims if d.name == name]
    assert len(hits) == 1, f"{name!r} not in {[d.name for d in dims]}"
    return hits[0]


@pytest.fixture(scope="module")
def cube():
    return _scan("cube", 20000)


@pytest.fixture(scope="module")
def cube_features_dims():
    points, normals, cad = _scan("cube_features", 200000)
    return measure(points, normals, "auto", cad, scale_sigma_rel=0.003)


def test_cube_box_distances_and_uncertainty_grows_with_scale_sigma(cube):
    points, normals, _ = cube
    first = measure(points, normals, "box", scale_sigma_rel=0.003)
    second = measure(points, normals, "box", scale_sigma_rel=0.006, u_model_mm=0.1)
    assert [d.kind for d in first] == ["distance"] * 3 + ["length"] * 3
    for d, e in zip(first, second, strict=True):
        assert d.measured == pytest.approx(76.2, abs=0.01) and e.measured == d.measured
        assert d.nominal is None and d.deviation is None and d.units == "mm"
        assert d.components["u_fit"] < 0.005 and d.components["u_model"] == 0.0
        assert d.components["u_scale"] == pytest.approx(0.003 * d.measured)
        assert d.U95 == pytest.approx(1.96 * np.hypot(d.components["u_fit"], 0.003 * d.measured))
        assert d.U95 == pytest.approx(76.2 * 0.003 * 1.96, rel=0.01)  # 0.45 mm: the scale dominates
        assert e.U95 == pytest.approx(1.96 * np.sqrt(e.components["u_fit"] ** 2 + (0.006 * e.measured) ** 2 + 0.1**2))


def test_anisotropic_box_is_measured_as_such_with_and_without_cad(cube):
    points, normals, cad = _scan("cube", 20000, seed=2, scale=np.array([76.0, 76.3, 76.5]) / 76.2)
    for dims in (measure(points, normals, "box"), measure(points, None, "box", cad)):
        distances, lengths = dims[:3], dims[3:]
        for d, want in zip(distances + lengths, [76.0, 76.3, 76.5] * 2, strict=True):
            assert d.measured == pytest.approx(want, abs=0.01), d.name
    for d, want in zip(dims, [-0.2, 0.1, 0.3] * 2, strict=True):  # with the CAD: nominal 76.2, deviations
        assert d.nominal == pytest.approx(76.2, abs=1e-3) and d.deviation == pytest.approx(want, abs=0.01)
    assert dims[0].name.startswith("box x") and dims[2].name.startswith("box z")


def test_box_without_its_base_and_with_a_closure_base(cube):
    points, normals, _ = cube
    above = points[:, 2] > 0.5  # no points on the base: the height comes from the side faces
    dims = measure(points[above], normals[above], "box")
    assert len(dims) == 3 and "missing" in dims[2].note
    assert dims[2].measured == pytest.approx(76.2 - 0.5, abs=0.05)
    closed = measure(points, normals, "box", base_is_closure=True)
    assert "closure" in closed[2].note and "closure" not in closed[0].note


def test_cube_features_with_cad_countersinks_bores_groove_and_pocket(cube_features_dims):
    dims = cube_features_dims
    for x, bore, countersink in ((-20.0, 8.0, 16.0), (20.0, 10.0, 20.0)):
        where = f"along z at x={x:.2f} y=20.00"
        angle = _find(dims, f"cone {where} included angle")
        assert angle.kind == "angle" and angle.units == "deg" and angle.components["u_scale"] == 0.0
        assert angle.measured == pytest.approx(90.0, abs=0.5) and angle.nominal == pytest.approx(90.0, abs=0.05)
        assert _find(dims, f"cone {where} diameter").measured == pytest.approx(countersink, abs=0.05)
        d = _find(dims, f"cylinder {where}")
        assert d.kind == "diameter" and d.measured == pytest.approx(bore, abs=0.05)
        assert abs(d.deviation) < 0.01 and d.U95 > 1.96 * 0.003 * bore
    groove = _find(dims, "cylinder along z at x=38.10 y=0.00")
    assert groove.kind == "radius" and groove.measured == pytest.approx(6.0, abs=0.05)
    pocket_and_slot = {
        "+x@-15.00 to -x@15.00": 30.0,
        "+y@-25.00 to -y@-11.00": 14.0,
        "+z@76.20 to +z@66.20": 10.0,
        "+z@76.20 to +z@46.20": 30.0,
        "+z@20.00 to -z@35.00": 15.0,
        "-y@-38.10 to -y@-26.10": 12.0,
        "-z@0.00 to +z@76.20": 76.2,
    }
    for name, want in pocket_and_slot.items():
        d = _find(dims, name)
        assert d.measured == pytest.approx(want, abs=0.02) and d.nominal == pytest.approx(want, abs=1e-3)
    assert "depth" in _find(dims, "+z@76.20 to +z@66.20").note


def test_cube_features_without_cad_finds_the_faces_bores_and_groove():
    points, normals, _ = _scan("cube_features", 60000, seed=3)
    dims = measure(points, normals, "auto")
    assert _find(dims, "-x@-38.10 to +x@38.10").measured == pytest.approx(76.2, abs=0.01)
    bores = sorted(d.measured for d in dims if d.kind == "diameter")
    assert bores == pytest.approx([8.0, 10.0], abs=0.05)
    assert [d.measured for d in dims if d.kind == "radius"] == pytest.approx([6.0], abs=0.05)
    assert all(d.nominal is None for d in dims)


def test_freeform_fillet_radius_length_width_and_step():
    points, normals, cad = _scan("freeform", 50000)
    dims = measure(points, normals, "auto", cad)
    fillet = [d for d in dims if d.kind == "radius"]
    assert len(fillet) == 1 and fillet[0].measured == pytest.approx(6.0, abs=0.05)
    assert fillet[0].name.startswith("cylinder along y")
    assert _find(dims, "-x@-45.00 to +x@45.00").measured == pytest.approx(90.0, abs=0.01)
    assert _find(dims, "-y@-35.00 to +y@35.00").measured == pytest.approx(70.0, abs=0.01)
    assert _find(dims, "+z@16.00 to -z@0.00").measured == pytest.approx(16.0, abs=0.01)


def test_no_box_like_structure_is_one_clear_line():
    sphere = trimesh.creation.icosphere(3, radius=40.0)
    rng = np.random.default_rng(0)
    points, normals, _ = sample_surface(sphere.vertices, sphere.faces, 10000, rng)
    points += rng.normal(0.0, NOISE_MM, points.shape)
    for shape in ("box", "auto"):
        with pytest.raises(ModelError) as err:
            measure(points, normals, shape)
        assert "\n" not in str(err.value) and ("box-like" in str(err.value) or "no measurable" in str(err.value))
    with pytest.raises(ModelError, match="unknown shape"):
        measure(points, normals, "sphere")
    with pytest.raises(ModelError, match="at least 100"):
        measure(points[:10], normals[:10], "box")


def test_report_markdown_and_json(cube):
    points, normals, cad = cube
    dims = measure(points, normals, "box", cad, scale_sigma_rel=0.003)
    text = inspection_report(dims, title="cube", notes=("scale from the factor graph",))
    assert text.startswith("# cube") and text.count("\n| ") == len(dims) + 1 and "76.200" in text
    assert "scale from the factor graph" in text
    data = json.loads(json.dumps(report_dict(dims)))
    assert data["k"] == 1.96 and data["dimensions"][0]["U95"] == pytest.approx(dims[0].U95)
    assert set(data["dimensions"][0]) >= {"name", "kind", "nominal", "measured", "deviation", "components"}


def _model_from_a_run(tmp_path, status: str | None, reasons: list[str]):
    """part.stl (the cube, mm) with the model.json `vio model` writes beside it and the run.json it names."""
    part = build_part("cube")
    folder = tmp_path / "model"
    write_stl(folder / "part.stl", part.vertices_mm, part.faces, "vio part model, mm")
    (folder / "run").mkdir()
    (folder / "run" / "run.json").write_text(json.dumps({"status": status, "reasons": reasons}))
    meta = {"run": str(folder / "run"), "run_status": status, "scale_sigma_rel": 0.002, "warnings": []}
    (folder / "model.json").write_text(json.dumps(meta))
    return folder / "part.stl"


def test_dimensions_from_a_degraded_run_are_flagged_everywhere(tmp_path, caplog):
    reason = "tracking lost 2.0-4.0 s: 3 tracked features (< 20)"
    model = _model_from_a_run(tmp_path, "degraded", [reason])
    with caplog.at_level("WARNING", logger="vio.model.commands"):
        text = measure_file(model, "box", out_dir=tmp_path / "out")
    assert any("degraded" in r.getMessage() and reason in r.getMessage() for r in caplog.records)
    md = (tmp_path / "out" / "measure.md").read_text()
    assert md == text
    head, table = md.split("| # |", 1)
    assert "**Warning:**" in head and "degraded" in head and reason in head  # above the table
    rows = [line for line in table.splitlines()[2:] if line.startswith("| ")]
    assert len(rows) == 6 and all("DEGRADED RUN" in row for row in rows)  # 3 distances, 3 edge lengths
    data = json.loads((tmp_path / "out" / "measure.json").read_text())
    assert data["run_status"] == "degraded" and reason in data["warnings"][0]
    assert all(d["flags"] == ["degraded run"] for d in data["dimensions"]) and len(data["dimensions"]) == 6
    assert data["dimensions"][0]["components"]["u_scale"] > 0  # the scale sigma still comes from model.json


def test_dimensions_from_an_ok_run_carry_no_flag(tmp_path):
    model = _model_from_a_run(tmp_path, "ok", [])
    measure_file(model, "box", out_dir=tmp_path / "out")
    data = json.loads((tmp_path / "out" / "measure.json").read_text())
    assert data["run_status"] == "ok" and data["warnings"] == []
    assert all(d["flags"] == [] for d in data["dimensions"])
    assert "Warning" not in (tmp_path / "out" / "measure.md").read_text()


def test_a_model_from_a_failed_run_is_refused_and_nothing_written(tmp_path):
    model = _model_from_a_run(tmp_path, "failed", ["no estimate: initialisation never succeeded"])
    with pytest.raises(ModelError, match=r"part\.stl: the run it was built from failed \(no estimate") as err:
        measure_file(model, "box", out_dir=tmp_path / "out")
    assert "\n" not in str(err.value) and not (tmp_path / "out").exists()
    model = _model_from_a_run(tmp_path / "killed", "running", [])  # `vio run` killed before it wrote its status
    with pytest.raises(ModelError, match=r"did not finish \(status 'running'\)"):
        measure_file(model, "box", out_dir=tmp_path / "out")
    (model.with_name("model.json")).write_text("{not json")
    with pytest.raises(ModelError, match=r"model\.json: not a readable JSON file"):
        measure_file(model, "box", out_dir=tmp_path / "out")


def test_an_uncertainty_that_is_not_a_finite_non_negative_number_is_refused(tmp_path):
    model = _model_from_a_run(tmp_path, "ok", [])
    for kwargs in ({"scale_sigma_rel": float("nan")}, {"scale_sigma_rel": -0.01}, {"u_model_mm": float("inf")}):
        with pytest.raises(ModelError, match="must be a finite number >= 0"):
            measure_file(model, "box", out_dir=tmp_path / "out", **kwargs)
    assert not (tmp_path / "out").exists()


def test_the_base_uncertainty_goes_with_the_dimensions_that_end_on_the_base(cube):
    """`vio model` closes the base on a support plane known to +-u_base: the height and the vertical edges carry it,
    the widths do not."""
    points, normals, _ = cube
    dims = measure(points, normals, "box", scale_sigma_rel=0.003, base_is_closure=True, u_base_mm=0.4)
    for d in dims:
        vertical = d.name.startswith(("box z", "box edge z"))
        assert d.components["u_model"] == pytest.approx(0.4 if vertical else 0.0), d.name
        assert d.U95 == pytest.approx(
            1.96 * np.sqrt(d.components["u_fit"] ** 2 + (0.003 * d.measured) ** 2 + (0.4 if vertical else 0.0) ** 2)
        )
    assert all("base: the model's closure" in d.note for d in dims if d.name.startswith("box z"))
