"""Scenario definition files (`data/synthetic/*.yaml`): a built-in scenario with its motion parameters changed.

scenario: orbit          # orbit | figure8 | room
duration_s: 60           # optional default duration (the command line's --duration wins)
motion:                  # optional; keys per scenario below, unknown keys are errors
  ring_s: 15.0
  elevations_deg: [0, 20, 40, 60]
  radius_min_m: 0.38
  radius_max_m: 0.66
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from vio.errors import SimulationError
from vio.kalibr import read_yaml

MOTION_KEYS: dict[str, dict[str, type]] = {
    "orbit": {"ring_s": float, "elevations_deg": list, "radius_min_m": float, "radius_max_m": float},
    "figure8": {"loop_s": float},
    "room": {"lap_s": float},
}


@dataclass(frozen=True)
class Definition:
    base: str  # the built-in scenario: orbit, figure8 or room
    duration_s: float | None = None  # default duration, s
    motion: dict[str, Any] = field(default_factory=dict)  # keyword arguments of the camera-motion builder


def read_definition(path: Path) -> Definition:
    """Read and validate a scenario YAML; raises SimulationError naming the file and the problem."""
    data = read_yaml(path, SimulationError)
    unknown = sorted(set(data) - {"scenario", "duration_s", "motion", "description"})
    if unknown:
        raise SimulationError(f"{path}: unknown key(s) {', '.join(unknown)} (scenario, duration_s, motion)")
    base = data.get("scenario")
    if base not in MOTION_KEYS:
        raise SimulationError(f"{path}: 'scenario' must be one of {', '.join(MOTION_KEYS)}, got {base!r}")
    duration = data.get("duration_s")
    if duration is not None and (not isinstance(duration, (int, float)) or duration <= 0):
        raise SimulationError(f"{path}: duration_s must be a positive number, got {duration!r}")
    motion = data.get("motion") or {}
    if not isinstance(motion, dict):
        raise SimulationError(f"{path}: 'motion' must be a mapping")
    allowed = MOTION_KEYS[base]
    bad = sorted(set(motion) - set(allowed))
    if bad:
        raise SimulationError(f"{path}: unknown motion key(s) {', '.join(bad)} for {base}; known: {', '.join(allowed)}")
    kwargs: dict[str, Any] = {}
    for key, value in motion.items():
        if allowed[key] is list:
            if not isinstance(value, list) or not value or not all(isinstance(v, (int, float)) for v in value):
                raise SimulationError(f"{path}: motion.{key} must be a non-empty list of numbers")
            kwargs[key] = tuple(float(v) for v in value)
        else:
            if not isinstance(value, (int, float)) or isinstance(value, bool) or value <= 0:
                raise SimulationError(f"{path}: motion.{key} must be a positive number, got {value!r}")
            kwargs[key] = float(value)
    return Definition(base, None if duration is None else float(duration), kwargs)
