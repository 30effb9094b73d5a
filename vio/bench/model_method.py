"""The `model` method of `vio bench`: the whole part chain on one simulated capture, scored against its CAD.

`vio run` (anchored to known positions when the method says so), then `vio model`, `vio measure --shape box|auto
--cad` and `vio compare --cad`, each of the last three as the user runs it (a child process of the worker, so the
model's own peak memory is measured). The row holds the trajectory's scores (as the `vio` method's) plus the
part's: every measured dimension's error and whether its stated U95 covers the truth, the deviation window and
standard deviation against the CAD, completeness, mesh checks, the model's wall time and peak memory.
"""

from __future__ import annotations

import json
import logging
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from vio.bench.suites import Case, Method
from vio.children import die_with_parent

log = logging.getLogger(__name__)

MODEL_KEYS = (
    "part",
    "dims",
    "dim_abs_err_med_mm",
    "dim_abs_err_max_mm",
    "dims_within_u95",
    "u95_med_mm",
    "dev_std_mm",
    "dev_max_pos_mm",
    "dev_max_neg_mm",
    "completeness",
    "watertight",
    "non_manifold_edges",
    "intersecting_triangles",
    "scale_sigma_rel",
    "model_s",
    "model_peak_rss_mb",
)


def write_known_positions(capture: Path, path: Path, hz: float, sigma_m: float, seed: int) -> Path:
    """A `--positions` CSV from the capture's ground truth: body positions at `hz` with Gaussian noise of
    `sigma_m` per axis (as a surveyed tripod ring or a robot arm would give them), seeded for repeatability."""
    from vio.readers import open_capture

    cap = open_capture(capture, needs=())
    gt = cap.ground_truth
    if gt is None:
        raise ValueError(f"{capture}: no ground truth to take known positions from")
    times = np.arange(gt.t_ns[0], gt.t_ns[-1], int(1e9 / hz))
    idx = np.searchsorted(gt.t_ns, times).clip(0, len(gt.t_ns) - 1)
    rng = np.random.default_rng([seed, 7])
    p = np.asarray(gt.p_world, float)[idx] + rng.normal(0.0, sigma_m, (len(idx), 3))
    lines = ["t_s,x,y,z,sigma_m"] + [
        f"{t * 1e-9:.9f},{x:.6f},{y:.6f},{z:.6f},{sigma_m:g}" for t, (x, y, z) in zip(gt.t_ns[idx], p, strict=True)
    ]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def _vio(args: list[str], log_path: Path) -> float:
    """Run `vio ARGS...` as a child process (its output to `log_path`); returns its wall time. Raises with the
    command's last log line when it fails."""
    t0 = time.perf_counter()
    with open(log_path, "w", encoding="utf-8") as logf:
        proc = subprocess.run(
            [sys.executable, "-m", "vio.cli", *args],
            stdout=logf,
            stderr=subprocess.STDOUT,
            preexec_fn=die_with_parent,  # the step dies with its worker (no orphan computing on)
        )
    if proc.returncode != 0:
        tail = log_path.read_text(encoding="utf-8", errors="replace").strip().splitlines()[-1:]
        raise RuntimeError(f"vio {args[0]} failed: {tail[0] if tail else 'no output'}")
    return time.perf_counter() - t0


def _children_peak_mb() -> float:
    """Peak RSS of the largest child process waited for so far, MiB."""
    return resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0


def part_scores(model_dir: Path, measure_dir: Path, compare_dir: Path) -> dict[str, Any]:
    """The part's row fields from the files `vio model`, `vio measure` and `vio compare` wrote."""
    model = json.loads((model_dir / "model.json").read_text(encoding="utf-8"))
    dims = json.loads((measure_dir / "measure.json").read_text(encoding="utf-8"))["dimensions"]
    rep = json.loads((compare_dir / "report.json").read_text(encoding="utf-8"))
    # face-to-face distances with a nominal (a box's edge lengths repeat them; radii and angles are in `dims`)
    lengths = [d for d in dims if d.get("nominal") is not None and d.get("kind") == "distance"]
    errs = [abs(d["measured"] - d["nominal"]) for d in lengths]
    dev = rep["deviation"]
    return {
        "dims": [
            {k: d.get(k) for k in ("name", "kind", "nominal", "measured", "deviation", "U95", "units")} for d in dims
        ],
        "dim_abs_err_med_mm": float(np.median(errs)) if errs else None,
        "dim_abs_err_max_mm": float(np.max(errs)) if errs else None,
        "dims_within_u95": f"{sum(e <= d['U95'] for e, d in zip(errs, lengths, strict=True))}/{len(errs)}",
        "u95_med_mm": float(np.median([d["U95"] for d in lengths])) if lengths else None,
        "dev_std_mm": dev["std_mm"],
        "dev_max_pos_mm": dev["max_positive_mm"],
        "dev_max_neg_mm": dev["max_negative_mm"],
        "completeness": rep["completeness"],
        "watertight": bool(model["mesh"].get("watertight")),
        "non_manifold_edges": rep["quality"].get("non_manifold_edges"),
        "intersecting_triangles": rep["quality"].get("intersecting_triangles"),
        "scale_sigma_rel": model.get("scale_sigma_rel"),
    }


def run_model(case: Case, method: Method, capture: Path, out: Path, score_run) -> list[dict[str, Any]]:
    """One part-model row: the run (scored by `score_run(trajectory_path, wall_s, run_json) -> row`), then the
    model, measure and compare steps on it."""
    from vio.bench.methods import MethodOutput, _info, _latencies
    from vio.config import load_config
    from vio.pipeline import run_capture

    positions = None
    if method.positions_sigma_m > 0:
        positions = write_known_positions(capture, out / "positions.csv", 2.0, method.positions_sigma_m, case.seed)
    run_dir = out / "run"
    cfg = load_config(None, ["run.progress=false", *method.overrides], method.presets)
    t0 = time.perf_counter()
    run_capture(capture, run_dir, cfg, positions=None if positions is None else str(positions))
    wall = time.perf_counter() - t0
    run = json.loads((run_dir / "run.json").read_text(encoding="utf-8"))
    row = score_run(MethodOutput(method.name, run_dir / "trajectory.tum", wall, _latencies(run), "se3", _info(run)))
    cad = capture / "scene" / "cad.stl"
    shape = "box" if case.part == "cube" else "auto"
    model_dir, measure_dir, compare_dir = out / "model", out / "measure", out / "compare"
    row["part"] = case.part
    row["model_s"] = _vio(["model", str(capture), "--run", str(run_dir), "--out", str(model_dir), *method.model_args],
                          out / "model.log")  # fmt: skip
    row["model_peak_rss_mb"] = _children_peak_mb()
    _vio(["measure", str(model_dir / "part.stl"), "--cad", str(cad), "--shape", shape, "--out", str(measure_dir)],
         out / "measure.log")  # fmt: skip
    _vio(["compare", str(model_dir / "part.stl"), "--cad", str(cad), "--out", str(compare_dir)], out / "compare.log")
    row.update(part_scores(model_dir, measure_dir, compare_dir))
    return [row]
