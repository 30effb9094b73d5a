"""The part-model commands end to end through the command line: `vio model` on a short simulated capture posed
by its ground truth (the stage on its own, without the estimator), `vio compare` and `vio measure` on a model
whose deviation is known (the CAD scaled by 1.002), and their one-line errors."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from tests.conftest import ROOT
from vio.sim.api import simulate
from vio.sim.parts import build_part, read_stl_mesh, write_stl
from vio.trajio import read_trajectory, write_tum

VIO = [sys.executable, "-m", "vio.cli"]


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([*VIO, *args], capture_output=True, text=True, cwd=ROOT, timeout=600)


@pytest.mark.slow
def test_vio_model_writes_a_watertight_part(tmp_path):
    cap = simulate("figure8", tmp_path / "cap", duration_s=4.0, stills_hz=2.0, stills_size=(1008, 756))
    gt = tmp_path / "gt"
    gt.mkdir()
    write_tum(gt / "trajectory.tum", read_trajectory(cap / "mav0" / "state_groundtruth_estimate0" / "data.csv"))
    (gt / "run.json").write_text(json.dumps({"status": "degraded", "reasons": ["tracking lost 1.00-2.00 s"]}))
    (tmp_path / "m").mkdir()
    (tmp_path / "m" / "dense.ply").write_text("a previous model's file")
    r = _run("model", str(cap), "--run", str(gt), "--out", str(tmp_path / "m"), "--no-adjust")  # true poses
    assert r.returncode == 0, r.stderr[-2000:]
    meta = json.loads((tmp_path / "m" / "model.json").read_text())
    assert meta["status"] == "degraded" and "tracking lost 1.00-2.00 s" in meta["warnings"][0]
    assert meta["mesh"]["watertight"] and meta["mesh"]["non_manifold_edges"] == 0 and meta["num_views"] == 8
    assert meta["fill_creases"] is True  # the default; --no-crease-fill leaves the edges' holes open
    v, f = read_stl_mesh(tmp_path / "m" / "part.stl")  # millimetres, the part on its base
    assert 60.0 < np.ptp(v[:, 2]) < 90.0 and len(f) > 1000
    assert (tmp_path / "m" / "dense.ply").stat().st_size > 0 and (tmp_path / "m" / "part.ply").stat().st_size > 0


def test_no_model_from_a_failed_or_unfinished_run(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "trajectory.tum").write_text("0 0 0 0 0 0 0 1\n")
    for status in ("failed", "running"):
        (run / "run.json").write_text(json.dumps({"status": status}))
        r = _run("model", str(tmp_path), "--run", str(run), "--out", str(tmp_path / "m"))
        assert r.returncode == 2 and f"the run is {status}" in r.stderr and "Traceback" not in r.stderr
        assert not (tmp_path / "m" / "model.json").exists()


def test_compare_and_measure_a_model_with_a_known_scale_error(tmp_path):
    cube = build_part("cube")
    cad, model = tmp_path / "cad.stl", tmp_path / "model.stl"
    write_stl(cad, cube.vertices_mm, cube.faces, "cad, mm")
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    write_stl(model, (cube.vertices_mm * 1.002) @ R.T + [5.0, -3.0, 1.0], cube.faces, "model, mm")
    r = _run("compare", str(model), "--cad", str(cad), "--out", str(tmp_path / "c"))
    assert r.returncode == 0, r.stderr[-2000:]
    rep = json.loads((tmp_path / "c" / "report.json").read_text())
    assert abs(rep["deviation"]["mean_mm"] - 0.0762) < 0.03 and rep["completeness"] > 0.99  # faces 76.2 * 0.001 out
    r = _run("measure", str(model), "--cad", str(cad), "--shape", "box", "--scale-sigma", "0.003")
    assert r.returncode == 0, r.stderr[-2000:]
    assert "76.352" in r.stdout or "76.35" in r.stdout  # 76.2 * 1.002
    bad = _run("compare", str(tmp_path / "nothing.stl"), "--cad", str(cad), "--out", str(tmp_path / "x"))
    assert bad.returncode == 2 and "nothing.stl" in bad.stderr and "Traceback" not in bad.stderr
    bad = _run("model", "--out", str(tmp_path / "y"), "--middlebury", str(tmp_path / "none_par.txt"))
    assert bad.returncode == 2 and "none_par.txt" in bad.stderr and "Traceback" not in bad.stderr
