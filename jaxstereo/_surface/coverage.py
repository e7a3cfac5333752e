"""How far a DEM cell's height depends on which part of the cell the survey happened to see.

A cell beside a rock's edge holds the points of whichever side the cameras saw: the rock's top from one
viewpoint, the crevice beside it from another (through water the views change). Its median is then as
uncertain as the relief around it, whatever the matching noise. Two cases count:

- a cell seen only in part: fewer points than `SEEN_FRACTION` of the count where the surface nearby is
  wholly seen (the upper quartile of the counts over `COUNT_NEIGHBOURHOOD` cells);
- a cell filled from its neighbours (`fill_holes`): not seen at all;
- a cell whose points lie on both sides of a step (a rock's edge): the inter-quartile range of its points'
  heights more than `STEP_SPREAD_CELLS` times its width, steeper than any face a plane could give it (76
  degrees). Its median is whichever side holds more of its points, and the other viewpoint may tip it.

The first two get a standard deviation of (1 - coverage) times half the range of the seen heights around it
(its 3x3 neighbours when seen in part; within the fill's reach when filled), the third half its points'
inter-quartile range. Other cells get zero.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

SEEN_FRACTION = 0.5
COUNT_NEIGHBOURHOOD = 9  # cells square: about a rock's size on 5 mm cells, holding wholly seen cells
STEP_SPREAD_CELLS = 2.0  # a plane across a cell spreads its heights' quartiles by width * tan(slope) / 2


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


def straddle_sigma(spread: np.ndarray, spacing: float) -> np.ndarray:
    """The std (metres, the shape of `spread`) of the cells whose points lie on both sides of a step: half the
    inter-quartile range `spread` (metres) of each cell's points' heights where it exceeds `STEP_SPREAD_CELLS`
    times the cell's width `spacing` (metres); zero elsewhere (NaN spreads too: cells without enough points)."""
    spread = np.nan_to_num(np.asarray(spread, dtype=np.float64), nan=0.0)
    return np.where(spread > STEP_SPREAD_CELLS * spacing, 0.5 * spread, 0.0)
