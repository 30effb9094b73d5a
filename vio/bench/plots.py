"""Benchmark figures (matplotlib, Agg backend), written atomically as PNG under `out/plots/`.

- `trajectories.png`: each capture from above (world x-y, metres), ground truth against every method's aligned
  estimate (4-DoF alignment; Sim3 for vision_only; imu_only is not aligned: it starts from the true state).
  The view is the ground truth's extent: a method that drifts out of it says so in the legend with its final error.
- `error_over_time.png`: position error after the same alignment against time, log scale, one panel per capture.
- `error_distribution.png`: box plots of ATE per method over all captures and seeds, one panel per IMU grade.
"""

from __future__ import annotations

import io
import logging
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from vio.atomic import write_bytes  # noqa: E402
from vio.bench.ranking import headline_key, method_rank  # noqa: E402

log = logging.getLogger(__name__)

COLORS = {"vio": "tab:blue", "batch": "tab:green", "vision_only": "tab:purple", "imu_only": "tab:red"}
MAX_PANELS = 12


def _color(method: str) -> str:
    return COLORS.get(method, "tab:orange")


def _save(fig: plt.Figure, path: Path) -> None:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    write_bytes(path, buf.getvalue())


def _read_trace(path: Path) -> np.ndarray:
    """(N, 5) t_s, x, y, z, err_m from an aligned_<method>.csv."""
    return np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)


def _traces(out: Path, case_key: str) -> dict[str, np.ndarray]:
    found: dict[str, np.ndarray] = {}
    for p in sorted((out / "runs" / case_key).glob("*/aligned_*.csv")):
        method = p.stem.removeprefix("aligned_")
        try:
            found[method] = _read_trace(p)
        except (OSError, ValueError) as exc:
            log.warning("bench plots: cannot read %s: %s", p, exc)
    return dict(sorted(found.items(), key=lambda kv: method_rank(kv[0])))


def _grid(n: int) -> tuple[plt.Figure, np.ndarray]:
    cols = min(n, 3)
    rows = int(np.ceil(n / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(5.2 * cols, 4.4 * rows), squeeze=False, layout="constrained")
    for ax in axes.flat[n:]:
        ax.set_visible(False)
    return fig, axes.flat


def ground_truth_path(out: Path, case_key: str) -> Path | None:
    """The capture's ground truth: the cached capture `out/captures/<case>`, or the copy `out/ground_truth/<case>.csv`
    kept when the captures were elsewhere (a shared `--captures` folder, a remote worker's cache)."""
    for p in (out / "captures" / case_key, out / "ground_truth" / f"{case_key}.csv"):
        if p.exists():
            return p
    return None


def plot_trajectories(cases: list[Any], out: Path, path: Path) -> None:
    from vio.trajio import read_trajectory

    fig, axes = _grid(len(cases))
    for ax, case in zip(axes, cases, strict=False):
        gt = read_trajectory(ground_truth_path(out, case.key))
        ax.plot(gt.p_world[:, 0], gt.p_world[:, 1], color="black", lw=2.5, label="ground truth", zorder=1)
        lo, hi = gt.p_world[:, :2].min(axis=0), gt.p_world[:, :2].max(axis=0)
        pad = 0.25 * max(float((hi - lo).max()), 0.1)
        box_lo, box_hi = lo - pad, hi + pad
        for method, tr in _traces(out, case.key).items():
            xy = tr[:, 1:3]
            leaves = bool(((xy < box_lo) | (xy > box_hi)).any())
            label = f"{method} (leaves view; final error {tr[-1, 4]:.3g} m)" if leaves else method
            ax.plot(xy[:, 0], xy[:, 1], color=_color(method), lw=1.2, label=label, zorder=2)
        ax.set_xlim(box_lo[0], box_hi[0])
        ax.set_ylim(box_lo[1], box_hi[1])
        ax.set_aspect("equal", adjustable="box")
        ax.set_title(f"{case.label}, {case.imu} IMU, seed {case.seed}")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper right")
    fig.suptitle("Trajectories from above (aligned 4-DoF; vision_only Sim3; imu_only unaligned from the true start)")
    _save(fig, path)


def plot_error_over_time(cases: list[Any], out: Path, path: Path) -> None:
    fig, axes = _grid(len(cases))
    for ax, case in zip(axes, cases, strict=False):
        for method, tr in _traces(out, case.key).items():
            ax.semilogy(tr[:, 0], np.maximum(tr[:, 4], 1e-5), color=_color(method), lw=1.2, label=method)
        ax.set_title(f"{case.label}, {case.imu} IMU, seed {case.seed}")
        ax.set_xlabel("time (s)")
        ax.set_ylabel("position error (m)")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7)
    fig.suptitle("Position error over time (4-DoF alignment; vision_only Sim3; imu_only unaligned from the true start)")
    _save(fig, path)


def plot_error_distribution(rows: list[dict[str, Any]], path: Path) -> None:
    imus = sorted({r["imu"] for r in rows})
    fig, axes = plt.subplots(1, max(len(imus), 1), figsize=(6 * max(len(imus), 1), 4.5), squeeze=False)
    for ax, imu in zip(axes.flat, imus, strict=False):
        methods = sorted({r["method"] for r in rows if r["imu"] == imu}, key=method_rank)
        data, labels = [], []
        for m in methods:
            key = headline_key(m)
            vals = [r[key] for r in rows if r["imu"] == imu and r["method"] == m and r.get(key) is not None]
            if vals:
                data.append(vals)
                labels.append(f"{m}\n(Sim3)" if m == "vision_only" else m)
        if data:
            box = ax.boxplot(data, patch_artist=True, widths=0.6, showfliers=False)
            ax.set_xticks(range(1, len(labels) + 1), labels)
            for patch, lab in zip(box["boxes"], labels, strict=True):
                patch.set_facecolor(_color(lab.split("\n")[0]))
                patch.set_alpha(0.6)
            for i, vals in enumerate(data, start=1):
                ax.scatter(np.full(len(vals), i), vals, s=10, color="black", zorder=3)
            ax.set_yscale("log")
        ax.set_title(f"{imu} IMU: ATE over all captures and seeds")
        ax.set_ylabel("ATE RMSE (m, log)")
        ax.grid(alpha=0.3, which="both", axis="y")
    _save(fig, path)


def make_plots(suite: Any, rows: list[dict[str, Any]], out: Path) -> list[Path]:
    """Write the three figures; returns their paths. Panels show at most MAX_PANELS captures (first seeds first)."""
    out = Path(out)
    plots = out / "plots"
    cases = sorted(suite.cases, key=lambda c: (c.seed, c.imu != "phone"))[:MAX_PANELS]
    cases = [c for c in cases if ground_truth_path(out, c.key) is not None]
    ok_rows = [r for r in rows if "error" not in r]
    paths = []
    if cases:
        paths += [plots / "trajectories.png", plots / "error_over_time.png"]
        plot_trajectories(cases, out, paths[0])
        plot_error_over_time(cases, out, paths[1])
    paths.append(plots / "error_distribution.png")
    plot_error_distribution(ok_rows, paths[-1])
    return paths
