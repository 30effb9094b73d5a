"""Our trajectory metrics equal evo's command-line tools on the same files (evo is GPL: run as a program only).

evo lives in its own venv (`make venv` creates `.venv-evo`); the tests skip with a reason when it is missing.
Each evo run writes `--save_results` (a zip with `stats.json` at full precision and, when aligning with scale,
`alignment_transformation_sim3.npy`), which we compare with `vio.metrics.evaluate` to 1e-6 relative.
"""

from __future__ import annotations

import io
import json
import os
import subprocess
import zipfile
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tests.conftest import ROOT, shared_path
from vio.metrics import evaluate
from vio.trajio import Trajectory, read_trajectory, write_tum

EVO_BIN = ROOT / ".venv-evo" / "bin"
REL = 1e-6

pytestmark = pytest.mark.skipif(
    not (EVO_BIN / "evo_ape").exists(),
    reason=f"evo oracle not installed: {EVO_BIN}/evo_ape missing (run `make venv` to create .venv-evo)",
)


def run_evo(jobs: dict[str, list[str]], workdir: Path) -> dict[str, dict]:
    """Run evo commands; return per job the parsed stats, error count and Sim3 scale (if any).

    The first job runs alone because a first run creates $HOME/.evo/settings.json and concurrent first runs race
    on that file; the others then run in parallel.
    """
    env = {**os.environ, "MPLBACKEND": "Agg", "HOME": str(workdir)}

    def start(name: str, args: list[str]) -> subprocess.Popen:
        out = workdir / f"{name}.zip"
        cmd = [str(EVO_BIN / args[0]), *args[1:], "--save_results", str(out), "--no_warnings", "--silent"]
        return subprocess.Popen(cmd, cwd=workdir, env=env, stderr=subprocess.PIPE, text=True)

    names = list(jobs)
    first = start(names[0], jobs[names[0]])
    first.wait(timeout=300)
    procs = {names[0]: first} | {name: start(name, jobs[name]) for name in names[1:]}
    results = {}
    for name, proc in procs.items():
        _, err = proc.communicate(timeout=300)
        assert proc.returncode == 0, f"{name}: {err}"
        with zipfile.ZipFile(workdir / f"{name}.zip") as z:
            res = {"stats": json.loads(z.read("stats.json")), "n": np.load(io.BytesIO(z.read("error_array.npy"))).size}
            if "alignment_transformation_sim3.npy" in z.namelist():
                T = np.load(io.BytesIO(z.read("alignment_transformation_sim3.npy")))
                res["scale"] = float(np.cbrt(np.linalg.det(T[:3, :3])))
        results[name] = res
    return results


def check(ours: dict, theirs: dict, prefix: str = "", suffix: str = "") -> None:
    for key in ("rmse", "mean", "median", "max"):
        mine = ours[f"{prefix}{key}{suffix}"]
        assert mine == pytest.approx(theirs["stats"][key], rel=REL), (key, mine, theirs["stats"][key])


@pytest.fixture(scope="module")
def pair(tmp_path_factory) -> tuple[Path, Path, Trajectory, Trajectory]:
    """A 20 s ground truth at 20 Hz and a noisy, scaled, rotated, time-jittered estimate at 10 Hz."""
    d = tmp_path_factory.mktemp("evo")
    t = 1_600_000_000_000_000_000 + np.arange(0, 20_000_000_000, 50_000_000, dtype=np.int64)
    ts = (t - t[0]) * 1e-9
    p = np.column_stack([2 * np.cos(0.3 * ts), 2 * np.sin(0.3 * ts), 0.5 * np.sin(0.7 * ts)])
    rot = Rotation.from_rotvec(np.column_stack([0.1 * np.sin(ts), 0.2 * np.cos(0.5 * ts), 0.3 * ts]))
    gt = Trajectory(t, p, rot.as_quat()[:, [3, 0, 1, 2]])
    rng = np.random.default_rng(0)
    R = Rotation.from_rotvec([0.1, -0.2, 0.5])
    pe = 1.02 * R.apply(p + rng.normal(scale=0.02, size=p.shape)) + [1.0, 2.0, 3.0]
    qe = (R * rot * Rotation.from_rotvec(rng.normal(scale=0.01, size=p.shape))).as_quat()[:, [3, 0, 1, 2]]
    te = t[::2] + rng.integers(-4_000_000, 4_000_000, t[::2].size)
    est = Trajectory(te, pe[::2], qe[::2])
    write_tum(d / "gt.tum", gt)
    write_tum(d / "est.tum", est)
    return d / "gt.tum", d / "est.tum", read_trajectory(d / "gt.tum"), read_trajectory(d / "est.tum")


