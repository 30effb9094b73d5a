"""The part model: the stage after the estimator (`vio model`, `vio compare`, `vio measure`).

It reads a run's output files and the capture's images, never the estimator's internals. One step per module:
views (calibrated, undistorted images with metric poses), dense (multi-view stereo depth maps), isolate (support
plane, region of interest), fuse (depth fusion into a signed distance volume), mesh (watertight surface), register
(rigid alignment to the CAD), deviation (signed distances, tolerance window), quality (mesh checks of the study's
Table 2), measure (fitted primitives and dimensions with uncertainty), report (report.md/json). Records shared by
the steps are in `vio.model.records`.
"""
