"""Frontends: OpenCV feature tracking and IMU preintegration (depend on `vio` records only)."""