def test_ape_and_rpe_equal_evo(pair):
    gt_path, est_path, gt, est = pair
    files = [str(gt_path), str(est_path)]
    rpe = ["evo_rpe", "tum", *files, "--all_pairs", "--pairs_from_reference", "-u", "m"]
    jobs = {
        "ape_se3": ["evo_ape", "tum", *files, "-a"],
        "ape_sim3": ["evo_ape", "tum", *files, "-as"],
        "ape_none": ["evo_ape", "tum", *files],
        "ape_se3_rot": ["evo_ape", "tum", *files, "-a", "-r", "angle_deg"],
        "rpe_se3_1": [*rpe, "-d", "1", "-a"],
        "rpe_se3_5": [*rpe, "-d", "5", "-a"],
        "rpe_se3_5_rot": [*rpe, "-d", "5", "-a", "-r", "angle_deg"],
        "rpe_sim3_2": [*rpe, "-d", "2", "-as"],
        "rpe_none_2": [*rpe, "-d", "2"],
        "ape_se3_interp": ["evo_ape", "tum", *files, "-a", "--sync_method", "interpolation"],
        "rpe_se3_2_interp": [*rpe, "-d", "2", "-a", "--sync_method", "interpolation"],
    }
    evo = run_evo(jobs, gt_path.parent)
    se3, sim3, none = (evaluate(gt, est, align=a) for a in ("se3", "sim3", "none"))

    check(se3, evo["ape_se3"], "ate_", "_m")
    check(sim3, evo["ape_sim3"], "ate_", "_m")
    check(none, evo["ape_none"], "ate_", "_m")
    assert se3["pairs"] == evo["ape_se3"]["n"] == 200
    assert se3["ate_rot_rmse_deg"] == pytest.approx(evo["ape_se3_rot"]["stats"]["rmse"], rel=REL)
    assert sim3["scale"] == pytest.approx(evo["ape_sim3"]["scale"], rel=REL)
    assert sim3["scale"] == pytest.approx(1 / 1.02, rel=0.01)  # the estimate was made 2 % too large

    for ours, name, seg in [(se3, "rpe_se3_1", "1m"), (se3, "rpe_se3_5", "5m"), (sim3, "rpe_sim3_2", "2m")]:
        check(ours["rpe"][seg], evo[name], "trans_", "_m")
        assert ours["rpe"][seg]["pairs"] == evo[name]["n"]
    check(none["rpe"]["2m"], evo["rpe_none_2"], "trans_", "_m")
    check(se3["rpe"]["5m"], evo["rpe_se3_5_rot"], "rot_", "_deg")
    interp = evaluate(gt, est, align="se3", sync="interpolate")
    check(interp, evo["ape_se3_interp"], "ate_", "_m")
    check(interp["rpe"]["2m"], evo["rpe_se3_2_interp"], "trans_", "_m")
    assert abs(interp["ate_rmse_m"] - se3["ate_rmse_m"]) > 1e-5  # the two really differ here (4e-5 m)
    # Sanity: the scale error is visible in the RPE unless Sim3 alignment removes it.
    assert sim3["rpe"]["2m"]["trans_rmse_m"] < se3["rpe"]["2m"]["trans_rmse_m"]


def test_real_euroc_groundtruth_vs_vicon_equals_evo(tmp_path):
    """Real data: EuRoC V1_01 re-estimated ground truth (20 Hz CSV) scored against the raw Vicon track (200 Hz)."""
    csv = read_trajectory(shared_path("euroc_v1_01", "mav0", "state_groundtruth_estimate0", "data.csv"))
    vicon_path = shared_path("euroc_v1_01", "vicon_groundtruth_200hz.txt")
    write_tum(tmp_path / "est.tum", csv)  # evo's `tum` mode reads TUM only
    evo = run_evo({"ape": ["evo_ape", "tum", str(vicon_path), str(tmp_path / "est.tum"), "-a"]}, tmp_path)
    ours = evaluate(read_trajectory(vicon_path), read_trajectory(tmp_path / "est.tum"), align="se3")
    check(ours, evo["ape"], "ate_", "_m")
    assert ours["pairs"] == evo["ape"]["n"] > 2000
    assert ours["ate_rmse_m"] < 0.05  # the two ground truths of the same flight agree to centimetres
