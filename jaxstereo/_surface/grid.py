"""Gridding surveys into DEMs (regular grids of height, NaN where there is no data)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np

from .._geometry.errors import JaxStereoError
from .._geometry.types import PathLike
from .._stereo.survey import Survey
from .coverage import filled_sigma, partial_coverage_sigma, straddle_sigma
from .gap_fill import lower_side_sources, survey_baseline_xy

SIGMA_LAYERS = ("sigma_match", "sigma_calibration", "sigma_level")
ERROR_LAYERS = SIGMA_LAYERS + ("dz_subpixel", "sigma_coverage")


@dataclasses.dataclass(frozen=True)
class DEM:
    """A digital elevation model on a regular grid.

    **Fields:** `x` (nx,) and `y` (ny,) cell-centre coordinates, world metres; `z` (ny, nx) heights,
    metres, NaN where no data; `spacing` metres. From a survey with error bars (`grid_survey`), each cell's
    vertical standard deviation (ny, nx) metres in three parts: `sigma_match` (matching; its errors are
    correlated over `correlation_m` metres, independent beyond), `sigma_calibration` and `sigma_level`
    (shared by every cell of the survey); `dz_subpixel` the signed offset (metres) between the two sub-pixel
    estimators, a systematic error of unknown sign (see `Survey.dz_subpixel`); `sigma_coverage` the std of a
    cell seen only in part or filled from its neighbours (see `coverage.py`); None when unknown.
    `calibration_id` names the cameras the survey was made with (a digest; surveys with the same one share the
    calibration's errors) and `water_level` its level (metres, NaN when dry or unknown): empty / NaN when
    unknown.
    """

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    spacing: float
    sigma_match: np.ndarray | None = None
    sigma_calibration: np.ndarray | None = None
    sigma_level: np.ndarray | None = None
    dz_subpixel: np.ndarray | None = None
    sigma_coverage: np.ndarray | None = None
    correlation_m: float = float("nan")
    calibration_id: str = ""
    water_level: float = float("nan")

    @property
    def has_sigma(self) -> bool:
        return all(getattr(self, key) is not None for key in SIGMA_LAYERS)

    @property
    def sigma(self) -> np.ndarray | None:
        """Each cell's total vertical standard deviation (ny, nx) metres, or None."""
        if not self.has_sigma:
            return None
        method = 0.0 if self.dz_subpixel is None else self.dz_subpixel**2
        coverage = 0.0 if self.sigma_coverage is None else self.sigma_coverage**2
        return np.sqrt(self.sigma_match**2 + self.sigma_calibration**2 + self.sigma_level**2 + method + coverage)

    def with_layers(self, fn: Callable[[np.ndarray], np.ndarray]) -> "DEM":
        """This DEM with `fn` applied to its height and to each of its error layers (ny, nx) -> (ny', nx')."""
        layers = {key: None if getattr(self, key) is None else fn(getattr(self, key)) for key in ERROR_LAYERS}
        return dataclasses.replace(self, z=fn(self.z), **layers)


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
    return _grid_median_cells(points, spacing, x, y, min_count)[0]


def _grid_median_cells(points, spacing, x, y, min_count) -> tuple[DEM, _CellHeights]:
    """`grid_median`'s DEM and the sorted heights of its cells."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or points.shape[0] == 0:
        raise JaxStereoError(f"points must be a non-empty (N, 3) array, got shape {points.shape}")
    if not spacing > 0:
        raise JaxStereoError(f"grid spacing must be positive, got {spacing}")
    if x is None or y is None:
        x, y = grid_extent(points, spacing)
    cells = _CellHeights(points, x, y, spacing)
    has = cells.counts >= max(1, min_count)
    out = np.where(has, cells.quantile(0.5), np.nan)
    return DEM(x, y, out.reshape(y.size, x.size), float(spacing)), cells


class _CellHeights:
    """The points' heights sorted within each cell of a grid: `counts` (ny * nx,) points per cell, and
    `quantile(q)` each cell's height quantile (ny * nx,) metres (the mean of the two middle points' for the
    median; NaN for empty cells)."""

    def __init__(self, points: np.ndarray, x: np.ndarray, y: np.ndarray, spacing: float):
        cell, inside = _cell_index(points, x, y, spacing)
        order = np.lexsort((points[inside, 2], cell))
        self.z = points[inside, 2][order]
        self.counts = np.bincount(cell, minlength=x.size * y.size)
        self.starts = np.concatenate([[0], np.cumsum(self.counts)[:-1]])

    def quantile(self, q: float) -> np.ndarray:
        has = self.counts > 0
        position = q * (self.counts[has] - 1)
        out = np.full(self.counts.size, np.nan)
        out[has] = 0.5 * (self.z[self.starts[has] + np.floor(position).astype(np.int64)]
                          + self.z[self.starts[has] + np.ceil(position).astype(np.int64)])
        return out


def fill_holes(dem: DEM, max_gap_m: float, baseline_xy: tuple[float, float] | None = None) -> DEM:
    """Fill empty cells whose nearest data lies within `max_gap_m` (nearest value, and the nearest cell's
    sigma layers, with `sigma_coverage` from the range of the seen heights within reach); larger holes stay NaN.

    With `baseline_xy`, the survey's stereo baseline in the world's (x, y) (`gap_fill.survey_baseline_xy`), a cell
    with seen cells within reach on both sides of it along the grid axis nearer the baseline takes the lower of the
    two nearest instead (`gap_fill.lower_side_sources`: the surface a camera could not see there lies behind a
    foreground).
    """
    from scipy import ndimage

    empty = np.isnan(dem.z)
    if not empty.any() or max_gap_m <= 0:
        return dem
    dist, (ii, jj) = ndimage.distance_transform_edt(empty, return_indices=True)
    fill = empty & (dist * dem.spacing <= max_gap_m)
    if baseline_xy is not None:
        lower_side_sources(dem.z, fill, int(np.floor(max_gap_m / dem.spacing + 1e-9)), baseline_xy, ii, jj)

    def filled(layer):
        out = layer.copy()
        out[fill] = layer[ii[fill], jj[fill]]
        return out

    out = dem.with_layers(filled)
    if dem.has_sigma:  # a filled height was not seen: as uncertain as the seen heights within reach
        reach = int(np.ceil(max_gap_m / dem.spacing))
        own = np.where(np.isfinite(dem.z), 0.0, np.nan) if dem.sigma_coverage is None else out.sigma_coverage
        out = dataclasses.replace(out, sigma_coverage=np.where(fill, filled_sigma(dem.z, reach), own))
    return out


def grid_survey_filled(survey: Survey, spacing: float, max_gap_m: float, x: np.ndarray | None = None,
                       y: np.ndarray | None = None) -> DEM:
    """`grid_survey` with its gaps up to `max_gap_m` metres filled (`fill_holes`), a gap along the survey's own
    stereo baseline from its lower side."""
    return fill_holes(grid_survey(survey, spacing, x, y), max_gap_m, survey_baseline_xy(survey.rig_json))


def grid_survey(survey: Survey, spacing: float, x: np.ndarray | None = None, y: np.ndarray | None = None,
                min_count: int = 1) -> DEM:
    """`grid_median` of a survey's points, with each cell's sigma layers when the survey has error bars.

    A cell's matching std is the RMS of its points' `sigma_z_match` divided by the square root of the number of
    independent matches in it (one per `MATCH_CORRELATION_PX`-wide square of pixels: neighbouring matches share
    most of their fitting window, so their errors are nearly the same); its calibration and level stds are
    the means of its points' (shared errors do not average out); a cell seen in part, or whose points lie on
    both sides of a step, gets `sigma_coverage` (`partial_coverage_sigma`, `straddle_sigma`). `correlation_m`
    is the matching window's footprint at the survey's median distance from the left camera.
    """
    from .._stereo.uncertainty import MATCH_CORRELATION_PX

    dem, heights = _grid_median_cells(survey.points, spacing, x, y, min_count)
    if survey.cov is None or survey.sigma_z_match is None or survey.sigma_z_level is None:
        return dem
    cells, inside = _cell_index(survey.points, dem.x, dem.y, spacing)
    n = dem.x.size * dem.y.size
    count = np.bincount(cells, minlength=n).astype(np.float64)
    has = np.isfinite(dem.z.ravel())

    def cell_mean(values):
        total = np.bincount(cells, weights=values[inside], minlength=n)
        return np.where(has, total / np.maximum(count, 1), np.nan).reshape(dem.z.shape)

    independent = np.maximum(1.0, count.reshape(dem.z.shape) / MATCH_CORRELATION_PX**2)
    spread = (heights.quantile(0.75) - heights.quantile(0.25)).reshape(dem.z.shape)
    coverage = np.fmax(partial_coverage_sigma(dem.z, count.reshape(dem.z.shape)),
                       np.where(np.isfinite(dem.z), straddle_sigma(spread, spacing), np.nan))
    match = np.sqrt(cell_mean(survey.sigma_z_match.astype(np.float64) ** 2) / independent)
    return dataclasses.replace(dem, sigma_match=match, sigma_calibration=cell_mean(survey.sigma_z_calibration),
                               sigma_level=cell_mean(survey.sigma_z_level.astype(np.float64)),
                               dz_subpixel=None if survey.dz_subpixel is None else
                               cell_mean(survey.dz_subpixel.astype(np.float64)),
                               sigma_coverage=coverage, correlation_m=_match_footprint(survey),
                               calibration_id=_calibration_id(survey),
                               water_level=float(survey.water_level))


def _calibration_id(survey) -> str:
    """A digest of the survey's two cameras (intrinsics, distortion, poses): equal for surveys of one rig."""
    import hashlib
    import json

    try:
        rig = json.loads(survey.rig_json)
        cameras = json.dumps([rig["left"], rig["right"]], sort_keys=True)
    except (ValueError, KeyError, TypeError):
        return ""
    return hashlib.sha1(cameras.encode()).hexdigest()[:16]


