import warnings

import numpy as np

from jaxstereo._surface.nan_median import nan_median


def test_nan_median_equals_numpys_to_the_last_bit_with_any_share_of_gaps():
    rng = np.random.default_rng(3)
    for _ in range(200):
        values = rng.normal(size=(rng.integers(1, 12), rng.integers(1, 25)))
        values[rng.uniform(size=values.shape) < rng.uniform()] = np.nan  # from no gap to rows of gaps only
        for axis in (0, 1):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # numpy's "All-NaN slice"
                expected = np.nanmedian(values, axis=axis)
            np.testing.assert_array_equal(nan_median(values, axis), expected)
    assert np.isnan(nan_median(np.zeros((3, 0)), axis=1)).all() and nan_median(np.zeros((3, 0)), axis=1).shape == (3,)
