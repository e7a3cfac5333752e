"""How far a DEM cell's height depends on which part of the cell the survey happened to see.

A cell beside a rock's edge holds the points of whichever side the cameras saw: the rock's top from one
viewpoint, the crevice beside it from another (through water the views change). Its median is then as
uncertain as the relief around it, whatever the matching noise. Two cases count:

- a cell seen only in part: fewer points than `SEEN_FRACTION` of the count where the surface nearby is
  wholly seen (the upper quartile of the counts over `COUNT_NEIGHBOURHOOD` cells);
- a cell filled from its neighbours (`fill_holes`): not seen at all.

Each gets a standard deviation of (1 - coverage) times half the range of the seen heights around it (its 3x3
neighbours when seen in part; within the fill's reach when filled). Cells wholly seen get zero.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

SEEN_FRACTION = 0.5
COUNT_NEIGHBOURHOOD = 9  # cells square: about a rock's size on 5 mm cells, holding wholly seen cells


def half_range(z: np.ndarray, size: int) -> np.ndarray:
    """Half the range of the known heights (metres) within a `size` x `size` square around each cell (ny, nx);
    zero where none is known."""
    known = np.isfinite(z)
    high = ndimage.maximum_filter(np.where(known, z, -np.inf), size=size, mode="nearest")
    low = ndimage.minimum_filter(np.where(known, z, np.inf), size=size, mode="nearest")
    spread = 0.5 * (high - low)
    return np.where(np.isfinite(spread), spread, 0.0)


def partial_coverage_sigma(z: np.ndarray, count: np.ndarray) -> np.ndarray:
    """The std (metres, (ny, nx)) of each seen cell's height for the part of it the survey did not see.

    **Arguments:** the cell medians `z` (ny, nx) metres, NaN where empty; the number of points per cell
    `count` (ny, nx). NaN where `z` is NaN.
    """
    count = np.asarray(count, dtype=np.float64)
    expected = ndimage.percentile_filter(count, 75, size=COUNT_NEIGHBOURHOOD, mode="nearest")
    coverage = np.clip(count / np.maximum(SEEN_FRACTION * expected, 1.0), 0.0, 1.0)
    return np.where(np.isfinite(z), (1.0 - coverage) * half_range(z, 3), np.nan)


def filled_sigma(z: np.ndarray, reach_cells: int) -> np.ndarray:
    """The std (metres, (ny, nx)) of a height filled from the seen cells within `reach_cells`: half their
    range. `z` (ny, nx) metres holds the seen cells only (NaN elsewhere)."""
    return half_range(z, 2 * max(1, int(reach_cells)) + 1)
