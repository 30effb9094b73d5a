"""Issue 14's bad input through the command line: a CAD that is not a valid STL, a mesh with no faces, a run without
images, a model that does not overlap the CAD, and (issue 20) a model built from a failed run. Each ends with exit
status 2 and one `vio <command>: error:` line naming the file, no traceback, and no output passed off as complete."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import ROOT
from vio.sim.parts import build_part, write_stl

VIO = [sys.executable, "-m", "vio.cli"]


def _one_line_error(command: str, *args: str) -> str:
    """Run `vio command args...`; assert it ended with one error line and return that line."""
    res = subprocess.run([*VIO, command, *args], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr[-2000:]
    line = res.stderr.strip().splitlines()[-1]
    assert line.startswith(f"vio {command}: error: "), res.stderr[-2000:]
    return line


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("bad")
    cube, freeform = build_part("cube"), build_part("freeform")
    write_stl(root / "cube.stl", cube.vertices_mm, cube.faces, "cube, mm")
    write_stl(root / "freeform.stl", freeform.vertices_mm, freeform.faces, "the wrong part, mm")
    (root / "not.stl").write_text("this is not an STL\n")
    (root / "empty.stl").write_bytes(b"no faces".ljust(80) + np.uint32(0).tobytes())
    return {p.stem: p for p in root.glob("*.stl")}


def test_a_cad_that_is_not_an_stl(files, tmp_path):
    for command in ("compare", "measure"):
        line = _one_line_error(command, str(files["cube"]), "--cad", str(files["not"]), "--out", str(tmp_path / "o"))
        assert "CAD: " in line and "not.stl: not an STL" in line
    assert not (tmp_path / "o").exists()


def test_a_mesh_with_no_faces(files, tmp_path):
    line = _one_line_error("compare", str(files["empty"]), "--cad", str(files["cube"]), "--out", str(tmp_path / "o"))
    assert "empty.stl: the mesh has no faces" in line
    line = _one_line_error("measure", str(files["empty"]), "--out", str(tmp_path / "o"))
    assert "empty.stl: the mesh has no faces" in line
    line = _one_line_error("compare", str(files["cube"]), "--cad", str(files["empty"]), "--out", str(tmp_path / "o"))
    assert "CAD: " in line and "empty.stl" in line and "no faces" in line
    assert not (tmp_path / "o").exists()


def test_a_model_that_does_not_overlap_the_cad(files, tmp_path):
    wrong = ("--cad", str(files["cube"]), "--out", str(tmp_path / "o"))
    for command in ("compare", "measure"):
        line = _one_line_error(command, str(files["freeform"]), *wrong)
        assert "freeform.stl: the model does not overlap the CAD" in line
    assert not (tmp_path / "o").exists()


def test_a_run_without_images(sim_capture, tmp_path):
    capture = sim_capture("figure8", duration_s=1.0, images=False)  # cam0 lists no frames, and there are no stills
    assert not (capture / "mav0" / "cam1").exists() and len((capture / "mav0/cam0/data.csv").read_text().split()) <= 2
    run = tmp_path / "run"
    run.mkdir()
    (run / "trajectory.tum").write_text("0.0 0 0 0 0 0 0 1\n1.0 0 0 0 0 0 0 1\n")
    out = tmp_path / "m"
    line = _one_line_error("model", str(capture), "--run", str(run), "--out", str(out))
    assert str(capture) in line and "no camera frames" in line
    assert not any((out / name).exists() for name in ("part.stl", "part.ply", "dense.ply", "model.json"))
    out = tmp_path / "m2"  # without --run, `vio model` runs `vio run` first: it fails the same way
    line = _one_line_error("model", str(capture), "--out", str(out))
    assert "no camera frames" in line and not (out / "model.json").exists()
    run_json = out / "run" / "run.json"  # the run it tried says so, and is not passed off as complete
    assert not run_json.exists() or json.loads(run_json.read_text())["status"] == "failed"


def test_a_model_from_a_failed_run(files, tmp_path):
    folder = tmp_path / "model"
    folder.mkdir()
    (folder / "part.stl").write_bytes(files["cube"].read_bytes())
    (folder / "run").mkdir()
    (folder / "run" / "run.json").write_text(json.dumps({"status": "failed", "reasons": ["no estimate"]}))
    (folder / "model.json").write_text(json.dumps({"run": str(folder / "run"), "run_status": "failed"}))
    line = _one_line_error("measure", str(folder / "part.stl"), "--shape", "box", "--out", str(tmp_path / "o"))
    assert "part.stl: the run it was built from failed (no estimate)" in line
    assert not (tmp_path / "o").exists()
