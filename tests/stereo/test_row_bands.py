"""Bands of rows on threads (`map_row_bands`): how many, how tall, and the whole image's values from them."""

import cv2
import numpy as np
import pytest

from jaxstereo._stereo import row_bands
from jaxstereo._stereo.row_bands import MAX_BAND_PIXELS, map_row_bands

HALO = 30


def _vertical_sums(image: np.ndarray, calls: list):
    """`fn` for `map_row_bands`: each pixel's sum over the 2 HALO + 1 rows around it (reflected at the band's
    edges, so exact only HALO rows in), recording the band it was called on. Whole numbers: exact in float32."""

    def fn(start: int, stop: int) -> tuple:
        calls.append((start, stop))
        return (cv2.boxFilter(image[start:stop], -1, (1, 2 * HALO + 1), normalize=False), None)

    return fn


@pytest.mark.parametrize(("shape", "cores", "bands"), [((1152, 1728), 2, 4), ((1152, 1728), 4, 4),
                                                       ((3000, 4000), 2, 24), ((240, 320), 2, 2)])
def test_bands_keep_within_the_pixel_budget_in_a_multiple_of_the_threads(monkeypatch, shape, cores, bands):
    """The development flume's 1728 x 1152 pair: four bands of 288 rows on 2 cores, and on 4; a 12-megapixel
    image: 24 bands of 125 rows (the fewest in a multiple of 2 within the budget); a small image: one band a
    core. Each band's own rows hold at most `MAX_BAND_PIXELS` pixels, and the bands give the whole image's
    values exactly."""
    monkeypatch.setattr(row_bands, "available_cores", lambda: cores)
    h, w = shape
    image = np.random.default_rng(0).integers(0, 256, shape).astype(np.float32)
    calls = []
    banded, none = map_row_bands(_vertical_sums(image, calls), h, HALO, width=w)
    assert none is None
    assert len(calls) == bands
    own = np.diff([round(h * i / bands) for i in range(bands + 1)])
    assert own.max() * w <= MAX_BAND_PIXELS or bands == cores
    assert [stop - start for start, stop in sorted(calls)] == [
        min(h, e1 + HALO) - max(0, e0 - HALO) for e0, e1 in zip(np.cumsum([0, *own[:-1]]), np.cumsum(own))]
    (whole,) = _vertical_sums(image, [])(0, h)[:1]
    np.testing.assert_array_equal(banded, whole)


def test_without_the_width_there_is_one_band_a_thread(monkeypatch):
    monkeypatch.setattr(row_bands, "available_cores", lambda: 2)
    calls = []
    map_row_bands(_vertical_sums(np.zeros((1152, 1728), np.float32), calls), 1152, HALO)
    assert sorted(calls) == [(0, 576 + HALO), (576 - HALO, 1152)]
