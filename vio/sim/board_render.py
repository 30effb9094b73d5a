"""Images of a planar calibration board seen by a pinhole-radtan camera (the calibration oracle).

Each output pixel (distorted image) is undistorted to a normalized ray, the ray meets the board plane through the
inverse homography of `cam_T_board`, and the board's texture is sampled there (bilinear, on a 2x supersampled
grid averaged down, so edges are anti-aliased like a real sensor's). Board frame: x along the columns, y along the
rows, z into the board (OpenCV's), metres; the texture covers [-margin, w + margin] x [-margin, h + margin].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vio.records import CameraCalib

TEXTURE_PX_PER_M = 8000.0  # board texture resolution: 8 px per mm
SUPERSAMPLE = 2
WALL_GREY = 140  # what the camera sees beyond the board's margin


@dataclass(frozen=True)
class BoardTexture:
    """A board's picture and where it lies in the board frame."""

    image: np.ndarray  # (H, W) uint8 texture
    origin_m: np.ndarray  # (2,) board-frame (x, y) of the texture's pixel (0, 0) centre, m
    px_per_m: float  # texture pixels per metre


def chessboard_texture(cols: int, rows: int, square_m: float, px_per_m: float = TEXTURE_PX_PER_M) -> BoardTexture:
    """A chessboard with `cols` x `rows` inner corners (corner (0, 0) at the board origin), one square of white
    margin around it."""
    nx, ny = cols + 1, rows + 1  # squares
    sq = int(round(square_m * px_per_m))
    img = np.full(((ny + 2) * sq, (nx + 2) * sq), 255, np.uint8)
    for j in range(ny):
        for i in range(nx):
            if (i + j) % 2 == 0:
                img[(j + 1) * sq : (j + 2) * sq, (i + 1) * sq : (i + 2) * sq] = 0
    # the square (0, 0) spans [-square, 0] in the board frame (the first inner corner is the origin), the margin
    # another square: the texture's edge is at -2 squares; its first pixel's centre half a pixel in
    scale = sq / square_m
    return BoardTexture(img, np.full(2, -2.0 * square_m + 0.5 / scale), scale)


def charuco_texture(
    cols: int, rows: int, square_m: float, marker_m: float, dictionary: str, px_per_m: float = TEXTURE_PX_PER_M
) -> BoardTexture:
    """OpenCV's ChArUco board of `cols` x `rows` squares (its corners' board frame), one square of margin."""
    import cv2

    sq = int(round(square_m * px_per_m))
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    board = cv2.aruco.CharucoBoard((cols, rows), square_m, marker_m, d)
    inner = board.generateImage((cols * sq, rows * sq), marginSize=0, borderBits=1)
    img = np.full((rows * sq + 2 * sq, cols * sq + 2 * sq), 255, np.uint8)
    img[sq:-sq, sq:-sq] = inner
    scale = sq / square_m
    return BoardTexture(img, np.array([-square_m, -square_m]) + 0.5 / scale, scale)


def undistorted_rays(cam: CameraCalib) -> np.ndarray:
    """(H*s, W*s, 2) normalized image coordinates (x/z, y/z) of the supersampled pixel grid of `cam`'s distorted
    image (s = SUPERSAMPLE): computed once per camera, shared by every view."""
    import cv2

    s = SUPERSAMPLE
    u, v = np.meshgrid((np.arange(cam.width * s) + 0.5) / s - 0.5, (np.arange(cam.height * s) + 0.5) / s - 0.5)
    pix = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
    K = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1.0]])
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)
    xn = cv2.undistortPoints(pix, K, np.asarray(cam.dist, float), None, None, None, criteria)
    return xn.reshape(u.shape + (2,))


def render_board(
    tex: BoardTexture,
    cam: CameraCalib,
    cam_T_board: np.ndarray,
    rays: np.ndarray,
    rng: np.random.Generator | None = None,
    noise_sigma: float = 0.0,
) -> np.ndarray:
    """The (height, width) uint8 image of the board at `cam_T_board` (4x4, board frame in the camera frame, m)
    through `cam` whose `rays` are `undistorted_rays(cam)`; `noise_sigma` grey levels of noise drawn from `rng`."""
    import cv2

    R, t = cam_T_board[:3, :3], cam_T_board[:3, 3]
    H_inv = np.linalg.inv(np.column_stack([R[:, 0], R[:, 1], t]))  # camera ray -> board (x, y, 1) up to scale
    x, y = rays[..., 0], rays[..., 1]
    bx = H_inv[0, 0] * x + H_inv[0, 1] * y + H_inv[0, 2]
    by = H_inv[1, 0] * x + H_inv[1, 1] * y + H_inv[1, 2]
    bz = H_inv[2, 0] * x + H_inv[2, 1] * y + H_inv[2, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        map_x = ((bx / bz - tex.origin_m[0]) * tex.px_per_m).astype(np.float32)
        map_y = ((by / bz - tex.origin_m[1]) * tex.px_per_m).astype(np.float32)
    map_x[~(bz > 0)] = -1e6  # rays that meet the plane behind the camera see the wall
    img = cv2.remap(tex.image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=WALL_GREY)
    img = cv2.resize(img.astype(np.float32), (cam.width, cam.height), interpolation=cv2.INTER_AREA)
    if rng is not None and noise_sigma > 0:
        img = img + rng.normal(0.0, noise_sigma, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)
