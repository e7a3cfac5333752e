"""Cross-sections: profiles along lines from DEMs or point clouds, and moving-average smoothing."""

from __future__ import annotations

import numpy as np

from .._geometry.errors import JaxStereoError
from .._geometry.types import Vector2
from .grid import DEM, dem_heights


def profile_from_dem(dem: DEM, start_xy: Vector2, end_xy: Vector2,
                     step_m: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Heights along the segment `start_xy -> end_xy` (world metres), bilinear in the DEM.

    **Returns:** `(s, z)`: distance along the segment (n,) metres and height (n,) metres (NaN where a
    neighbouring DEM cell is empty). The default step is the DEM spacing.
    """
    start = np.asarray(start_xy, dtype=np.float64)
    end = np.asarray(end_xy, dtype=np.float64)
    length = float(np.linalg.norm(end - start))
    if length == 0:
        raise JaxStereoError("profile start and end are the same point")
    step = step_m or dem.spacing
    s = np.arange(0.0, length + step / 2, step)
    xy = start + (s / length)[:, None] * (end - start)
    return s, dem_heights(dem, xy)


def profile_from_points(points: np.ndarray, y_m: float, half_width_m: float, step_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Cross-shore profile straight from a cloud: median z of the points within `half_width_m` of `y_m`,
    in bins of `step_m` along x. **Returns** `(x, z)` bin centres and medians (NaN for empty bins)."""
    sel = points[np.abs(points[:, 1] - y_m) <= half_width_m]
    if sel.shape[0] == 0:
        raise JaxStereoError(f"no survey points within {half_width_m} m of y = {y_m} m")
    x0 = np.floor(sel[:, 0].min() / step_m) * step_m
    idx = np.floor((sel[:, 0] - x0) / step_m).astype(int)
    n = idx.max() + 1
    z = np.full(n, np.nan)
    order = np.lexsort((sel[:, 2], idx))
    idx_s, z_s = idx[order], sel[order, 2]
    counts = np.bincount(idx_s, minlength=n)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    has = counts > 0
    z[has] = 0.5 * (z_s[starts[has] + (counts[has] - 1) // 2] + z_s[starts[has] + counts[has] // 2])
    return x0 + step_m * (np.arange(n) + 0.5), z


def moving_average(z: np.ndarray, window: int) -> np.ndarray:
    """Centred moving average over `window` points (odd), ignoring NaNs; NaN where a window holds none."""
    if window < 1 or window % 2 == 0:
        raise JaxStereoError(f"moving-average window must be an odd number of points, got {window}")
    valid = np.isfinite(z)
    kernel = np.ones(window)
    total = np.convolve(np.where(valid, z, 0.0), kernel, mode="same")
    count = np.convolve(valid.astype(np.float64), kernel, mode="same")
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / count, np.nan)
