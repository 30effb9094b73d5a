"""The simulator: smooth hand-held trajectories, an IMU model, a ray-cast textured scene, and an ASL writer.

Entry points: `vio.sim.api.load_scenario` and `vio.sim.api.simulate` (the `vio simulate` command).
"""
