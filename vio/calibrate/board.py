"""Calibration boards: the `--board` spec, the board's corner coordinates, and corner detection in one image.

Specs (sizes in millimetres, stored in metres):
- `chessboard:COLSxROWS:SQUARE_MM`: COLS x ROWS *inner* corners (OpenCV's `patternSize`), e.g. `chessboard:9x6:25`;
- `charuco:COLSxROWS:SQUARE_MM:MARKER_MM[:DICT]`: COLS x ROWS *squares*, ArUco markers of MARKER_MM from DICT
  (an OpenCV predefined dictionary name, default `DICT_6X6_250`, e.g. `charuco:7x5:40:30:DICT_4X4_50`).
Board frame: x along the columns, y along the rows, z into the board (OpenCV's convention), metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vio.errors import CalibrationError

DEFAULT_DICT = "DICT_6X6_250"
MIN_CHARUCO_CORNERS = 6  # fewer ChArUco corners than this in a view: too few to constrain a pose with intrinsics
SPEC_HELP = "expected chessboard:COLSxROWS:SQUARE_MM or charuco:COLSxROWS:SQUARE_MM:MARKER_MM[:DICT]"


@dataclass(frozen=True)
class Board:
    """A planar calibration target."""

    kind: str  # "chessboard" | "charuco"
    cols: int  # chessboard: inner corners per row; charuco: squares per row
    rows: int  # chessboard: inner corners per column; charuco: squares per column
    square_m: float  # side of one square, m
    marker_m: float = 0.0  # ArUco marker side (charuco only), m
    dictionary: str = ""  # OpenCV predefined ArUco dictionary name (charuco only)

    @property
    def n_corners(self) -> int:
        """Number of corners the board carries (chessboard inner corners; ChArUco chessboard corners)."""
        if self.kind == "chessboard":
            return self.cols * self.rows
        return (self.cols - 1) * (self.rows - 1)

    def corners_board(self) -> np.ndarray:
        """(n_corners, 3) corner coordinates in the board frame, m; row i is the corner with id i."""
        nx, ny = (self.cols, self.rows) if self.kind == "chessboard" else (self.cols - 1, self.rows - 1)
        xy = np.indices((nx, ny)).T.reshape(-1, 2).astype(np.float64) * self.square_m
        if self.kind == "charuco":  # OpenCV's ChArUco corners start one square in from the board's edge
            xy += self.square_m
        return np.hstack([xy, np.zeros((xy.shape[0], 1))])

    def describe(self) -> str:
        if self.kind == "chessboard":
            return f"chessboard {self.cols}x{self.rows} inner corners, {self.square_m * 1e3:g} mm squares"
        return (
            f"ChArUco {self.cols}x{self.rows} squares of {self.square_m * 1e3:g} mm, "
            f"{self.marker_m * 1e3:g} mm {self.dictionary} markers"
        )


def parse_board(spec: str) -> Board:
    """A `Board` from its `--board` spec (see the module docstring); CalibrationError with the expected form."""
    parts = spec.strip().split(":")
    kind = parts[0].lower()
    try:
        if kind not in ("chessboard", "charuco") or len(parts) < 3:
            raise ValueError
        cols, rows = (int(v) for v in parts[1].lower().split("x"))
        square_m = float(parts[2]) * 1e-3
        if kind == "chessboard":
            if len(parts) != 3:
                raise ValueError
            board = Board("chessboard", cols, rows, square_m)
        else:
            if len(parts) not in (4, 5):
                raise ValueError
            dictionary = parts[4].upper() if len(parts) == 5 else DEFAULT_DICT
            board = Board("charuco", cols, rows, square_m, float(parts[3]) * 1e-3, dictionary)
    except ValueError:
        raise CalibrationError(f"--board {spec!r}: {SPEC_HELP}") from None
    if board.square_m <= 0 or min(board.cols, board.rows) < 3:
        raise CalibrationError(f"--board {spec!r}: at least 3x3 and a positive square size")
    if kind == "charuco":
        if not 0 < board.marker_m < board.square_m:
            raise CalibrationError(f"--board {spec!r}: the marker must be smaller than the square")
        import cv2

        if not hasattr(cv2.aruco, board.dictionary):
            raise CalibrationError(f"--board {spec!r}: unknown ArUco dictionary {board.dictionary}")
    return board


@dataclass(frozen=True)
class Detection:
    """The board's corners found in one image."""

    ids: np.ndarray  # (N,) int corner ids (rows of Board.corners_board())
    uv: np.ndarray  # (N, 2) float64 corner positions in the (distorted) image, px


class BoardDetector:
    """Finds a board's corners in grayscale images (the OpenCV detectors are built once)."""

    def __init__(self, board: Board, method: str = "classic", subpix_half_window_px: int = 5) -> None:
        import cv2

        if method not in ("classic", "sb"):
            raise CalibrationError(f"detector must be 'classic' or 'sb', got {method!r}")
        self.board = board
        self.method = method
        self.half_window = int(subpix_half_window_px)
        self._cv2 = cv2
        self._charuco = None
        if board.kind == "charuco":
            dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board.dictionary))
            cboard = cv2.aruco.CharucoBoard((board.cols, board.rows), board.square_m, board.marker_m, dictionary)
            self._charuco = cv2.aruco.CharucoDetector(cboard)

    def detect(self, gray: np.ndarray) -> Detection | None:
        """The corners in a grayscale uint8 image, or None when the board is not found (or too little of it)."""
        if self._charuco is not None:
            corners, ids, _, _ = self._charuco.detectBoard(gray)
            if ids is None or len(ids) < MIN_CHARUCO_CORNERS:
                return None
            return Detection(np.asarray(ids, int).ravel(), np.asarray(corners, np.float64).reshape(-1, 2))
        cv2 = self._cv2
        size = (self.board.cols, self.board.rows)
        if self.method == "sb":
            found, corners = cv2.findChessboardCornersSB(gray, size, flags=cv2.CALIB_CB_ACCURACY)
        else:
            found, corners = cv2.findChessboardCorners(gray, size)
            if found:  # OpenCV's own calibration test: a 5 px half-window, 30 iterations or 0.1 px
                criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 30, 0.1)
                w = self.half_window
                corners = cv2.cornerSubPix(gray, corners, (w, w), (-1, -1), criteria)
        if not found:
            return None
        return Detection(np.arange(self.board.n_corners), np.asarray(corners, np.float64).reshape(-1, 2))
