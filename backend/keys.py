"""GTSAM keys: `X(k)` pose (world_T_body), `V(k)` velocity (world, m/s), `B(k)` IMU bias share the keyframe index
k; `L(j)` is the landmark of track id j (world point, m). No arithmetic on keys."""

from __future__ import annotations

from gtsam.symbol_shorthand import B, L, V, X

__all__ = ["B", "L", "V", "X"]
