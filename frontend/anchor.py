"""Drift-free tracking: each track re-aligned, every frame, with the patch it had when it was born.

Frame-to-frame KLT (`frontend.tracker`) adds a small error at every step, so a track's pixel wanders from its
surface point as it ages: on the simulated 60 s orbit (seed 401) the median error grows from 0.18 px after one or
two frames to 0.87 px after 31-50 frames (`python -m vio.bench.klt_error`). The original KLT tracker (Shi and
Tomasi, "Good features to track", 1994) answered with an affine model against the feature's first appearance; SVO
aligns each feature with its reference keyframe's patch for the same reason.

`AnchorAligner` keeps, for every live track, its template: the (2r+1)^2 intensities around the pixel where the
track began, in the image it began in. Each frame, starting from KLT's new position, Gauss-Newton fits the warp

    I(t + A d) = gain * T(d) + bias        for every template offset d

(forward additive Lucas-Kanade with an affine A, a translation t and the photometric gain and bias, eight
parameters per track, all tracks at once in numpy). The fitted t is the track's new pixel: its error no longer adds
up along the track, since every frame is compared with the same template. A track whose fit fails (a singular
system or warp, a shift from KLT's position over `anchor_max_shift_px`, a correlation under `anchor_min_ncc`, or an
affine stretched beyond `anchor_max_stretch`: the view has changed too much for one affine) keeps KLT's pixel and
takes a new template there (re-anchoring), as a tracker without templates would have done every frame.
"""

from __future__ import annotations

import cv2
import numpy as np

from vio.config import TrackerConfig

_DAMPING = 1e-6  # relative Levenberg-Marquardt damping of the normal equations (keeps flat patches solvable)
_STOP_PX = 0.01  # iteration ends when no track's translation step exceeds this, px


