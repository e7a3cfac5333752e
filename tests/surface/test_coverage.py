"""The coverage term of a DEM's error bars: a cell seen in part, or filled from its neighbours, is as uncertain
as the seen relief around it; a wholly seen cell owes nothing to it."""

import numpy as np
import pytest

from jaxstereo import DEM, fill_holes
from jaxstereo._surface.coverage import SEEN_FRACTION, filled_sigma, partial_coverage_sigma


def _step(nx=20, ny=20, high=0.1):
    """Heights (ny, nx) metres: 0 left of column 10, `high` from it on."""
    z = np.zeros((ny, nx))
    z[:, 10:] = high
    return z


def test_wholly_seen_cells_get_nothing_and_a_sparse_cell_half_its_neighbours_range():
    z = _step()
    count = np.full(z.shape, 40.0)
    assert np.all(partial_coverage_sigma(z, count) == 0.0)
    count[5, 10] = 4.0  # a tenth of its neighbours' points, on the step
    sigma = partial_coverage_sigma(z, count)
    coverage = 4.0 / (SEEN_FRACTION * 40.0)
    assert sigma[5, 10] == pytest.approx((1 - coverage) * 0.05)  # its 3x3 spans 0 to 0.1 m
    count[5, 15] = 4.0  # as sparse, on the flat top: nothing to be uncertain about
    assert partial_coverage_sigma(z, count)[5, 15] == 0.0
    assert np.count_nonzero(sigma) == 1


def test_empty_cells_stay_empty():
    z = _step()
    z[3, 3] = np.nan
    count = np.full(z.shape, 40.0)
    count[3, 3] = 0
    assert np.isnan(partial_coverage_sigma(z, count)[3, 3])


def test_a_filled_cell_is_as_uncertain_as_the_seen_heights_within_reach():
    z = _step()
    z[8, 9:11] = np.nan  # two cells across the step, unseen
    layers = {key: np.where(np.isfinite(z), 0.001, np.nan) for key in ("sigma_match", "sigma_calibration",
                                                                       "sigma_level")}
    x = np.arange(20) * 0.005
    dem = DEM(x, x.copy(), z, 0.005, **layers, sigma_coverage=np.where(np.isfinite(z), 0.0, np.nan))
    filled = fill_holes(dem, 0.005)
    assert np.all(np.isfinite(filled.z))
    np.testing.assert_allclose(filled.sigma_coverage[8, 9:11], 0.05)  # the seen cells within one cell: 0 to 0.1
    assert np.count_nonzero(filled.sigma_coverage) == 2
    np.testing.assert_allclose(filled.sigma[8, 9:11], np.sqrt(3 * 0.001**2 + 0.05**2))
    far = dem.z.copy()
    far[:, :] = 0.02
    far[8, 9] = np.nan
    assert filled_sigma(far, 1)[8, 9] == 0.0  # a flat neighbourhood: the fill is as good as a measurement


def test_a_cell_whose_points_lie_on_both_sides_of_a_step_gets_half_their_spread():
    from jaxstereo._surface.coverage import STEP_SPREAD_CELLS, straddle_sigma

    spacing = 0.005
    steepest = 0.005 * np.tan(np.radians(75)) / 2  # a plane at 75 degrees across the cell: its quartiles' spread
    assert steepest < STEP_SPREAD_CELLS * spacing
    spread = np.array([0.0, steepest, 0.03, np.nan])
    np.testing.assert_array_equal(straddle_sigma(spread, spacing), [0.0, 0.0, 0.015, 0.0])


def test_grid_survey_marks_the_cells_that_straddle_a_step_and_no_others():
    """A survey of a slope with a 40 mm step at x = 0.0505 m (inside the cell centred on 0.05): that cell's points
    lie on both sides, its median on the side that holds more, and its coverage std half their spread; the cells
    on the 1:2 slope either side get none."""
    import json

    from jaxstereo import Survey, grid_survey

    rng = np.random.default_rng(4)
    n = 40000
    x, y = rng.uniform(0, 0.1, n), rng.uniform(0, 0.1, n)
    z = x / 2 + 0.04 * (x < 0.0505) + rng.normal(0, 0.0003, n)
    cov = np.zeros((n, 6), np.float32)
    cov[:, 2] = 0.001**2
    rig = {"left": {"R": np.eye(3).tolist(), "t": [0.0, 0.0, -2.0], "fx": 2000.0}, "right": {}}
    survey = Survey(np.column_stack([x, y, z]), np.zeros((n, 3), np.uint8), np.zeros((n, 2)), np.zeros(n, bool),
                    json.dumps(rig), "exact", 0.16, cov, np.full(n, 0.001, np.float32), np.zeros(n, np.float32),
                    np.zeros(n, np.float32))
    dem = grid_survey(survey, 0.005)
    column = int(np.argmin(np.abs(dem.x - 0.05)))
    inner = slice(1, -1)  # the grid's edge cells are half as full
    step = dem.sigma_coverage[inner, column]
    inside = (x >= 0.0475) & (x < 0.0525) & (y > 0.0025) & (y < 0.0975)
    q1, q3 = np.percentile(z[inside], [25, 75])
    assert np.all(step > 0.015)  # 60 % of the cell above the step: its quartiles 40 mm apart
    assert np.median(step) == pytest.approx((q3 - q1) / 2, rel=0.05)
    others = np.delete(dem.sigma_coverage[inner], column, axis=1)[:, 1:-1]
    assert np.all(others == 0.0)
