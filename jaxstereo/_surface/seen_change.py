"""The change between two surveys where both saw the surface, carried into the cells one of them did not see.

A cell beside a rock's edge holds whichever side of the edge the cameras saw (`coverage.py`): through air
the crevice's floor, through water the rock's flank, or the reverse, because refraction moves the viewpoints;
a cell across the edge takes the side that holds more of its points. Two surveys of an unchanged model then
disagree there by up to the rock's height, and each such cell reads as erosion or accretion that never
happened: on the POV-Ray flume's undamaged model, dry survey against wet, profiles read S up to 0.66 (grey
rock: 1.06) from crevices between rocks that neither survey saw well.

The change itself is smoother than the surfaces: rocks that did not move leave no change at all, and a hole's change
is its depth, which varies over a stone's size rather than over a cell. So the damage compares the surveys where
both saw the surface wholly, and each cell that one of them saw only in part or filled from its neighbours or
straddling a step (its `sigma_coverage` above the tolerance, by default any) takes its change from the cells around
it that both saw wholly: its own change kept within the range of theirs within a quarter of a stone, the profiler's
foot's radius (5 x 5 cells of 5 mm for a 36 mm stone; see `_seen_range`; its 3 x 3 neighbours' until round 68,
their median until round 64, their range less those beyond 3 MADs until round 66), else the nearest such cell's
within a stone's size (Dn50). The after-surface there is the before-surface plus that change. On the POV-Ray
development flume (about 30 % of the cells carried) the undamaged model's largest S is 0.10 since round 68 (0.14 with
the 3 x 3 neighbours and round 67's edges of a face, `damage._paired_edges`; grey rock: 0.12, 0.08 before), and the
stage III hole's central A_e reads +2.4 % from the truth (+0.5 % with the 3 x 3 neighbours; +6.8 % comparing every
cell). Where the change is not smooth it carries wrongly: a floor cell that one survey saw wholly takes the change
across a removed rock's edge that the other saw in part (the README lists the rules tried instead).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy import ndimage

from .grid import DEM

SEEN_TOLERANCE_M = 0.0  # a cell is seen wholly when no part of it went unseen in either survey
# A carried cell's change is kept within the changes of the cells both surveys saw wholly within this many stones
# (Dn50) of it: a quarter, the profiler's foot's radius (two 5 mm cells either side for a 36 mm stone).
NEIGHBOURHOOD_DN50 = 0.25


def change_where_seen(before: DEM, after: DEM, tolerance_m: float, reach_m: float) -> tuple[DEM, np.ndarray]:
    """The after-surface to compare with `before`: in each cell that either survey saw only in part, filled or
    across a step (`sigma_coverage` above `tolerance_m` metres, see `coverage.py`), the before-height plus the change
    (after - before) the cells both surveys saw wholly allow: the cell's own kept within the range of theirs within
    `NEIGHBOURHOOD_DN50` times `reach_m` (a square of cells at least 3 x 3; `_seen_range`), else the nearest
    one's within `reach_m` metres.

    **Arguments:** two DEMs on one grid (ny, nx), metres; `reach_m` a stone's size (Dn50), metres. A DEM without a
    `sigma_coverage` layer (a DEM of the true surface, or one gridded without error bars) counts as seen wholly
    wherever it has a height.

    **Returns:** `(after', carried)`: the after DEM with its heights replaced in the carried cells (its error
    layers untouched), and the carried cells (ny, nx) bool. Cells empty in either DEM stay as they were.
    """
    known = np.isfinite(before.z) & np.isfinite(after.z)
    unseen = np.zeros(known.shape, bool)
    for dem in (before, after):
        if dem.sigma_coverage is not None:
            unseen |= ~(np.nan_to_num(dem.sigma_coverage, nan=np.inf) <= tolerance_m)
    seen = known & ~unseen
    if not seen.any():  # no cell to take a change from
        return after, np.zeros(known.shape, bool)
    distance, (rows, cols) = ndimage.distance_transform_edt(~seen, return_indices=True)
    carried = known & unseen & (distance * before.spacing <= reach_m)
    if not carried.any():
        return after, carried
    change = np.where(seen, after.z - before.z, np.nan)
    row, col = np.nonzero(carried)
    size = 2 * max(1, int(round(NEIGHBOURHOOD_DN50 * reach_m / before.spacing))) + 1
    low, high = (bound[row, col] for bound in _seen_range(change, size))
    some = np.isfinite(low)  # a wholly seen cell within the square
    estimate = change[rows[row, col], cols[row, col]]  # else the nearest seen cell's
    own = after.z[row, col] - before.z[row, col]  # finite: a carried cell holds a height in both DEMs
    estimate[some] = np.clip(own[some], low[some], high[some])
    z = after.z.copy()
    z[row, col] = before.z[row, col] + estimate
    return dataclasses.replace(after, z=z), carried


def _seen_range(change: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """The lowest and the highest change (m) of the wholly seen cells in the `size` x `size` square of cells around
    each cell: `(low, high)`, each (ny, nx), +inf and -inf where the square holds none. `change` (ny, nx) is NaN
    where a cell was not seen wholly. A carried cell keeps its own change where it lies within that range, else
    takes the range's nearer end (`change_where_seen`).

    The change is smooth, so a cell's true change lies among its neighbours': the range says what a cell seen only
    in part may read, and its own reading is the best guess inside it. The median of the neighbours instead flattens
    a narrow hole's floor cells, most of whose neighbours lie on its rim (on five POV-Ray flumes it read the central
    profile's eroded area up to 19 % below the range). Until round 66 the range left out the neighbours beyond 3
    scaled MADs of their median, so that one mismatched neighbour would not open it; but where most neighbours agree
    their MAD is nil, and a hole's floor cells among rim cells were all left out: the cell took the rim's change.
    Over 18 POV-Ray flumes (the development flume and rigs A-Q; the five profiles nearest each hole's centre against
    the true sweep at each one's own y), with the whole range 88 % of the 90 profiles' A_e lie within 10 % of the
    truth (79 % without the MADs' outliers), the median error 3.8 % (4.6), the mean -2.7 % (-4.4), d_e 93 % within
    5 mm (91 %); the central profiles miss 10 % on two flumes (three), and the undamaged model's largest S is 0.26
    either way (the development flume 0.15 against 0.12; grey rock at most 0.21 either way).

    Until round 68 the neighbours were the 3 x 3 cells around. In a small deep hole (flume V: 29 cm2, 73 mm deep)
    whose floor the surveys saw mostly in part, a floor cell whose wholly seen 3 x 3 neighbours all lay on the rim
    took the rim's change, and the profiler's foot, closed over such cells, stood 10-14 mm over the floor: the
    central A_e -14.3 %, d_e -10.2 mm. The cells within the foot's radius (5 x 5) reach the floor cells seen wholly:
    -9.8 %, +0.2 mm. Over 23 POV-Ray flumes (the development flume, rigs A-V; 115 profiles) the central profiles'
    misses fell from six to three (A_e: C, J; d_e: T), d_e within 5 mm 89 -> 92 % (RMS 4.2 -> 2.9 mm), A_e within
    10 % 87 % either way, its mean -1.6 -> +0.3 % (C left out); the undamaged model's largest S 0.26 either way (the
    development flume 0.14 -> 0.10; grey rock at most 0.21 -> 0.16), its largest d_e's median 7.5 -> 10.6 mm."""
    seen = np.isfinite(change)
    low = ndimage.minimum_filter(np.where(seen, change, np.inf), size=size, mode="constant", cval=np.inf)
    high = ndimage.maximum_filter(np.where(seen, change, -np.inf), size=size, mode="constant", cval=-np.inf)
    return low, high


def on_common_cells(before: DEM, after: DEM) -> tuple[DEM, DEM]:
    """The two DEMs (one grid, (ny, nx), metres) with their heights emptied (NaN) wherever either is empty.

    A cell that only one survey holds has no change to measure, and a profile drawn through it would compare that
    survey's height with the other's bridged across the gap: at the foot of a rock's face, a crevice's floor in
    one against a line from the floor to the rock's top in the other. On the POV-Ray flume seen by its rig turned
    180 degrees, one such cell per section gave the undamaged model (dry survey against wet) a profile S of 0.31
    (grey rock: 0.36); compared on their common cells, 0.09 (0.14), and nothing else the scorecard reads moved.
    """
    both = np.isfinite(before.z) & np.isfinite(after.z)
    return (dataclasses.replace(before, z=np.where(both, before.z, np.nan)),
            dataclasses.replace(after, z=np.where(both, after.z, np.nan)))