def _sample(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples of a float32 (H, W[, C]) image at (N, P) float32 positions x, y: (N, P[, C]) float32."""
    if x.shape[0] == 0:
        return np.zeros(x.shape + image.shape[2:], np.float32)
    return cv2.remap(image, x, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


class AnchorAligner:
    """Templates and warps of the tracker's live tracks, in the tracker's order (see the module docstring)."""

    def __init__(self, cfg: TrackerConfig) -> None:
        self.cfg = cfg
        r = int(cfg.anchor_radius_px)
        d = np.arange(-r - 1, r + 2, dtype=np.float64)  # one pixel of margin for the gradients
        dx, dy = np.meshgrid(d, d)
        self._d = np.column_stack([dx.ravel(), dy.ravel()])  # (Q, 2) sampled offsets, px, row-major
        self._side = d.size
        inner = np.zeros((d.size, d.size), bool)
        inner[1:-1, 1:-1] = True
        inner = inner.ravel()  # the (2r+1)^2 offsets of the template among them
        self._dx = self._d[inner, 0].astype(np.float32)
        self._dy = self._d[inner, 1].astype(np.float32)
        self._t = np.zeros((0, int(inner.sum())), np.float32)  # (N, P) templates
        self._a = np.zeros((0, 2, 2))  # (N, 2, 2) affine warps, template to image
        self.stats = {"aligned": 0, "reanchored": 0}

    def __len__(self) -> int:
        return self._t.shape[0]

    @staticmethod
    def prepare(gray: np.ndarray) -> np.ndarray:
        """The frame as float32, sampled bilinearly by the alignment."""
        return gray.astype(np.float32)

    def keep(self, idx: np.ndarray) -> None:
        """Keep only the tracks at `idx` (the tracker's survivors), in that order."""
        self._t = self._t[idx]
        self._a = self._a[idx]

    def add(self, prepared: np.ndarray, uv: np.ndarray) -> None:
        """Append templates for new tracks at (M, 2) pixels of the frame `prepared` (from `prepare`)."""
        t = self._templates(prepared, uv)
        self._t = np.vstack([self._t, t])
        self._a = np.concatenate([self._a, np.broadcast_to(np.eye(2), (t.shape[0], 2, 2))])

    def _warped(self, image: np.ndarray, t: np.ndarray, a: np.ndarray) -> np.ndarray:
        """(N, S, S) float32 samples of the image at the offsets (with margin) under the warps t + a d."""
        dx, dy = self._d[:, 0], self._d[:, 1]
        x = (t[:, 0, None] + a[:, 0, 0, None] * dx + a[:, 0, 1, None] * dy).astype(np.float32)
        y = (t[:, 1, None] + a[:, 1, 0, None] * dx + a[:, 1, 1, None] * dy).astype(np.float32)
        return _sample(image, x, y).reshape(-1, self._side, self._side)

    def _templates(self, prepared: np.ndarray, uv: np.ndarray) -> np.ndarray:
        uv = np.asarray(uv, np.float64).reshape(-1, 2)
        s = self._warped(prepared, uv, np.broadcast_to(np.eye(2), (uv.shape[0], 2, 2)))
        return np.ascontiguousarray(s[:, 1:-1, 1:-1]).reshape(uv.shape[0], self._t.shape[1])

    def align(self, prepared: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """(N, 2) pixels of the first N live tracks (all, or the older ones before new detections) aligned with
        their templates in this frame, from KLT's (N, 2) `uv`; the tracks that fail keep `uv` and are re-anchored
        there."""
        cfg = self.cfg
        n = uv.shape[0]
        if n == 0:
            return uv
        if n > len(self):
            raise ValueError(f"{n} pixels to align but {len(self)} templates")
        dx, dy = self._dx, self._dy
        T = self._t[:n]
        a = self._a[:n].copy()
        t = np.asarray(uv, np.float64).copy()
        gain = np.ones(n)
        bias = np.zeros(n)
        ok = np.ones(n, bool)
        eye = np.eye(8)
        act = np.arange(n)  # the tracks still iterating
        for _ in range(int(cfg.anchor_iterations)):
            if act.size == 0:
                break
            m = act.size
            aa = a[act]
            s = self._warped(prepared, t[act], aa)
            # gradients along the template's axes (central differences), then in the image: grad I = g_d A^-1
            gu = 0.5 * (s[:, 1:-1, 2:] - s[:, 1:-1, :-2]).reshape(m, -1)
            gv = 0.5 * (s[:, 2:, 1:-1] - s[:, :-2, 1:-1]).reshape(m, -1)
            det = aa[:, 0, 0] * aa[:, 1, 1] - aa[:, 0, 1] * aa[:, 1, 0]
            flat = ~(np.abs(det) > 1e-3)  # a collapsed warp (or NaN): the track fails, its step is void
            ok[act[flat]] = False
            det[flat] = 1.0
            inv = (np.stack([aa[:, 1, 1], -aa[:, 0, 1], -aa[:, 1, 0], aa[:, 0, 0]], axis=1) / det[:, None]).reshape(
                m, 2, 2
            )
            inv[flat] = np.eye(2)
            inv = inv.astype(np.float32)
            gx = gu * inv[:, 0, 0, None] + gv * inv[:, 1, 0, None]
            gy = gu * inv[:, 0, 1, None] + gv * inv[:, 1, 1, None]
            Ta = T[act]
            r = s[:, 1:-1, 1:-1].reshape(m, -1) - (gain[act, None] * Ta + bias[act, None]).astype(np.float32)
            J = np.empty((m, 8, dx.size), np.float32)  # rows: a11, a12, a21, a22, tx, ty, gain, bias
            J[:, 0], J[:, 1], J[:, 2], J[:, 3], J[:, 4], J[:, 5] = gx * dx, gx * dy, gy * dx, gy * dy, gx, gy
            J[:, 6], J[:, 7] = -Ta, -1.0
            H = np.matmul(J, J.transpose(0, 2, 1)).astype(np.float64)
            H += (_DAMPING * np.trace(H, axis1=1, axis2=2)[:, None, None] + 1e-9) * eye
            g = -np.matmul(J, r[..., None])[..., 0].astype(np.float64)
            step = np.linalg.solve(H, g[..., None])[..., 0]
            good = np.isfinite(step).all(axis=1) & ~flat
            ok[act[~good]] = False
            step[~good] = 0.0
            a[act] += step[:, :4].reshape(m, 2, 2)
            t[act] += step[:, 4:6]
            gain[act] += step[:, 6]
            bias[act] += step[:, 7]
            near = np.linalg.norm(t[act] - uv[act], axis=1) <= cfg.anchor_max_shift_px
            act = act[good & near & (np.abs(step[:, 4:6]).max(axis=1) >= _STOP_PX)]
        sv = np.linalg.svd(a, compute_uv=False)
        stretch = float(cfg.anchor_max_stretch)
        ok &= np.isfinite(t).all(axis=1) & (np.linalg.norm(t - uv, axis=1) <= cfg.anchor_max_shift_px)
        ok &= (sv[:, 0] <= stretch) & (sv[:, 1] >= 1.0 / stretch)
        fitted = self._warped(prepared, t[ok], a[ok])[:, 1:-1, 1:-1].reshape(-1, T.shape[1])
        ok[ok] &= zncc_rows(T[ok].astype(np.float64), fitted.astype(np.float64)) >= cfg.anchor_min_ncc
        out = np.where(ok[:, None], t, uv)
        self._a[:n] = np.where(ok[:, None, None], a, np.eye(2))
        fail = np.flatnonzero(~ok)
        if fail.size:
            self._t[fail] = self._templates(prepared, uv[fail])
        self.stats["aligned"] += int(ok.sum())
        self.stats["reanchored"] += int(fail.size)
        return out


def zncc_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N,) zero-mean normalized cross-correlation of (N, P) rows (1: identical up to gain and offset), computed in
    the inputs' precision."""
    a = a - a.mean(axis=1, keepdims=True)
    b = b - b.mean(axis=1, keepdims=True)
    den = np.sqrt((a * a).sum(axis=1) * (b * b).sum(axis=1))
    return np.where(den > 0, (a * b).sum(axis=1) / np.maximum(den, 1e-12), 0.0)
