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
