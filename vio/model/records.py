"""Records passed between the part-model steps. World is the run's world frame (z up, metres) unless stated."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class View:
    """One calibrated image for multi-view stereo: undistorted to an ideal pinhole camera, with its metric pose."""

    name: str  # e.g. the image file name or the still's t_ns
    image: np.ndarray  # (H, W) uint8 grayscale or (H, W, 3) uint8 BGR, undistorted
    K: np.ndarray  # (3, 3) pinhole intrinsics of the undistorted image, px
    world_T_cam: np.ndarray  # (4, 4) camera (OpenCV axes) in world, translation m
    t_ns: int | None = None  # capture time (stills and video frames), None for image sets without time

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) px."""
        return int(self.image.shape[1]), int(self.image.shape[0])


@dataclass(frozen=True)
class DepthMap:
    """Depth of one view from multi-view stereo."""

    view: int  # index of the reference view
    depth_m: np.ndarray  # (H, W) float32 z-depth along the camera's optical axis, m; NaN where unknown
    confidence: np.ndarray | None = None  # (H, W) float32 in [0, 1] (e.g. NCC or consistency), or None


@dataclass(frozen=True)
class SupportPlane:
    """The plane the part stands on (table top), n . p = d with n pointing up (towards the cameras)."""

    normal: np.ndarray  # (3,) unit, world
    d_m: float  # offset, m
    inlier_rms_m: float  # RMS distance of the RANSAC inliers, m

    def height(self, p_world: np.ndarray) -> np.ndarray:
        """(N,) signed height of points above the plane, m."""
        return np.asarray(p_world, float) @ self.normal - self.d_m


@dataclass(frozen=True)
class Roi:
    """The region of interest: an axis-aligned box in the support frame (z up from the plane), metres."""

    world_T_support: np.ndarray  # (4, 4) support frame (origin on the plane, z = plane normal) in world
    lo: np.ndarray  # (3,) min corner in the support frame, m
    hi: np.ndarray  # (3,) max corner in the support frame, m


@dataclass(frozen=True)
class Mesh:
    """A triangle mesh: vertices (V, 3) in metres in the frame named by `frame`, faces (F, 3) counter-clockwise
    seen from outside (outward normals)."""

    vertices: np.ndarray  # (V, 3) float64
    faces: np.ndarray  # (F, 3) int64
    frame: str = "world"  # "world" (the run's world), "support" (the part on its base, z up), "cad" (registered)
    colours: np.ndarray | None = None  # (V, 3) uint8 RGB, optional


@dataclass(frozen=True)
class ModelInfo:
    """What `vio model` did, for model.json."""

    num_views: int
    num_depth_maps: int
    num_dense_points: int
    voxel_m: float
    support: SupportPlane
    roi: Roi
    timings_s: dict[str, float] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
