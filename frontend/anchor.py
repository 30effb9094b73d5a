"""Drift-free tracking: each track re-aligned with the patch it had when it was born.

Frame-to-frame KLT (`frontend.tracker`) adds a small error at every step, so a track's pixel wanders from its
surface point as it ages: on the simulated 60 s orbit (seed 401) the median error grows from 0.18 px after one or
two frames to 0.87 px after 31-50 frames (`python -m vio.bench.klt_error`). The original KLT tracker (Shi and
Tomasi, "Good features to track", 1994) answered with an affine model against the feature's first appearance; SVO
aligns each feature with its reference keyframe's patch for the same reason.

`AnchorAligner` keeps, for every live track, its template: the (2r+1)^2 intensities around the pixel where the
track began, in the image it began in. In every frame (or, with the tracker's `anchor_keyframes_only`, in every
keyframe) Gauss-Newton fits, from KLT's new position, the warp

    I(t + A d) = gain * T(d) + bias        for every template offset d

with an affine A, a translation t and the photometric gain and bias, all tracks at once in numpy. It is Baker and
Matthews' inverse compositional algorithm with the appearance "projected out" ("Lucas-Kanade 20 years on", 2004):
the template's steepest-descent images (its gradient times the warp's Jacobian) are made orthogonal to the template
and to a constant when the template is taken, so gain and bias drop out of the warp's equations, and their 6x6
Gauss-Newton matrix is inverted once per template; an iteration is then one bilinear sample of the frame under the
warp and two small matrix products (half the time of the forward-additive fit with all eight parameters that came
before it, for the same error by track age: docs/BENCHMARKS.md). The step is divided by the patch's contrast
against the template (the gain, to first order). The fitted t is the track's new pixel: its error no longer adds
up along the track, since every frame is compared with the same template. A track whose fit fails (a singular
step, a shift from KLT's position over `anchor_max_shift_px`, a correlation under `anchor_min_ncc`, or an
affine stretched beyond `anchor_max_stretch`: the view has changed too much for one affine) keeps KLT's pixel and
takes a new template there (re-anchoring), as a tracker without templates would have done every frame.
"""

from __future__ import annotations

import cv2
import numpy as np

from vio.config import TrackerConfig

