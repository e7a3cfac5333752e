"""Gridding surveys into DEMs (regular grids of height, NaN where there is no data)."""

from __future__ import annotations

import dataclasses

import numpy as np

from .._geometry.errors import JaxStereoError
from .._geometry.types import PathLike


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


def fill_holes(dem: DEM, max_gap_m: float) -> DEM:
    """Fill empty cells whose nearest data lies within `max_gap_m` (nearest value); larger holes stay NaN."""
    from scipy import ndimage

    empty = np.isnan(dem.z)
    if not empty.any() or max_gap_m <= 0:
        return dem
    dist, (ii, jj) = ndimage.distance_transform_edt(empty, return_indices=True)
    z = dem.z.copy()
    fill = empty & (dist * dem.spacing <= max_gap_m)
    z[fill] = dem.z[ii[fill], jj[fill]]
    return DEM(dem.x, dem.y, z, dem.spacing)


def grid_delaunay(points: np.ndarray, spacing: float, x: np.ndarray | None = None,
                  y: np.ndarray | None = None) -> DEM:
    """Linear interpolation on the Delaunay triangulation of the points (the paper's gridding).

    Cells outside the points' convex hull stay NaN. Slower than `grid_median` for large clouds.
    """
    from scipy.interpolate import LinearNDInterpolator

    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or points.shape[0] < 3:
        raise JaxStereoError(f"points must be an (N >= 3, 3) array, got shape {points.shape}")
    if x is None or y is None:
        x, y = grid_extent(points, spacing)
    interp = LinearNDInterpolator(points[:, :2], points[:, 2])
    X, Y = np.meshgrid(x, y)
    return DEM(x, y, interp(X, Y), float(spacing))


def save_dem(dem: DEM, path: PathLike) -> None:
    """Write a DEM `.npz` (x, y, z, spacing) atomically."""
    from pathlib import Path

    from .._app.io import atomic_path

    if Path(path).suffix != ".npz":
        raise JaxStereoError(f"DEM file {str(path)!r} must end in .npz")
    with atomic_path(path) as tmp:
        np.savez(tmp, x=dem.x, y=dem.y, z=dem.z, spacing=np.array(dem.spacing), kind=np.array("dem"))


def load_dem(path: PathLike) -> DEM:
    """Read a DEM `.npz`; `JaxStereoError` if it is not one."""
    from .._app.io import read_npz

    return _dem_from_fields(read_npz(path, "DEM"), path)


def _dem_from_fields(data: dict, path) -> DEM:
    if not {"x", "y", "z", "spacing"} <= set(data):
        raise JaxStereoError(f"{str(path)!r} is not a DEM (needs x, y, z, spacing)")
    return DEM(data["x"], data["y"], data["z"], float(data["spacing"]))


def load_surface(path: PathLike, spacing: float, x: np.ndarray | None = None, y: np.ndarray | None = None,
                 max_gap_m: float = 0.0) -> DEM:
    """A DEM from a file holding a DEM or a survey (gridded by median per cell, on `x`, `y` if given)."""
    from .._app.io import read_npz

    fields = read_npz(path, "survey or DEM")  # read once, whichever it holds
    if {"x", "y", "z", "spacing"} <= set(fields):
        dem = _dem_from_fields(fields, path)
        if x is not None and (dem.z.shape != (len(y), len(x)) or not np.allclose(dem.x, x) or not np.allclose(dem.y, y)):
            dem = _resample(dem, x, y)
        return dem
    if "points" in fields:
        from .._stereo.survey import survey_from_fields

        survey = survey_from_fields(fields, path)
        if len(survey) == 0:
            raise JaxStereoError(f"survey {str(path)!r} holds no points")
        return fill_holes(grid_median(survey.points, spacing, x, y), max_gap_m)
    raise JaxStereoError(f"{str(path)!r} is neither a survey nor a DEM")


def dem_heights(dem: DEM, xy) -> np.ndarray:
    """Bilinear height (metres) of a DEM at world points `xy` (..., 2) metres; returns (...,), NaN outside
    the grid's cell centres or where a cell that takes part in the interpolation is empty.

    The one DEM sampler of the package: profiles, resampling and the refinement's surface control use it.
    """
    from scipy import ndimage

    xy = np.asarray(xy, dtype=np.float64)
    col = (xy[..., 0] - dem.x[0]) / dem.spacing
    row = (xy[..., 1] - dem.y[0]) / dem.spacing
    z = ndimage.map_coordinates(np.nan_to_num(dem.z, nan=0.0), [row, col], order=1, mode="nearest")
    holes = ndimage.map_coordinates(np.isnan(dem.z).astype(np.float64), [row, col], order=1, mode="nearest")
    outside = (col < 0) | (col > dem.x.size - 1) | (row < 0) | (row > dem.y.size - 1) | ~np.isfinite(col + row)
    return np.where((holes > 0) | outside, np.nan, z)


def _resample(dem: DEM, x, y) -> DEM:
    X, Y = np.meshgrid(x, y)
    z = dem_heights(dem, np.stack([X, Y], axis=-1))
    return DEM(np.asarray(x), np.asarray(y), z, float(x[1] - x[0]) if len(x) > 1 else dem.spacing)
