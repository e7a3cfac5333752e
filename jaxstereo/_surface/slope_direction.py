"""Which way along x the design slope rises, and DEMs mirrored in x so that it rises with x.

The damage is computed with the slope rising with x (`to_slope_frame`). The world frame comes from the origin
board, so the model may face either way along x: a rig whose cameras are turned 180 degrees about their axes sees
the board's corners in the opposite order, and its x runs down the slope. The initial survey says which way the
slope rises: the design line through the given point, drawn up the slope in each direction, lies on the armour in
one and over the floor or the toe in the other.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .grid import DEM

DIRECTIONS = ("+x", "-x")


def slope_direction(before: DEM, cot: float, swl: float, origin, dn50: float) -> str:
    """The direction ("+x" or "-x") in which the design slope of cotangent `cot` through `origin` (x, z) metres
    rises, from the initial DEM `before`: the one whose line, over the heights from 2 Dn50 below to 2 Dn50 above
    the SWL `swl` (m), lies nearer the DEM (median absolute vertical distance over the DEM's rows; a direction
    whose line leaves the DEM loses). "+x" when neither line meets the DEM: the damage then says what is wrong."""
    x0, z0 = (float(v) for v in origin)
    heights = np.linspace(swl - 2 * dn50, swl + 2 * dn50, 33)
    distance = {}
    for sign, name in ((1.0, "+x"), (-1.0, "-x")):
        x = x0 + sign * cot * (heights - z0)
        columns = np.rint((x - before.x[0]) / before.spacing).astype(int)
        inside = (columns >= 0) & (columns < before.x.size)
        if not inside.any():
            continue
        z = before.z[:, columns[inside]]
        gap = np.abs(z - heights[inside][None, :])
        gap = gap[np.isfinite(gap)]
        if gap.size >= max(3, before.y.size):  # about a height per row at least
            distance[name] = float(np.median(gap))
    if not distance:
        return "+x"
    return min(distance, key=distance.get)


def mirrored_in_x(dem: DEM) -> DEM:
    """`dem` seen in the frame x -> -x (its columns reversed, every error layer with them): a slope that rose
    toward -x rises with x there."""
    flipped = dem.with_layers(lambda layer: layer[:, ::-1])
    return dataclasses.replace(flipped, x=-dem.x[::-1])
