"""The capture advice of backend/uncertainty.py: the run's acceleration from its own estimate against the
simulator's truth, and the one-line advice on how to capture next time."""

from __future__ import annotations

from backend.uncertainty import ADVISE_ABOVE_REL, motion_excitation, scale_advice
from vio.bench.scale_limit import scale_limit
from vio.readers import open_capture
from vio.records import StateEstimate


def test_excitation_from_states_matches_the_ground_truth(sim_capture):
    """States at 5 Hz (ground-truth poses, velocities and biases) and the noisy phone IMU give the integral of the
    squared body acceleration that the simulator's own accelerations give (the white noise's share removed)."""
    cap = open_capture(sim_capture("orbit", 6.0, images=False), needs=("imu",))
    gt = cap.ground_truth
    states = [
        StateEstimate(n, int(gt.t_ns[i]), gt.world_T_body(i), gt.v_world[i], gt.b_w[i], gt.b_a[i])
        for n, i in enumerate(range(0, len(gt), 40))
    ]
    exc = motion_excitation(cap.imu, states, cap.imu_calib.accelerometer_noise_density)
    truth = scale_limit(gt, cap.imu_calib).excitation
    assert exc is not None and abs(exc / truth - 1.0) < 0.1, (exc, truth)
    assert motion_excitation(cap.imu, states[:1], 0.015) is None


def test_advice_names_the_limit_and_what_to_do():
    assert scale_advice(ADVISE_ABOVE_REL * 0.9, 1.0, 0.015) is None  # a small sigma needs no advice
    slow = scale_advice(0.0077, 8.7, 0.015)  # the 30 s orbit: 0.51 % from its accelerations
    assert slow is not None and "0.51 %" in slow and "s of brisk motion" in slow and "\n" not in slow
    brisk = scale_advice(0.0058, 96.9, 0.015)  # the 30 s room walk: the accelerometer allows 0.15 %
    assert brisk is not None and "the images limit the scale" in brisk
    assert "do not show the scale" in scale_advice(0.01, 0.0, 0.015)
