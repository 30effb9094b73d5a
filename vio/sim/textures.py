"""Procedural, band-limited surface textures with strong corners (Shi-Tomasi/KLT friendly) and their mip pyramids.

A face texture is drawn at the box's texel size (metres per texel): a smooth multi-scale tone, then overlapping
random rectangles (axis-aligned and rotated), ellipses and bars whose sizes are log-uniform over a range in
metres chosen per style (so features exist at every viewing distance the scenarios use), then a Gaussian blur of
about one texel (band limit). Every face gets its own random stream, so faces look different.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from vio.sim.scene import Box, Scene


@dataclass(frozen=True)
class Style:
    size_min_m: float  # smallest feature, m
    size_max_m: float  # largest feature, m
    coverage: float  # expected summed feature area / face area
    margin_m: float = 0.0  # plain border band (a printed label's margin), m
    margin_tone: float = 0.85  # its brightness (before the face's shading)


STYLES = {
    "object": Style(0.003, 0.022, 2.5, margin_m=0.005),
    "table": Style(0.008, 0.15, 2.5),
    "wall": Style(0.03, 0.5, 2.0),
    "furniture": Style(0.02, 0.3, 2.0),
}
_MAX_SHAPES = 30000


def face_texture(box: Box, face: int, rng: np.random.Generator) -> np.ndarray:
    """(h, w) float32 texture in [0, 1] of one face; texel (i, j) sits at (lo_u + j * texel, lo_v + i * texel)."""
    _, _, su, sv = box.face_extent(face)
    w = int(np.ceil(su / box.texel_m)) + 1
    h = int(np.ceil(sv / box.texel_m)) + 1
    style = STYLES[box.style]
    tone = rng.uniform(0.35, 0.65)
    img = np.full((h, w), tone, np.float32)
    for cells, amp in ((4, 0.12), (16, 0.06)):  # slow tone variation over the face
        coarse = rng.uniform(-amp, amp, (max(2, h * cells // max(w, h)), max(2, w * cells // max(w, h))))
        img += cv2.resize(coarse.astype(np.float32), (w, h), interpolation=cv2.INTER_CUBIC)
    a, b = np.log(style.size_min_m), np.log(style.size_max_m)
    mean_area = (style.size_max_m**2 - style.size_min_m**2) / (2.0 * (b - a))
    count = int(min(_MAX_SHAPES, style.coverage * su * sv / mean_area))
    sizes = np.exp(rng.uniform(a, b, count)) / box.texel_m  # texels
    centres = rng.uniform(0.0, 1.0, (count, 2)) * np.array([w, h])
    grey = rng.uniform(0.03, 0.97, count)
    kind = rng.uniform(0.0, 1.0, count)
    aspect = np.exp(rng.uniform(-0.9, 0.9, count))
    angle = rng.uniform(0.0, np.pi, count)
    shift = 4  # sub-texel drawing precision (cv2 fixed point)
    for i in range(count):
        sx, sy = 0.5 * sizes[i] * aspect[i], 0.5 * sizes[i] / aspect[i]
        c = centres[i]
        colour = float(grey[i])
        if kind[i] < 0.45:  # axis-aligned rectangle
            p0 = np.round((c - [sx, sy]) * 2**shift).astype(np.int64)
            p1 = np.round((c + [sx, sy]) * 2**shift).astype(np.int64)
            cv2.rectangle(img, (int(p0[0]), int(p0[1])), (int(p1[0]), int(p1[1])), colour, -1, cv2.LINE_8, shift)
        elif kind[i] < 0.75:  # rotated rectangle
            ca, sa = np.cos(angle[i]), np.sin(angle[i])
            corners = np.array([[-sx, -sy], [sx, -sy], [sx, sy], [-sx, sy]]) @ np.array([[ca, sa], [-sa, ca]]) + c
            cv2.fillPoly(img, [np.round(corners * 2**shift).astype(np.int32)], colour, cv2.LINE_8, shift)
        elif kind[i] < 0.9:  # ellipse (blob)
            centre = (int(round(c[0] * 2**shift)), int(round(c[1] * 2**shift)))
            axes = (int(round(sx * 2**shift)), int(round(sy * 2**shift)))
            cv2.ellipse(img, centre, axes, float(np.degrees(angle[i])), 0.0, 360.0, colour, -1, cv2.LINE_8, shift)
        else:  # bar
            ca, sa = np.cos(angle[i]), np.sin(angle[i])
            hw = max(0.12 * sy, 1.0)
            corners = np.array([[-sx, -hw], [sx, -hw], [sx, hw], [-sx, hw]]) @ np.array([[ca, sa], [-sa, ca]]) + c
            cv2.fillPoly(img, [np.round(corners * 2**shift).astype(np.int32)], colour, cv2.LINE_8, shift)
    if style.margin_m > 0.0:
        m = int(round(style.margin_m / box.texel_m))
        border = np.ones((h, w), bool)
        border[m : h - m, m : w - m] = False
        img[border] = style.margin_tone
    img = cv2.GaussianBlur(img, (0, 0), 1.0)
    return np.clip(img, 0.0, 1.0)


def mip_pyramid(tex: np.ndarray, min_size: int = 8) -> list[np.ndarray]:
    """Levels 0..L: each level low-passes and halves the previous one (texel i of level l+1 sits at 2i of l)."""
    levels = [tex]
    while min(levels[-1].shape) >= 2 * min_size:
        levels.append(cv2.pyrDown(levels[-1]))
    return levels


def scene_textures(scene: Scene) -> dict[int, list[np.ndarray]]:
    """Mip pyramids of every face, keyed by surface id `6 * box_index + face`, seeded from the scene."""
    out: dict[int, list[np.ndarray]] = {}
    seeds = np.random.SeedSequence(scene.texture_seed).spawn(6 * len(scene.boxes))
    for bi, box in enumerate(scene.boxes):
        for f in range(6):
            sid = 6 * bi + f
            if f in box.hidden_faces:  # never seen: a plain stand-in
                out[sid] = [np.full((8, 8), 0.5, np.float32)]
            else:
                out[sid] = mip_pyramid(face_texture(box, f, np.random.default_rng(seeds[sid])))
    return out


@dataclass(frozen=True)
class Atlas:
    """Every mip level of every face packed into one image, so one `cv2.remap` samples a whole frame."""

    image: np.ndarray  # (H, W) float32
    origin: np.ndarray  # (S, L, 2) float32 atlas x, y of texel (0, 0) of surface s at level l
    size_max: np.ndarray  # (S, L, 2) float32 largest valid texel coordinate (w - 1, h - 1)
    levels: np.ndarray  # (S,) int32 number of mip levels


def build_atlas(textures: dict[int, list[np.ndarray]], width: int = 8192, gap: int = 2) -> Atlas:
    """Shelf-pack all levels (tallest first) into rows `width` texels wide, `gap` texels apart."""
    n_s = max(textures) + 1
    n_l = max(len(p) for p in textures.values())
    items = sorted(
        ((img.shape[0], img.shape[1], s, lv) for s, pyr in textures.items() for lv, img in enumerate(pyr)),
        key=lambda it: (-it[0], -it[1], it[2], it[3]),
    )
    origin = np.zeros((n_s, n_l, 2), np.float32)
    size_max = np.zeros((n_s, n_l, 2), np.float32)
    x = y = shelf_h = 0
    for h, w, s, lv in items:
        if x + w > width:
            x, y, shelf_h = 0, y + shelf_h + gap, 0
        origin[s, lv] = (x, y)
        size_max[s, lv] = (w - 1, h - 1)
        x += w + gap
        shelf_h = max(shelf_h, h)
    image = np.zeros((y + shelf_h, width), np.float32)
    for s, pyr in textures.items():
        for lv, img in enumerate(pyr):
            ox, oy = (int(v) for v in origin[s, lv])
            image[oy : oy + img.shape[0], ox : ox + img.shape[1]] = img
    levels = np.zeros(n_s, np.int32)
    for s, pyr in textures.items():
        levels[s] = len(pyr)
    return Atlas(image, origin, size_max, levels)
