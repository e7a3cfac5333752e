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
    the SWL `swl` (m), lies nearer the DEM. Each direction is scored by the median absolute vertical distance
    between its line and the DEM over the DEM's rows and those heights, where the line has left the DEM's x range
    or crosses an empty cell counting as infinitely far: a line that runs off the survey after a few centimetres
    (over a toe the survey barely reaches) is not judged by those centimetres alone. Where both medians are
    infinite, the line over more surveyed cells wins. "+x" when neither line meets the DEM at a row's worth of
    cells: the damage then says what is wrong."""
    x0, z0 = (float(v) for v in origin)
    heights = np.linspace(swl - 2 * dn50, swl + 2 * dn50, 33)
    score = {}
    for sign, name in ((1.0, "+x"), (-1.0, "-x")):
        x = x0 + sign * cot * (heights - z0)
        columns = np.rint((x - before.x[0]) / before.spacing).astype(int)
        inside = (columns >= 0) & (columns < before.x.size)
        gap = np.full((before.y.size, heights.size), np.inf)
        gap[:, inside] = np.abs(before.z[:, columns[inside]] - heights[inside][None, :])
        gap[np.isnan(gap)] = np.inf  # an empty cell
        met = int(np.isfinite(gap).sum())
        if met >= max(3, before.y.size):  # about a height per row at least
            score[name] = (float(np.median(gap)), -met)
    if not score:
        return "+x"
    return min(score, key=score.get)


def mirrored_in_x(dem: DEM) -> DEM:
    """`dem` seen in the frame x -> -x (its columns reversed, every error layer with them): a slope that rose
    toward -x rises with x there."""
    flipped = dem.with_layers(lambda layer: layer[:, ::-1])
    return dataclasses.replace(flipped, x=-dem.x[::-1])
