"""vio: metric visual-inertial reconstruction from a phone camera and IMU, fused in GTSAM."""

from __future__ import annotations

import logging

__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())
