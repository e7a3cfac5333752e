"""Board corner detection with OpenCV: chessboard (SB detector, classic fallback) and ChArUco."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from .boards import BoardSpec
from .corner_edges import refine_chessboard_corners

MIN_CORNERS = 6


@dataclasses.dataclass(frozen=True)
class Detection:
    """Corners found in one image: `ids` (n,) into `BoardSpec.corners`, `pixels` (n, 2) float64."""

    ids: np.ndarray
    pixels: np.ndarray


def _canonical_chessboard_order(pixels: np.ndarray, cols: int, rows: int) -> np.ndarray:
    """Undo the detector's 180-degree ambiguity: corner 0 is the one nearest the image's top-left."""
    grid = pixels.reshape(rows, cols, 2)
    first, last = grid[0, 0], grid[-1, -1]
    if first.sum() > last.sum():
        grid = grid[::-1, ::-1]
    return grid.reshape(-1, 2)


def detect_board(image: np.ndarray, board: BoardSpec) -> Detection | None:
    """Find the board's corners in a grey (h, w) or RGB (h, w, 3) uint8 image; None if not found.

    Chessboards: `cv2.findChessboardCornersSB` (exhaustive, accuracy), falling back to the classic
    `findChessboardCorners` refined with `cornerSubPix`; corners are ordered so that corner 0 is the
    one nearest the image's top-left, whatever order the detector returns, then placed where the board's
    edge lines through them meet (`refine_chessboard_corners`: 0.015 px RMS against 0.04 px for the detector
    alone on the POV-Ray flume's JPEG boards). ChArUco: `cv2.aruco.CharucoDetector`, at least 6 corners.
    """
    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    if board.kind == "chessboard":
        size = (board.cols, board.rows)
        found, corners = cv2.findChessboardCornersSB(grey, size, flags=cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY)
        if not found:
            found, corners = cv2.findChessboardCorners(
                grey, size, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
            )
            if not found:
                return None
            criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 60, 1e-4)
            corners = cv2.cornerSubPix(grey, corners, (11, 11), (-1, -1), criteria)
        pixels = _canonical_chessboard_order(corners.reshape(-1, 2).astype(np.float64), board.cols, board.rows)
        pixels, _ = refine_chessboard_corners(grey, pixels, board.rows, board.cols)
        return Detection(np.arange(board.cols * board.rows), pixels)
    detector = cv2.aruco.CharucoDetector(board.charuco_board())
    corners, ids, _, _ = detector.detectBoard(grey)
    if ids is None or len(ids) < MIN_CORNERS:
        return None
    ids = ids.ravel().astype(np.int64)
    order = np.argsort(ids)
    return Detection(ids[order], corners.reshape(-1, 2).astype(np.float64)[order])