def _cell_index(points, x, y, spacing):
    """Flat cell index of the points inside the grid (k,), and which points are inside (N,)."""
    ix = np.floor((points[:, 0] - x[0]) / spacing + 0.5).astype(np.int64)
    iy = np.floor((points[:, 1] - y[0]) / spacing + 0.5).astype(np.int64)
    inside = (ix >= 0) & (ix < x.size) & (iy >= 0) & (iy < y.size)
    return iy[inside] * x.size + ix[inside], inside


def _match_footprint(survey) -> float:
    """The matching window's width on the surface (metres) at the survey's median distance, NaN if unknown."""
    import json

    from .._stereo.uncertainty import MATCH_CORRELATION_PX

    try:
        left = json.loads(survey.rig_json)["left"]
        center = -np.asarray(left["R"], float).T @ np.asarray(left["t"], float)
        distance = float(np.median(np.linalg.norm(survey.points - center, axis=1)))
        return MATCH_CORRELATION_PX * distance / float(left["fx"])
    except (ValueError, KeyError, TypeError):
        return float("nan")


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
    layers = {key: getattr(dem, key) for key in ERROR_LAYERS if getattr(dem, key) is not None}
    if layers:
        layers.update(correlation_m=np.array(dem.correlation_m), calibration_id=np.array(dem.calibration_id),
                      water_level=np.array(dem.water_level))
    with atomic_path(path) as tmp:
        np.savez(tmp, x=dem.x, y=dem.y, z=dem.z, spacing=np.array(dem.spacing), kind=np.array("dem"), **layers)


