"""Capture phases a user can be asked to add around the scenario's motion: a still start, brisk excitation, a
still end (issue 15: what makes the metric scale and the biases observable).

The phased capture runs, in order:

1. `still_start_s`: the phone held still at the scenario's first pose (zero velocity: the gyro bias and the
   accelerometer bias orthogonal to gravity become observable, and the estimator can start statically);
2. `excite_s`: the phone shaken about that pose in all directions (sums of sinusoids near 2 Hz on each axis,
   RMS acceleration `EXCITE_RMS_M_S2`, the motion `vio run`'s capture advice asks for), eased in and out over
   `EASE_S`; the orientation stays the first pose's;
3. the scenario's own motion, started and stopped smoothly: its clock ramps from rest to full speed over
   `RAMP_S` and back, so the scenario's whole `duration_s` of motion is covered (`duration_s + RAMP_S` of time);
4. `still_end_s`: held still at the scenario's last pose.

`PhasedMotion.total_s(duration_s)` is the capture's length. Every phase is C3 smooth (smoothstep7 blends), so the
finite-difference accelerations and angular rates of `vio.sim.trajectory.Trajectory` stay exact to ~1e-8.
With all three phases at zero the pose function is returned unchanged (the default captures are untouched).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vio.errors import SimulationError
from vio.sim.trajectory import PoseFn, smoothstep7

EXCITE_RMS_M_S2 = 5.6  # RMS of the shaking's acceleration magnitude (a phone shaken about 5 cm each way at 2 Hz)
EXCITE_FREQS_HZ = (1.7, 2.0, 2.3)  # one frequency per world axis: the direction of the shaking keeps changing
EASE_S = 0.5  # the shaking's envelope rises and falls over this long
RAMP_S = 1.0  # the scenario's motion starts and stops over this long
MAX_PHASE_S = 60.0


@dataclass(frozen=True)
class PhasedMotion:
    """Phase lengths in seconds (0: none)."""

    still_start_s: float = 0.0
    excite_s: float = 0.0
    still_end_s: float = 0.0

    def validate(self) -> None:
        for name, v in (
            ("--still-start", self.still_start_s),
            ("--excite", self.excite_s),
            ("--still-end", self.still_end_s),
        ):
            if not np.isfinite(v) or not 0.0 <= v <= MAX_PHASE_S:
                raise SimulationError(f"{name} must be between 0 and {MAX_PHASE_S:g} s, got {v:g}")
        if 0.0 < self.excite_s < 2.0 * EASE_S:
            raise SimulationError(f"--excite must be 0 or at least {2 * EASE_S:g} s, got {self.excite_s:g}")

    @property
    def active(self) -> bool:
        return self.still_start_s > 0.0 or self.excite_s > 0.0 or self.still_end_s > 0.0

    def motion_start_s(self) -> float:
        """Capture time at which the scenario's own motion starts (its clock still at 0), s."""
        return self.still_start_s + self.excite_s

    def total_s(self, duration_s: float) -> float:
        """The capture's length for `duration_s` of the scenario's motion, s."""
        return duration_s if not self.active else self.motion_start_s() + duration_s + RAMP_S + self.still_end_s

    def as_dict(self, duration_s: float) -> dict[str, float]:
        """What `scene/scene.yaml` records (capture times, s since its start)."""
        t0 = self.motion_start_s()
        return {
            "still_start_s": self.still_start_s,
            "excite_s": self.excite_s,
            "excite_rms_m_s2": EXCITE_RMS_M_S2 if self.excite_s > 0 else 0.0,
            "motion_start_s": t0,
            "motion_end_s": t0 + duration_s + RAMP_S,
            "still_end_s": self.still_end_s,
            "ramp_s": RAMP_S,
        }


def _ramp_integral(x: np.ndarray) -> np.ndarray:
    """Integral from 0 to x of smoothstep7: 0 below 0, x - 1/2 above 1."""
    xc = np.clip(x, 0.0, 1.0)
    inner = xc**5 * (7.0 - 14.0 * xc + 10.0 * xc**2 - 2.5 * xc**3)
    return np.where(x >= 1.0, x - 0.5, inner)


def scenario_clock(t: np.ndarray, motion_start_s: float, duration_s: float) -> np.ndarray:
    """The scenario's own time at capture time t: 0 until motion_start_s, then ramping up to full speed over
    RAMP_S, and back down to rest at duration_s; covers exactly [0, duration_s]."""
    u = t - motion_start_s
    up = RAMP_S * _ramp_integral(u / RAMP_S)
    down = RAMP_S * _ramp_integral((u - duration_s) / RAMP_S)
    return up - down


def excitation_offsets(rng: np.random.Generator, excite_s: float, start_s: float):
    """t (N,) -> (N, 3) world displacements of the shaking, m: three sinusoids (one per axis, seeded phases)
    with amplitudes giving EXCITE_RMS_M_S2 in all, under a smoothstep7 envelope over [start_s, start_s + excite_s]."""
    freqs = np.asarray(EXCITE_FREQS_HZ)
    phases = rng.uniform(0.0, 2.0 * np.pi, 3)
    per_axis_rms = EXCITE_RMS_M_S2 / np.sqrt(3.0)
    amps = per_axis_rms * np.sqrt(2.0) / (2.0 * np.pi * freqs) ** 2  # m; RMS of A w^2 sin is A w^2 / sqrt 2

    def offsets(t: np.ndarray) -> np.ndarray:
        env = smoothstep7((t - start_s) / EASE_S) * smoothstep7((start_s + excite_s - t) / EASE_S)
        wave = amps * np.sin(2.0 * np.pi * freqs * t[:, None] + phases)
        return env[:, None] * wave

    return offsets


def phased(pose_fn: PoseFn, motion: PhasedMotion, duration_s: float, rng: np.random.Generator) -> PoseFn:
    """The capture's body pose function: `pose_fn` (the scenario's, over [0, duration_s]) with the phases around
    it. Returns `pose_fn` itself when no phase is set."""
    motion.validate()
    if not motion.active:
        return pose_fn
    t_move = motion.motion_start_s()
    shake = excitation_offsets(rng, motion.excite_s, motion.still_start_s) if motion.excite_s > 0 else None

    def fn(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p, R = pose_fn(scenario_clock(t, t_move, duration_s))
        if shake is not None:
            p = p + shake(t)
        return p, R

    return fn
