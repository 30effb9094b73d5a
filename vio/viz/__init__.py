"""The viewer: the only package that imports rerun. The estimator never draws.

Modules (import the one you need; this file imports nothing, so `vio.viz.geometry` stays free of rerun):
  rerun_sink  `make_rerun_sink(rrd=..., serve=..., spawn=...)`: the sink that logs the run to rerun (sensor_time
              timeline, world z-up, camera OpenCV)
  blueprint   entity paths, the timeline name and the default viewer layout
  server      starts a rerun viewer process bound to 127.0.0.1 (web or native)
  geometry    numbers shown beside the estimate (pure numpy): the ground truth anchored in the estimate's world,
              reprojection errors in px
"""

from __future__ import annotations
