"""Pictures of a deviation analysis, as PNG bytes (matplotlib's Agg canvas, no pyplot state): the histogram of the
signed deviations with the tolerance window, and the registered model coloured by deviation from three viewpoints.

Deviations are in mm, positive outside the CAD; points are in the CAD frame (mm, z up). The colour scale is the
diverging 'RdBu_r' map (blue inside, red outside), saturated at +-limit.
"""

from __future__ import annotations

import io

import numpy as np

from vio.model.deviation import DeviationStats

COLOUR_MAP = "RdBu_r"
VIEWS = ((30.0, -60.0, "front left"), (30.0, 120.0, "back right"), (80.0, -90.0, "top"))  # (elevation, azimuth) deg


def _png(fig) -> bytes:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    return buf.getvalue()


def histogram_png(signed_mm: np.ndarray, stats: DeviationStats, limit_mm: float, title: str) -> bytes:
    """Histogram of signed deviations (N,) mm, bars coloured like the deviation map, with the window and mean."""
    from matplotlib import colormaps
    from matplotlib.figure import Figure

    d = np.asarray(signed_mm)
    lo, hi = float(np.percentile(d, 0.1)), float(np.percentile(d, 99.9))
    lo, hi = min(lo, -limit_mm), max(hi, limit_mm)
    counts, edges = np.histogram(np.clip(d, lo, hi), bins=120, range=(lo, hi))
    centres = 0.5 * (edges[1:] + edges[:-1])
    colours = colormaps[COLOUR_MAP](np.clip((centres + limit_mm) / (2 * limit_mm), 0, 1))
    fig = Figure(figsize=(8, 4.2))
    ax = fig.add_subplot()
    ax.bar(centres, 100.0 * counts / len(d), width=edges[1] - edges[0], color=colours, edgecolor="none")
    ax.axvline(0.0, color="black", lw=0.8)
    ax.axvline(stats.mean_mm, color="tab:green", lw=1.2, label=f"mean {stats.mean_mm:+.3f} mm")
    for x, name in ((stats.p01_mm, "1st"), (stats.p99_mm, "99th")):
        ax.axvline(x, color="grey", lw=1, ls="--")
        ax.text(x, ax.get_ylim()[1] * 0.95, f" {name} pct", fontsize=8, color="grey", ha="left", va="top")
    ax.set_xlabel("signed deviation from the CAD, mm (positive outside)")
    ax.set_ylabel("share of points, %")
    window = f"window {stats.max_positive_mm:+.2f} / {stats.max_negative_mm:+.2f} mm, std {stats.std_mm:.3f} mm"
    ax.set_title(f"{title}\n{window} (tails beyond the 0.1-99.9 percentiles are piled at the ends)", fontsize=10)
    ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    return _png(fig)


def deviation_png(points_cad_mm: np.ndarray, signed_mm: np.ndarray, limit_mm: float, title: str) -> bytes:
    """The points (N, 3; CAD frame, mm) as a 3D scatter coloured by signed deviation (N,), from three viewpoints.

    At most 30,000 points are drawn (a random, seeded subset).
    """
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure

    rng = np.random.default_rng(0)
    keep = rng.choice(len(points_cad_mm), min(30_000, len(points_cad_mm)), replace=False)
    p, d = np.asarray(points_cad_mm)[keep], np.asarray(signed_mm)[keep]
    norm = Normalize(-limit_mm, limit_mm)
    fig = Figure(figsize=(12, 4.4))
    centre = 0.5 * (p.min(axis=0) + p.max(axis=0))
    half = 0.5 * float(np.ptp(p, axis=0).max())
    for i, (elev, azim, name) in enumerate(VIEWS):
        ax = fig.add_subplot(1, 3, i + 1, projection="3d")
        ax.scatter(*p.T, c=d, cmap=COLOUR_MAP, norm=norm, s=1.5, depthshade=False, linewidths=0)
        ax.view_init(elev=elev, azim=azim)
        for setter, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), centre, strict=True):
            setter(c - half, c + half)
        ax.set_box_aspect((1, 1, 1))
        ax.set_title(name, fontsize=9)
        ax.tick_params(labelsize=6)
    fig.subplots_adjust(left=0.0, right=0.88, bottom=0.02, top=0.9, wspace=0.0)
    bar = fig.colorbar(ScalarMappable(norm=norm, cmap=colormaps[COLOUR_MAP]), ax=fig.axes, shrink=0.7, pad=0.02)
    bar.set_label(f"signed deviation, mm (saturated at +-{limit_mm:g})")
    fig.suptitle(title, fontsize=10)
    return _png(fig)
