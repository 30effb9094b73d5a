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
