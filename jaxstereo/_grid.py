"""Gridding surveys into DEMs (regular grids of height, NaN where there is no data)."""

from __future__ import annotations

import dataclasses

import numpy as np

from ._errors import JaxStereoError


@dataclasses.dataclass(frozen=True)
class DEM:
    """A digital elevation model on a regular grid.

    **Fields:** `x` (nx,) and `y` (ny,) cell-centre coordinates, world metres; `z` (ny, nx) heights,
    metres, NaN where no data; `spacing` metres.
    """

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    spacing: float


def grid_extent(points: np.ndarray, spacing: float):
    """Cell-centre axes covering the points' x, y range, aligned to multiples of `spacing`."""
    lo = np.floor(points[:, :2].min(axis=0) / spacing) * spacing
    hi = np.ceil(points[:, :2].max(axis=0) / spacing) * spacing
    x = np.arange(lo[0], hi[0] + spacing / 2, spacing)
    y = np.arange(lo[1], hi[1] + spacing / 2, spacing)
    return x, y


def grid_median(points: np.ndarray, spacing: float, x: np.ndarray | None = None, y: np.ndarray | None = None,
                min_count: int = 1) -> DEM:
    """Median height of the points falling in each cell (a robust, fast gridding); NaN for empty cells.

    **Arguments:** `points` (N, 3) world metres; `spacing` metres; optional cell-centre axes `x`, `y`
    (default: covering the points); `min_count` fewest points for a cell to get a value.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or points.shape[0] == 0:
        raise JaxStereoError(f"points must be a non-empty (N, 3) array, got shape {points.shape}")
    if not spacing > 0:
        raise JaxStereoError(f"grid spacing must be positive, got {spacing}")
    if x is None or y is None:
        x, y = grid_extent(points, spacing)
    ix = np.floor((points[:, 0] - x[0]) / spacing + 0.5).astype(np.int64)
    iy = np.floor((points[:, 1] - y[0]) / spacing + 0.5).astype(np.int64)
    inside = (ix >= 0) & (ix < x.size) & (iy >= 0) & (iy < y.size)
    cell = iy[inside] * x.size + ix[inside]
    z = points[inside, 2]
    order = np.argsort(z, kind="stable")
    order = order[np.argsort(cell[order], kind="stable")]
    cell_sorted = cell[order]
    z_sorted = z[order]
    counts = np.bincount(cell_sorted, minlength=x.size * y.size)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    has = counts >= max(1, min_count)
    lo = starts[has] + (counts[has] - 1) // 2
    hi = starts[has] + counts[has] // 2
    out = np.full(x.size * y.size, np.nan)
    out[has] = 0.5 * (z_sorted[lo] + z_sorted[hi])
    return DEM(x, y, out.reshape(y.size, x.size), float(spacing))