def load_dem(path: PathLike) -> DEM:
    """Read a DEM `.npz`; `JaxStereoError` if it is not one."""
    from .._app.io import read_npz

    return _dem_from_fields(read_npz(path, "DEM"), path)


def _dem_from_fields(data: dict, path) -> DEM:
    if not {"x", "y", "z", "spacing"} <= set(data):
        raise JaxStereoError(f"{str(path)!r} is not a DEM (needs x, y, z, spacing)")
    z = np.asarray(data["z"], dtype=np.float64)
    layers = {}
    for key in ERROR_LAYERS:
        if key in data:
            layer = np.asarray(data[key], dtype=np.float64)
            if layer.shape != z.shape:
                raise JaxStereoError(f"DEM {str(path)!r}: {key} has shape {layer.shape}, its heights {z.shape}")
            layers[key] = layer
    return DEM(np.asarray(data["x"]), np.asarray(data["y"]), z, float(data["spacing"]), **layers,
               correlation_m=float(data.get("correlation_m", np.nan)),
               calibration_id=str(data.get("calibration_id", "")), water_level=float(data.get("water_level", np.nan)))


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
        return grid_survey_filled(survey, spacing, max_gap_m, x, y)
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
    xy = np.stack([X, Y], axis=-1)
    resampled = dem.with_layers(lambda layer: dem_heights(dataclasses.replace(dem, z=layer), xy))
    return dataclasses.replace(resampled, x=np.asarray(x), y=np.asarray(y),
                               spacing=float(x[1] - x[0]) if len(x) > 1 else dem.spacing)
