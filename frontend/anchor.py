"""Drift-free tracking: each track re-aligned, every frame, with the patch it had when it was born.

Frame-to-frame KLT (`frontend.tracker`) adds a small error at every step, so a track's pixel wanders from its
surface point as it ages: on the simulated orbit the error grows from about 0.2 px after one or two frames to
1.1 px after 31-50 frames (`python -m vio.bench.klt_error`). The original KLT tracker (Shi and Tomasi, "Good
features to track", 1994) answered with an affine model against the feature's first appearance; SVO aligns each
feature with its reference keyframe's patch for the same reason.

`AnchorAligner` keeps, for every live track, its template: the (2r+1)^2 intensities around the pixel where the
track began, in the image it began in. Each frame, starting from KLT's new position, Gauss-Newton fits the warp

    I(t + A d) = gain * T(d) + bias        for every template offset d

(forward additive Lucas-Kanade with an affine A, a translation t and the photometric gain and bias, eight
parameters per track, all tracks at once in numpy). The fitted t is the track's new pixel: its error no longer adds
up along the track, since every frame is compared with the same template. A track whose fit fails (no
convergence, a shift from KLT's position over `anchor_max_shift_px`, a correlation under `anchor_min_ncc`, or an
affine stretched beyond `anchor_max_stretch`: the view has changed too much for one affine) keeps KLT's pixel and
takes a new template there (re-anchoring), as a tracker without templates would have done every frame.
"""

from __future__ import annotations

import cv2
import numpy as np

from vio.config import TrackerConfig

_DAMPING = 1e-6  # relative Levenberg-Marquardt damping of the normal equations (keeps flat patches solvable)
_STOP_PX = 0.01  # iteration ends when no track's translation step exceeds this, px


