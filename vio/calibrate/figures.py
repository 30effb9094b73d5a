"""Pictures of a calibration, as PNG bytes (matplotlib's Agg canvas, no pyplot state).

- coverage: every corner used, coloured by view, over the image frame with the coverage grid;
- residuals: reprojection residual vectors (magnified) at their corners, the residual scatter, per-view RMS;
- Allan deviation: one IMU sensor's three axes on log-log axes with the fitted white-noise (-1/2), random-walk
  (+1/2) and bias-instability (flat) lines and the points where the parameters are read.
"""

from __future__ import annotations

import io

import numpy as np

from vio.calibrate.camera import COVERAGE_GRID, CameraCalibration


def _png(fig) -> bytes:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    return buf.getvalue()


def _image_axes(ax, cal: CameraCalibration) -> None:
    ax.set_xlim(0, cal.width)
    ax.set_ylim(cal.height, 0)
    ax.set_aspect("equal")
    ax.set_xlabel("u (px)")
    ax.set_ylabel("v (px)")


def coverage_png(cal: CameraCalibration) -> bytes:
    """The corners of every view used, over the image with the COVERAGE_GRID cells."""
    from matplotlib import colormaps
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7.5, 6.0), layout="constrained")
    ax = fig.add_subplot()
    cmap = colormaps["turbo"]
    for i, uv in enumerate(cal.uv):
        ax.plot(uv[:, 0], uv[:, 1], ".", ms=3, color=cmap(i / max(len(cal.uv) - 1, 1)))
    nx, ny = COVERAGE_GRID
    for x in np.linspace(0, cal.width, nx + 1):
        ax.axvline(x, color="0.8", lw=0.6)
    for y in np.linspace(0, cal.height, ny + 1):
        ax.axhline(y, color="0.8", lw=0.6)
    _image_axes(ax, cal)
    ax.set_title(
        f"coverage: {len(cal.uv)} views, {sum(len(u) for u in cal.uv)} corners, "
        f"{100 * cal.coverage:.0f} % of the {nx}x{ny} cells"
    )
    return _png(fig)


def residuals_png(cal: CameraCalibration) -> bytes:
    """Residual vectors at their corners, the residual scatter, and each view's RMS."""
    from matplotlib.figure import Figure

    uv = np.vstack(cal.uv)
    res = np.vstack(cal.residuals_px)
    fig = Figure(figsize=(13, 4.6), layout="constrained")
    ax1, ax2, ax3 = fig.subplots(1, 3)
    scale = 0.05 * cal.width / max(float(np.percentile(np.linalg.norm(res, axis=1), 95)), 1e-9)
    ax1.quiver(uv[:, 0], uv[:, 1], res[:, 0] * scale, res[:, 1] * scale, angles="xy", scale_units="xy", scale=1)
    _image_axes(ax1, cal)
    ax1.set_title(f"residuals x{scale:.0f}")
    ax2.plot(res[:, 0], res[:, 1], ".", ms=2, alpha=0.5)
    lim = max(float(np.abs(res).max()), 1e-3) * 1.05
    ax2.set_xlim(-lim, lim)
    ax2.set_ylim(lim, -lim)
    ax2.set_aspect("equal")
    ax2.axhline(0, color="0.6", lw=0.6)
    ax2.axvline(0, color="0.6", lw=0.6)
    ax2.set_xlabel("du (px)")
    ax2.set_ylabel("dv (px)")
    ax2.set_title(f"RMS {cal.rms_px:.3f} px over {len(res)} corners")
    ax3.bar(np.arange(len(cal.view_rms_px)), cal.view_rms_px)
    ax3.axhline(cal.rms_px, color="C3", lw=1, label="overall RMS")
    ax3.set_xlabel("view")
    ax3.set_ylabel("RMS (px)")
    ax3.set_title("per-view RMS")
    ax3.legend()
    return _png(fig)


def allan_png(taus_s: np.ndarray, adev: np.ndarray, fits: tuple, unit: str, title: str) -> bytes:
    """One sensor's Allan deviation (3, T) per axis with each axis' fitted -1/2 and +1/2 lines and the points
    where N (tau = 1 s), K (tau = 3 s) and B (the minimum) are read."""
    from matplotlib.figure import Figure

    from vio.calibrate.allan import BIAS_INSTABILITY_FACTOR

    fig = Figure(figsize=(7.5, 5.5), layout="constrained")
    ax = fig.add_subplot()
    t = np.logspace(np.log10(taus_s[0]), np.log10(taus_s[-1]), 200)
    for j, (a, f) in enumerate(zip(adev, fits, strict=True)):
        c = f"C{j}"
        ax.loglog(taus_s, a, "-", color=c, lw=1.6, label=f"{'xyz'[j]}: N {f.white:.3g}, K {f.random_walk:.3g}")
        ax.loglog(t, f.white / np.sqrt(t), "--", color=c, lw=0.8)
        ax.loglog(t, f.random_walk * np.sqrt(t / 3.0), ":", color=c, lw=1.0)
        ax.loglog([1.0], [f.white], "o", color=c, ms=5)
        ax.loglog([3.0], [f.random_walk], "s", color=c, ms=5)
        ax.loglog([f.tau_min_s], [f.bias_instability * BIAS_INSTABILITY_FACTOR], "v", color=c, ms=6)
    lo = min(float(np.nanmin(adev)), min((f.random_walk for f in fits if f.random_walk > 0), default=np.inf)) / 2
    ax.set_ylim(lo, float(np.nanmax(adev)) * 2)
    ax.set_xlabel("tau (s)")
    ax.set_ylabel(f"Allan deviation ({unit})")
    ax.set_title(f"{title}: N on the -1/2 line at 1 s (o), K on the +1/2 line at 3 s (s), B at the minimum (v)")
    ax.grid(True, which="both", color="0.9")
    ax.legend(fontsize=8)
    return _png(fig)
