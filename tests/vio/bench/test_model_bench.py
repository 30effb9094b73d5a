"""`vio bench --suite model|parts`: the suites, the known positions it anchors runs to, the scores it reads from
the part commands' files, and its table. The suites themselves run in the benchmark (minutes per seed)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np

from tests.conftest import ROOT
from vio.bench.model_method import MODEL_KEYS, part_scores, write_known_positions
from vio.bench.report import ROW_KEYS, model_markdown
from vio.bench.suites import MODEL_SEEDS, Case, get_suite
from vio.readers import open_capture
from vio.readers.positions import read_positions
from vio.sim.parts import build_part, write_stl


def test_model_suites_use_held_out_seeds_and_distinct_captures():
    model = get_suite("model")
    assert [c.seed for c in model.cases] == MODEL_SEEDS and min(MODEL_SEEDS) > 12  # tests use seeds 0-12
    assert all(c.stills_hz == 2.0 and c.duration_s == 60.0 and c.part == "cube" for c in model.cases)
    assert {m.name for m in model.methods} == {"model", "model_positions"}
    parts = get_suite("parts")
    assert sorted(c.part for c in parts.cases) == ["cube", "cube_features", "freeform"]
    keys = {c.key for c in model.cases + parts.cases}
    assert len(keys) == len(model.cases) + len(parts.cases) - 1  # parts' cube is model's seed 101
    assert Case("orbit", 0, "phone", 4.0).key == "orbit_phone_s0_4s"  # the drift suites' cache names unchanged


def test_known_positions_follow_the_ground_truth(sim_capture, tmp_path):
    cap = sim_capture("orbit", 3.0, images=False)
    path = write_known_positions(cap, tmp_path / "positions.csv", 2.0, 1e-4, seed=5)
    known = read_positions(path)
    gt = open_capture(cap, needs=()).ground_truth
    assert len(known) == 6 and all(s == 1e-4 for _, _, s in known)
    err = [np.linalg.norm(p - gt.p_world[np.searchsorted(gt.t_ns, t)]) for t, p, _ in known]
    assert 1e-5 < np.median(err) < 5e-4  # the stated 0.1 mm noise, no more
    again = read_positions(write_known_positions(cap, tmp_path / "again.csv", 2.0, 1e-4, seed=5))
    assert all(np.array_equal(a[1], b[1]) for a, b in zip(known, again, strict=True))  # seeded


def _vio(*args: str) -> None:
    r = subprocess.run([sys.executable, "-m", "vio.cli", *args], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]


def test_part_scores_and_table_from_the_commands_files(tmp_path):
    """A model 0.2 % too large: the scores read from `vio measure` and `vio compare` outputs say so."""
    cube = build_part("cube")
    cad, model_dir = tmp_path / "cad.stl", tmp_path / "model"
    model_dir.mkdir()
    write_stl(cad, cube.vertices_mm, cube.faces, "cad, mm")
    write_stl(model_dir / "part.stl", cube.vertices_mm * 1.002, cube.faces, "model, mm")
    (model_dir / "model.json").write_text(json.dumps({"mesh": {"watertight": True}, "scale_sigma_rel": 0.0015}))
    _vio("measure", str(model_dir / "part.stl"), "--cad", str(cad), "--shape", "box", "--out", str(tmp_path / "me"))
    _vio("compare", str(model_dir / "part.stl"), "--cad", str(cad), "--out", str(tmp_path / "co"))
    s = part_scores(model_dir, tmp_path / "me", tmp_path / "co")
    assert set(s) <= set(MODEL_KEYS)
    assert len([d for d in s["dims"] if d["kind"] == "distance"]) == 3
    assert abs(s["dim_abs_err_max_mm"] - 0.1524) < 0.02  # 76.2 mm x 0.002
    assert s["dims_within_u95"] == "3/3"  # 0.15 mm inside U95 = 1.96 x 0.15 % x 76.35 mm = 0.22 mm
    assert s["watertight"] and s["completeness"] > 0.98 and s["scale_sigma_rel"] == 0.0015
    row = {**dict.fromkeys(ROW_KEYS), "scenario": "orbit", "imu": "phone", "seed": 101, "method": "model"}
    row.update(part="cube", model_s=100.0, model_peak_rss_mb=900.0, scale=0.998, ate_se3_m=0.004, **s)
    failed = {**row, "seed": 102, "error": "vio model failed: no support plane"}
    md = model_markdown([row, failed])
    assert "| cube | model | 101 | 4.0 | +0.200 | 0.150 |" in md
    assert "| cube | model | 1/2 |" in md and "3/3" in md
    assert model_markdown([failed]) == ""


def test_model_steps_die_with_their_worker(tmp_path):
    """A worker killed (the bench's time limit, SIGKILL) takes its model step with it: no orphan left computing."""
    import os
    import signal
    import time

    pid_file = tmp_path / "child.pid"
    code = (
        "import subprocess, sys, time; from vio.children import die_with_parent; "
        "p = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)'], preexec_fn=die_with_parent); "
        f"open({str(pid_file)!r}, 'w').write(str(p.pid)); time.sleep(60)"
    )
    worker = subprocess.Popen([sys.executable, "-c", code], cwd=ROOT)
    for _ in range(100):
        if pid_file.exists() and pid_file.read_text():
            break
        time.sleep(0.1)
    child = int(pid_file.read_text())
    worker.send_signal(signal.SIGKILL)
    worker.wait()
    for _ in range(50):
        try:
            os.kill(child, 0)
        except ProcessLookupError:
            return
        time.sleep(0.1)
    os.kill(child, signal.SIGKILL)
    raise AssertionError("the model step outlived its worker")
