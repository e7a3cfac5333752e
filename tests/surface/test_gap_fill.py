"""Gaps along the stereo baseline filled from their lower side (`gap_fill`, `fill_holes`), against analytic cases."""

import json

import numpy as np
import pytest

from jaxstereo._surface.gap_fill import survey_baseline_xy
from jaxstereo._surface.grid import DEM, fill_holes

SPACING = 0.005
FLOOR, WALL = 0.040, 0.115


def _hole_beside_a_wall(along_x=True):
    """A floor (0.040 m) left of a wall (0.115 m) with two empty cells at the wall's foot, as the right camera of a
    rig whose baseline runs along x leaves them; the same turned a quarter when `along_x` is False."""
    z = np.full((6, 10), FLOOR)
    z[:, 6:] = WALL
    z[:, 4:6] = np.nan  # the wall's foot, hidden: truly floor
    if not along_x:
        z = z.T.copy()
    ny, nx = z.shape
    return DEM(np.arange(nx) * SPACING, np.arange(ny) * SPACING, z, SPACING)


def test_a_gap_at_a_walls_foot_along_the_baseline_takes_the_floor():
    dem = _hole_beside_a_wall()
    nearest = fill_holes(dem, 0.01)
    # the nearest seen cell: the floor for the gap's first column, the wall top for its second
    np.testing.assert_array_equal(nearest.z[:, 4], FLOOR)
    np.testing.assert_array_equal(nearest.z[:, 5], WALL)
    lower = fill_holes(dem, 0.01, baseline_xy=(0.25, 0.001))
    np.testing.assert_array_equal(lower.z[:, 4:6], FLOOR)
    np.testing.assert_array_equal(lower.z[np.isfinite(dem.z)], dem.z[np.isfinite(dem.z)])  # seen cells kept


def test_the_grid_axis_nearer_the_baseline_is_searched():
    dem = _hole_beside_a_wall(along_x=False)  # the gap runs along y now
    np.testing.assert_array_equal(fill_holes(dem, 0.01, baseline_xy=(0.01, -0.22)).z[4:6], FLOOR)
    # searched across the baseline instead, along x, the gap's rows hold no seen cell: nearest, as without one
    across = fill_holes(dem, 0.01, baseline_xy=(0.22, 0.01))
    np.testing.assert_array_equal(across.z, fill_holes(dem, 0.01).z)


def test_a_gap_with_a_seen_cell_on_one_side_only_takes_the_nearest():
    dem = _hole_beside_a_wall()
    z = dem.z.copy()
    z[:, :4] = np.nan  # the floor gone too: nothing seen within reach on the left
    edge = DEM(dem.x, dem.y, z, SPACING)
    np.testing.assert_array_equal(fill_holes(edge, 0.01, baseline_xy=(1.0, 0.0)).z, fill_holes(edge, 0.01).z)


def test_the_error_layers_come_from_the_cell_the_height_comes_from():
    dem = _hole_beside_a_wall()
    sigma = np.where(dem.z > 0.1, 0.003, 0.001)  # the wall's cells 3 mm, the floor's 1 mm
    layered = DEM(dem.x, dem.y, dem.z, SPACING, sigma_match=sigma, sigma_calibration=np.zeros_like(sigma),
                  sigma_level=np.zeros_like(sigma))
    out = fill_holes(layered, 0.01, baseline_xy=(1.0, 0.0))
    np.testing.assert_array_equal(out.sigma_match[:, 4:6], 0.001)


def _rig_json(left_center, right_center):
    def camera(center):
        return {"R": np.eye(3).tolist(), "t": (-np.asarray(center, float)).tolist()}

    return json.dumps({"left": camera(left_center), "right": camera(right_center)})


def test_survey_baseline_xy_reads_the_centres_from_the_rig():
    assert survey_baseline_xy(_rig_json([0.1, 0.3, 2.0], [0.35, 0.31, 2.015])) == pytest.approx((0.25, 0.01))
    assert survey_baseline_xy(_rig_json([0.1, 0.3, 2.0], [0.1, 0.3, 2.2])) is None  # vertical: no direction
    assert survey_baseline_xy("not json") is None
    assert survey_baseline_xy(json.dumps({"left": {}})) is None
