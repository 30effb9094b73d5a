"""Backend: the GTSAM factor graph, initialisation and the iSAM2 smoother (depends on `vio` records only)."""
