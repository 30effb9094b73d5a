"""The estimator's start: the closed-form guesses (alignment.py), the inertial start (static or moving,
inertial.py), the two-view start without an IMU (visual.py), and the batch solve of the first window that both
hand to the smoother (window.py)."""