def _sample(image: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Bilinear samples of a float32 (H, W[, C]) image at (N, P, 2) positions: (N, P[, C]) float32."""
    n, p = xy.shape[:2]
    if n == 0:
        return np.zeros((0, p) + image.shape[2:], np.float32)
    mx = np.ascontiguousarray(xy[..., 0], np.float32)
    my = np.ascontiguousarray(xy[..., 1], np.float32)
    return cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


class AnchorAligner:
    """Templates and warps of the tracker's live tracks, in the tracker's order (see the module docstring)."""

    def __init__(self, cfg: TrackerConfig) -> None:
        self.cfg = cfg
        r = int(cfg.anchor_radius_px)
        d = np.arange(-r, r + 1, dtype=np.float64)
        dx, dy = np.meshgrid(d, d)
        self._d = np.column_stack([dx.ravel(), dy.ravel()])  # (P, 2) template offsets, px
        self._t = np.zeros((0, self._d.shape[0]), np.float32)  # (N, P) templates
        self._a = np.zeros((0, 2, 2))  # (N, 2, 2) affine warps, template to image
        self.stats = {"aligned": 0, "reanchored": 0}

    def __len__(self) -> int:
        return self._t.shape[0]

    @staticmethod
    def prepare(gray: np.ndarray) -> np.ndarray:
        """(H, W, 3) float32: the image and its x and y gradients (Scharr, per pixel), sampled together."""
        g = gray.astype(np.float32)
        gx = cv2.Scharr(g, cv2.CV_32F, 1, 0, scale=1.0 / 32.0)
        gy = cv2.Scharr(g, cv2.CV_32F, 0, 1, scale=1.0 / 32.0)
        return np.dstack([g, gx, gy])

    def keep(self, idx: np.ndarray) -> None:
        """Keep only the tracks at `idx` (the tracker's survivors), in that order."""
        self._t = self._t[idx]
        self._a = self._a[idx]

    def add(self, prepared: np.ndarray, uv: np.ndarray) -> None:
        """Append templates for new tracks at (M, 2) pixels of the frame `prepared` (from `prepare`)."""
        t = self._templates(prepared, uv)
        self._t = np.vstack([self._t, t])
        self._a = np.concatenate([self._a, np.broadcast_to(np.eye(2), (t.shape[0], 2, 2))])

    def _templates(self, prepared: np.ndarray, uv: np.ndarray) -> np.ndarray:
        return _sample(prepared[..., 0], np.asarray(uv, np.float64).reshape(-1, 1, 2) + self._d[None])

    def align(self, prepared: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """(N, 2) pixels of the N live tracks aligned with their templates in this frame, from KLT's (N, 2) `uv`;
        the tracks that fail keep `uv` and are re-anchored there."""
        cfg = self.cfg
        n = uv.shape[0]
        if n == 0:
            return uv
        d = self._d
        T = self._t
        a = self._a.copy()
        t = np.asarray(uv, np.float64).copy()
        gain = np.ones(n)
        bias = np.zeros(n)
        ok = np.ones(n, bool)
        J = np.empty((n, 8, d.shape[0]), np.float32)  # rows: a11, a12, a21, a22, tx, ty, gain, bias
        J[:, 6] = -T
        J[:, 7] = -1.0
        dx, dy = d[:, 0].astype(np.float32), d[:, 1].astype(np.float32)
        eye = np.eye(8)
        for _ in range(int(cfg.anchor_iterations)):
            s = _sample(prepared, t[:, None, :] + d @ a.transpose(0, 2, 1))  # (N, P, 3)
            gx, gy = s[..., 1], s[..., 2]
            r = s[..., 0] - (gain[:, None] * T + bias[:, None]).astype(np.float32)
            J[:, 0], J[:, 1], J[:, 2], J[:, 3], J[:, 4], J[:, 5] = gx * dx, gx * dy, gy * dx, gy * dy, gx, gy
            H = np.matmul(J, J.transpose(0, 2, 1)).astype(np.float64)
            H += (_DAMPING * np.trace(H, axis1=1, axis2=2)[:, None, None] + 1e-9) * eye
            g = -np.matmul(J, r[..., None])[..., 0].astype(np.float64)
            step = np.linalg.solve(H, g[..., None])[..., 0]
            step[~ok] = 0.0
            bad = ~np.isfinite(step).all(axis=1)
            step[bad] = 0.0
            ok &= ~bad
            a += step[:, :4].reshape(n, 2, 2)
            t += step[:, 4:6]
            gain += step[:, 6]
            bias += step[:, 7]
            if float(np.abs(step[:, 4:6]).max(initial=0.0)) < _STOP_PX:
                break
        ncc = _zncc(T.astype(np.float64), _sample(prepared[..., 0], t[:, None, :] + d @ a.transpose(0, 2, 1)))
        sv = np.linalg.svd(a, compute_uv=False) if n else np.zeros((0, 2))
        stretch = float(cfg.anchor_max_stretch)
        ok &= np.isfinite(t).all(axis=1) & (np.linalg.norm(t - uv, axis=1) <= cfg.anchor_max_shift_px)
        ok &= (ncc >= cfg.anchor_min_ncc) & (sv[:, 0] <= stretch) & (sv[:, 1] >= 1.0 / stretch)
        out = np.where(ok[:, None], t, uv)
        self._a = np.where(ok[:, None, None], a, np.eye(2))
        fail = np.flatnonzero(~ok)
        if fail.size:
            self._t[fail] = self._templates(prepared, uv[fail])
        self.stats["aligned"] += int(ok.sum())
        self.stats["reanchored"] += int(fail.size)
        return out


def _zncc(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N,) zero-mean normalized cross-correlation of (N, P) rows."""
    b = b.astype(np.float64)
    a = a - a.mean(axis=1, keepdims=True)
    b = b - b.mean(axis=1, keepdims=True)
    den = np.sqrt((a * a).sum(axis=1) * (b * b).sum(axis=1))
    return np.where(den > 0, (a * b).sum(axis=1) / np.maximum(den, 1e-12), 0.0)
