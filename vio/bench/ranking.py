"""How benchmark methods are presented: their order in tables and figures, and the ATE each one is judged by.

Shared by `vio.bench.report` (results.md) and `vio.bench.plots` (figures), so both list methods the same way.
"""

from __future__ import annotations

METHOD_ORDER = ("vio", "batch", "vio_fixed_lag", "vision_only", "imu_only")


def method_rank(method: str) -> tuple[int, str]:
    """Sort key: the methods of METHOD_ORDER in that order, then any other method by name."""
    return (METHOD_ORDER.index(method) if method in METHOD_ORDER else len(METHOD_ORDER), method)


def headline_key(method: str) -> str:
    """The ATE that is meaningful for a method: SE3, or Sim3 for vision_only (no metric scale)."""
    return "ate_sim3_m" if method == "vision_only" else "ate_se3_m"


NO_METRIC_SCALE = ("vision_only", "imu_only")


def has_metric_scale(method: str) -> bool:
    """Whether a method's Sim3 scale is a scale error worth reporting: not vision_only (its scale is arbitrary,
    the first baseline's) nor imu_only (the scale of a trajectory that is off by metres says nothing)."""
    return method not in NO_METRIC_SCALE
