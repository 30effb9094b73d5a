"""Camera intrinsics from views of a board (OpenCV), with outlier views dropped and parameter uncertainties.

Models (`model`):
- `radtan`: pinhole with Kalibr's radial-tangential distortion k1, k2, p1, p2 (OpenCV with k3 fixed at 0), the
  model `vio run` reads;
- `equidistant`: Kalibr's equidistant (OpenCV fisheye) k1..k4;
- `opencv`: OpenCV's default five coefficients k1, k2, p1, p2, k3 (default flags, as in OpenCV's own calibration
  test); not a Kalibr model, so it is for comparison only.
Outliers: after each solve, views whose RMS reprojection error exceeds `OUTLIER_FACTOR` x the median view RMS (and
`OUTLIER_FLOOR_PX`) are dropped and the calibration repeated. Standard deviations are OpenCV's
(`calibrateCameraExtended`: sigma^2 (J^T J)^-1 with sigma^2 the residual variance); for the fisheye model the same
formula on `cv2.fisheye.projectPoints`' Jacobian.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from vio.calibrate.board import Board
from vio.calibrate.views import View
from vio.errors import CalibrationError

log = logging.getLogger(__name__)

MODELS = ("radtan", "equidistant", "opencv")
DIST_NAMES = {"radtan": ("k1", "k2", "p1", "p2"), "equidistant": ("k1", "k2", "k3", "k4")}
DIST_NAMES["opencv"] = ("k1", "k2", "p1", "p2", "k3")
MIN_VIEWS = 3
OUTLIER_FACTOR = 3.0  # a view is an outlier above this many times the median view RMS ...
OUTLIER_FLOOR_PX = 0.5  # ... and above this RMS, px
MAX_ROUNDS = 3
COVERAGE_GRID = (8, 6)  # image cells (columns, rows) counted for the coverage figure


@dataclass(frozen=True)
class CameraCalibration:
    """The result of a camera calibration. Pixel coordinates are in the distorted image."""

    model: str  # radtan | equidistant | opencv
    width: int  # px
    height: int  # px
    fx: float  # px
    fy: float  # px
    cx: float  # px
    cy: float  # px
    dist: np.ndarray  # distortion coefficients named by DIST_NAMES[model]
    rms_px: float  # RMS reprojection error over every corner of the views used, px
    std: dict[str, float]  # one standard deviation of fx, fy, cx, cy (px) and each distortion coefficient
    view_names: tuple[str, ...]  # the views used
    view_rms_px: np.ndarray  # (V,) RMS reprojection error per view used, px
    uv: tuple[np.ndarray, ...]  # per view (N, 2) detected corners, px
    residuals_px: tuple[np.ndarray, ...]  # per view (N, 2) detected minus projected, px
    dropped: tuple[tuple[str, str], ...]  # (view, reason) dropped as outliers
    coverage: float  # fraction of the COVERAGE_GRID image cells holding a corner of a used view

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def params(self) -> dict[str, float]:
        """fx, fy, cx, cy and the distortion coefficients by name."""
        out = {"fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy}
        out.update({n: float(v) for n, v in zip(DIST_NAMES[self.model], self.dist, strict=True)})
        return out


def _solve_pinhole(obj, img, size, model):
    import cv2

    flags = cv2.CALIB_FIX_K3 if model == "radtan" else 0
    rms, K, dist, rvecs, tvecs, std_int, _, _ = cv2.calibrateCameraExtended(obj, img, size, None, None, flags=flags)
    n_dist = len(DIST_NAMES[model])
    dist = np.asarray(dist, float).ravel()[:n_dist]
    std = np.asarray(std_int, float).ravel()[: 4 + n_dist]
    residuals = []
    for o, i, r, t in zip(obj, img, rvecs, tvecs, strict=True):
        proj, _ = cv2.projectPoints(o, r, t, K, np.asarray(dist))
        residuals.append(i.reshape(-1, 2) - proj.reshape(-1, 2))
    return K, dist, std, residuals


def _solve_fisheye(obj, img, size):
    import cv2

    obj = [o.reshape(1, -1, 3).astype(np.float64) for o in obj]
    img = [i.reshape(1, -1, 2).astype(np.float64) for i in img]
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-10)
    flags = cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW
    _, K, D, rvecs, tvecs = cv2.fisheye.calibrate(
        obj, img, size, np.eye(3), np.zeros(4), flags=flags, criteria=criteria
    )
    dist = np.asarray(D, float).ravel()
    n_views = len(obj)
    residuals, blocks = [], []
    for o, i, r, t in zip(obj, img, rvecs, tvecs, strict=True):
        proj, jac = cv2.fisheye.projectPoints(o, r, t, K, D, alpha=0.0)
        residuals.append(i.reshape(-1, 2) - proj.reshape(-1, 2))
        blocks.append(np.asarray(jac, float))
    # The full Jacobian: 8 shared intrinsics (f, c, k) then 6 extrinsics per view (rvec, tvec); skew is fixed.
    n_rows = sum(b.shape[0] for b in blocks)
    J = np.zeros((n_rows, 8 + 6 * n_views))
    row = 0
    for v, b in enumerate(blocks):
        J[row : row + b.shape[0], :8] = b[:, :8]
        J[row : row + b.shape[0], 8 + 6 * v : 14 + 6 * v] = b[:, 8:14]
        row += b.shape[0]
    r = np.concatenate([res.ravel() for res in residuals])
    sigma2 = float(r @ r) / max(r.size - J.shape[1], 1)
    cov = sigma2 * np.linalg.pinv(J.T @ J)
    std = np.sqrt(np.maximum(np.diag(cov)[:8], 0.0))
    return K, dist, std, residuals


def _coverage(uv: list[np.ndarray], size: tuple[int, int]) -> float:
    nx, ny = COVERAGE_GRID
    pts = np.vstack(uv)
    ix = np.clip((pts[:, 0] / size[0] * nx).astype(int), 0, nx - 1)
    iy = np.clip((pts[:, 1] / size[1] * ny).astype(int), 0, ny - 1)
    return len(set(zip(ix.tolist(), iy.tolist(), strict=True))) / (nx * ny)


def calibrate_camera(
    views: list[View], board: Board, size: tuple[int, int], model: str = "radtan"
) -> CameraCalibration:
    """Intrinsics of the camera that took `views` of `board` (images of `size` = (width, height) px).

    Outlier views are dropped (see the module docstring); CalibrationError when fewer than MIN_VIEWS remain or
    OpenCV's solver fails.
    """
    import cv2

    if model not in MODELS:
        raise CalibrationError(f"camera model must be one of {', '.join(MODELS)}, got {model!r}")
    corners = board.corners_board()
    active = list(views)
    dropped: list[tuple[str, str]] = []
    for round_ in range(MAX_ROUNDS + 1):
        if len(active) < MIN_VIEWS:
            raise CalibrationError(
                f"only {len(active)} usable view(s) of the board; at least {MIN_VIEWS} are needed "
                "(more, from different angles and distances, give a better calibration)"
            )
        obj = [corners[v.detection.ids].astype(np.float32) for v in active]
        img = [v.detection.uv.astype(np.float32).reshape(-1, 1, 2) for v in active]
        try:
            if model == "equidistant":
                K, dist, std, residuals = _solve_fisheye(obj, img, size)
            else:
                K, dist, std, residuals = _solve_pinhole(obj, img, size, model)
        except cv2.error as exc:
            msg = str(exc).strip().splitlines()[-1] if str(exc).strip() else "solver failed"
            raise CalibrationError(f"OpenCV calibration failed ({msg}); check the board spec and the views") from None
        view_rms = np.array([np.sqrt(np.mean(np.sum(r**2, axis=1))) for r in residuals])
        limit = max(OUTLIER_FACTOR * float(np.median(view_rms)), OUTLIER_FLOOR_PX)
        bad = np.flatnonzero(view_rms > limit)
        if bad.size == 0 or round_ == MAX_ROUNDS:
            break
        for i in bad:
            reason = f"RMS {view_rms[i]:.2f} px > {limit:.2f} px ({OUTLIER_FACTOR:g} x the median view RMS)"
            dropped.append((active[i].name, reason))
            log.info("dropped %s: %s", active[i].name, reason)
        active = [v for i, v in enumerate(active) if i not in set(bad.tolist())]
    all_res = np.vstack(residuals)
    names = ("fx", "fy", "cx", "cy") + DIST_NAMES[model]
    uv = tuple(v.detection.uv for v in active)
    return CameraCalibration(
        model=model,
        width=int(size[0]),
        height=int(size[1]),
        fx=float(K[0, 0]),
        fy=float(K[1, 1]),
        cx=float(K[0, 2]),
        cy=float(K[1, 2]),
        dist=np.asarray(dist, float),
        rms_px=float(np.sqrt(np.mean(np.sum(all_res**2, axis=1)))),
        std={n: float(s) for n, s in zip(names, std, strict=True)},
        view_names=tuple(v.name for v in active),
        view_rms_px=view_rms,
        uv=uv,
        residuals_px=tuple(residuals),
        dropped=tuple(dropped),
        coverage=_coverage(list(uv), size),
    )
