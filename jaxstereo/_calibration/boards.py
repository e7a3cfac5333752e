"""Calibration boards: specs, their corners in the board frame, detection (OpenCV) and rendering."""

from __future__ import annotations

import dataclasses
import re

import cv2
import numpy as np

from .._geometry.errors import JaxStereoError

_CHARUCO_DICTS = {name[5:]: getattr(cv2.aruco, name) for name in dir(cv2.aruco) if name.startswith("DICT_")}


@dataclasses.dataclass(frozen=True)
class BoardSpec:
    """A planar calibration board.

    - `chessboard:COLSxROWS:SQUARE`: COLS x ROWS *inner corners* (OpenCV's pattern size), squares of
      SQUARE metres.
    - `charuco:COLSxROWS:SQUARE:MARKER:DICT`: COLS x ROWS *squares* (as `cv2.aruco.CharucoBoard`),
      square and marker sides in metres, an ArUco dictionary name such as `4X4_50`.

    Board frame: corners lie in its plane z = 0, x along the columns, y along the rows, metres.
    """

    kind: str
    cols: int
    rows: int
    square_m: float
    marker_m: float = 0.0
    dictionary: str = ""

    @classmethod
    def parse(cls, text: str) -> "BoardSpec":
        """Parse a board string; raise `JaxStereoError` naming what does not parse."""
        parts = str(text).strip().split(":")
        usage = ("expected 'chessboard:COLSxROWS:SQUARE' or 'charuco:COLSxROWS:SQUARE:MARKER:DICT' "
                 "(e.g. chessboard:9x6:0.025, charuco:7x5:0.04:0.03:4X4_50)")
        if not parts or parts[0] not in ("chessboard", "charuco"):
            raise JaxStereoError(f"board spec {text!r} does not parse: {usage}")
        kind = parts[0]
        if (kind == "chessboard" and len(parts) != 3) or (kind == "charuco" and len(parts) != 5):
            raise JaxStereoError(f"board spec {text!r} does not parse: {usage}")
        m = re.fullmatch(r"(\d+)[xX](\d+)", parts[1])
        if not m:
            raise JaxStereoError(f"board spec {text!r}: size {parts[1]!r} is not COLSxROWS")
        cols, rows = int(m.group(1)), int(m.group(2))
        try:
            square = float(parts[2])
            marker = float(parts[3]) if kind == "charuco" else 0.0
        except ValueError:
            raise JaxStereoError(f"board spec {text!r}: square and marker sizes must be numbers in metres") from None
        if not (np.isfinite(square) and square > 0):
            raise JaxStereoError(f"board spec {text!r}: square size must be positive (metres)")
        if kind == "chessboard":
            if cols < 2 or rows < 2:
                raise JaxStereoError(f"board spec {text!r}: a chessboard needs at least 2x2 inner corners")
            return cls(kind, cols, rows, square)
        if cols < 3 or rows < 3:
            raise JaxStereoError(f"board spec {text!r}: a ChArUco board needs at least 3x3 squares")
        if not (0 < marker < square):
            raise JaxStereoError(f"board spec {text!r}: the marker must be smaller than the square")
        dictionary = parts[4].upper().removeprefix("DICT_")
        if dictionary not in _CHARUCO_DICTS:
            raise JaxStereoError(f"board spec {text!r}: unknown ArUco dictionary {parts[4]!r}")
        return cls(kind, cols, rows, square, marker, dictionary)

    def __str__(self) -> str:
        if self.kind == "chessboard":
            return f"chessboard:{self.cols}x{self.rows}:{self.square_m:g}"
        return f"charuco:{self.cols}x{self.rows}:{self.square_m:g}:{self.marker_m:g}:{self.dictionary}"

    def charuco_board(self) -> cv2.aruco.CharucoBoard:
        """The `cv2.aruco.CharucoBoard` of a ChArUco spec."""
        dictionary = cv2.aruco.getPredefinedDictionary(_CHARUCO_DICTS[self.dictionary])
        return cv2.aruco.CharucoBoard((self.cols, self.rows), self.square_m, self.marker_m, dictionary)

    @property
    def corners(self) -> np.ndarray:
        """All corners of the board in its own frame (n, 3), metres, indexed by corner id."""
        if self.kind == "chessboard":
            i, j = np.meshgrid(np.arange(self.cols), np.arange(self.rows))
            return np.stack([i.ravel(), j.ravel(), np.zeros(i.size)], axis=-1) * self.square_m
        return np.asarray(self.charuco_board().getChessboardCorners(), dtype=np.float64)

    @property
    def outline(self) -> tuple[float, float, float, float]:
        """The printed board's extent in its frame: (x_min, x_max, y_min, y_max), metres (with a margin)."""
        s = self.square_m
        if self.kind == "chessboard":
            return (-1.6 * s, (self.cols + 0.6) * s, -1.6 * s, (self.rows + 0.6) * s)
        return (-0.5 * s, (self.cols + 0.5) * s, -0.5 * s, (self.rows + 0.5) * s)

    def reflectance(self, xy: np.ndarray, texture: np.ndarray | None = None) -> np.ndarray:
        """Board reflectance in [0, 1] at board-frame points (..., 2); NaN outside the board."""
        x, y = xy[..., 0], xy[..., 1]
        x0, x1, y0, y1 = self.outline
        inside = (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
        s = self.square_m
        if self.kind == "chessboard":
            squares = (x >= -s) & (x <= self.cols * s) & (y >= -s) & (y <= self.rows * s)
            black = ((np.floor(x / s) + np.floor(y / s)) % 2 == 0) & squares
            value = np.where(black, 0.06, 0.92)
        else:
            if texture is None:
                texture = self.texture()
            ppm = texture.shape[1] / (self.cols * s)
            col = np.floor(x * ppm).astype(np.int64)
            row = np.floor(y * ppm).astype(np.int64)
            on = (col >= 0) & (col < texture.shape[1]) & (row >= 0) & (row < texture.shape[0])
            value = np.where(on, texture[np.clip(row, 0, texture.shape[0] - 1), np.clip(col, 0, texture.shape[1] - 1)],
                             0.92)
        return np.where(inside, value, np.nan)

    def texture(self, pixels_per_square: int = 120) -> np.ndarray:
        """The printed ChArUco pattern as reflectance (rows, cols) in [0.06, 0.92]."""
        size = (self.cols * pixels_per_square, self.rows * pixels_per_square)
        img = self.charuco_board().generateImage(size, marginSize=0).astype(np.float64) / 255.0
        return 0.06 + 0.86 * img