_DAMPING = 1e-6  # relative damping of the templates' Gauss-Newton matrices (keeps flat patches invertible)
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
        d = np.arange(-r - 1, r + 2, dtype=np.float64)  # one pixel of margin for the template's gradients
        dx, dy = np.meshgrid(d, d)
        self._d = np.column_stack([dx.ravel(), dy.ravel()])  # (Q, 2) offsets with the margin, px, row-major
        self._side = d.size
        inner = np.zeros((d.size, d.size), bool)
        inner[1:-1, 1:-1] = True
        self._inner = self._d[inner.ravel()]  # (P, 2) the template's (2r+1)^2 offsets
        p = self._inner.shape[0]
        self._t = np.zeros((0, p), np.float32)  # (N, P) templates
        self._sd = np.zeros((0, 6, p), np.float32)  # (N, 6, P) steepest-descent images, photometry projected out
        self._hinv = np.zeros((0, 6, 6))  # (N, 6, 6) their inverse Gauss-Newton matrices
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
        self._t, self._sd, self._hinv, self._a = self._t[idx], self._sd[idx], self._hinv[idx], self._a[idx]

    def add(self, prepared: np.ndarray, uv: np.ndarray) -> None:
        """Append templates for new tracks at (M, 2) pixels of the frame `prepared` (from `prepare`)."""
        t, sd, hinv = self._templates(prepared, uv)
        self._t = np.vstack([self._t, t])
        self._sd = np.concatenate([self._sd, sd])
        self._hinv = np.concatenate([self._hinv, hinv])
        self._a = np.concatenate([self._a, np.broadcast_to(np.eye(2), (t.shape[0], 2, 2))])

    @staticmethod
    def _warped(image: np.ndarray, d: np.ndarray, t: np.ndarray, a: np.ndarray) -> np.ndarray:
        """(N, Q) float32 samples of the image at the (Q, 2) offsets `d` under the warps t + a d."""
        dx, dy = d[:, 0], d[:, 1]
        x = (t[:, 0, None] + a[:, 0, 0, None] * dx + a[:, 0, 1, None] * dy).astype(np.float32)
        y = (t[:, 1, None] + a[:, 1, 0, None] * dx + a[:, 1, 1, None] * dy).astype(np.float32)
        return _sample(image, x, y)

    def _templates(self, prepared: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Templates at (M, 2) pixels, their steepest-descent images and inverse Gauss-Newton matrices: the
        template's gradient times the affine's Jacobian, each made orthogonal to the template and to a constant
        (Baker and Matthews' "project out": gain and bias then drop out of the warp's equations)."""
        uv = np.asarray(uv, np.float64).reshape(-1, 2)
        m, k = uv.shape[0], self._side
        s = self._warped(prepared, self._d, uv, np.broadcast_to(np.eye(2), (m, 2, 2))).reshape(m, k, k)
        p = self._inner.shape[0]
        t = np.ascontiguousarray(s[:, 1:-1, 1:-1]).reshape(m, p)
        gx = 0.5 * (s[:, 1:-1, 2:] - s[:, 1:-1, :-2]).reshape(m, p)
        gy = 0.5 * (s[:, 2:, 1:-1] - s[:, :-2, 1:-1]).reshape(m, p)
        dx, dy = self._inner[:, 0].astype(np.float32), self._inner[:, 1].astype(np.float32)
        sd = np.stack([gx * dx, gx * dy, gy * dx, gy * dy, gx, gy], axis=1)  # d(warp)/d(a11 a12 a21 a22 tx ty)
        sd -= sd.mean(axis=2, keepdims=True)  # orthogonal to a constant (the bias)
        tc = t - t.mean(axis=1, keepdims=True)
        norm = np.maximum((tc * tc).sum(axis=1), 1e-12)
        sd -= (np.matmul(sd, tc[:, :, None]) / norm[:, None, None]) * tc[:, None, :]  # and to the template (gain)
        h = np.matmul(sd, sd.transpose(0, 2, 1)).astype(np.float64)
        h += (_DAMPING * np.trace(h, axis1=1, axis2=2)[:, None, None] + 1e-9) * np.eye(6)
        return t, sd, np.linalg.inv(h)

    def align(self, prepared: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """(N, 2) pixels of the first N live tracks (all, or the older ones before new detections) aligned with
        their templates in this frame, from KLT's (N, 2) `uv`; the tracks that fail keep `uv` and are re-anchored
        there. Inverse compositional Gauss-Newton: each iteration one sample of the image under the warp, and the
        step from the template's precomputed matrices, divided by the patch's gain against the template."""
        cfg = self.cfg
        n = uv.shape[0]
        if n == 0:
            return uv
        if n > len(self):
            raise ValueError(f"{n} pixels to align but {len(self)} templates")
        T = self._t[:n]
        tc = T - T.mean(axis=1, keepdims=True)
        tnorm = np.maximum((tc * tc).sum(axis=1), 1e-12)
        a = self._a[:n].copy()
        t = np.asarray(uv, np.float64).copy()
        ok = np.ones(n, bool)
        act = np.arange(n)  # the tracks still iterating
        for _ in range(int(cfg.anchor_iterations)):
            if act.size == 0:
                break
            w = self._warped(prepared, self._inner, t[act], a[act])
            e = w - T[act]
            gain = (w * tc[act]).sum(axis=1) / tnorm[act]  # the patch's contrast against the template's
            b = np.matmul(self._sd[act], e[:, :, None])[:, :, 0].astype(np.float64)
            dp = np.matmul(self._hinv[act], b[:, :, None])[:, :, 0] / np.clip(gain, 0.2, 5.0)[:, None]
            # compose with the inverse of the step's warp: A <- A (I + dA)^-1, t <- t - A (I + dA)^-1 dt
            m11, m12, m21, m22 = 1.0 + dp[:, 0], dp[:, 1], dp[:, 2], 1.0 + dp[:, 3]
            det = m11 * m22 - m12 * m21
            good = np.isfinite(dp).all(axis=1) & (np.abs(det) > 1e-3)
            det[~good] = 1.0
            minv = np.stack([m22, -m12, -m21, m11], axis=1).reshape(-1, 2, 2) / det[:, None, None]
            a_new = np.matmul(a[act], minv)
            move = -np.matmul(a_new, dp[:, 4:6, None])[:, :, 0]
            ok[act[~good]] = False
            a[act[good]] = a_new[good]
            t[act[good]] += move[good]
            near = np.linalg.norm(t[act] - uv[act], axis=1) <= cfg.anchor_max_shift_px
            act = act[good & near & (np.abs(move).max(axis=1) >= _STOP_PX)]
        sv = np.linalg.svd(a, compute_uv=False)
        stretch = float(cfg.anchor_max_stretch)
        ok &= np.isfinite(t).all(axis=1) & (np.linalg.norm(t - uv, axis=1) <= cfg.anchor_max_shift_px)
        ok &= (sv[:, 0] <= stretch) & (sv[:, 1] >= 1.0 / stretch)
        fitted = self._warped(prepared, self._inner, t[ok], a[ok])
        ok[ok] &= zncc_rows(T[ok].astype(np.float64), fitted.astype(np.float64)) >= cfg.anchor_min_ncc
        out = np.where(ok[:, None], t, uv)
        self._a[:n] = np.where(ok[:, None, None], a, np.eye(2))
        fail = np.flatnonzero(~ok)
        if fail.size:
            self._t[fail], self._sd[fail], self._hinv[fail] = self._templates(prepared, uv[fail])
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
