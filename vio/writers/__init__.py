"""Capture writers (the ASL layout the simulator and the tests write)."""
