"""Foreground fattening: disparity steps off the image's edges are moved back by dropping the band between."""

import numpy as np
import pytest

from jaxstereo._stereo.fattening import beside_occlusions, drop_fattened

H, W, EDGE = 30, 80, 50  # the foreground (a bright block) starts at column EDGE


def _scene(rng, carried: int):
    """A weakly textured background (columns < EDGE, disparity 10) beside a bright foreground (disparity 14)
    whose disparity SGBM carried `carried` pixels over the background."""
    image = 100 + rng.normal(0.0, 2.0, (H, W, 3))
    image[:, EDGE:] += 80
    disparity = np.full((H, W), 10.0) + rng.normal(0.0, 0.1, (H, W))
    disparity[:, EDGE - carried :] = 14.0
    return np.clip(image, 0, 255).astype(np.uint8), disparity.astype(np.float32)


@pytest.mark.parametrize("carried", [1, 4, 9])
def test_the_band_between_a_step_and_the_edge_is_flagged_exactly(carried):
    image, disparity = _scene(np.random.default_rng(carried), carried)
    flagged = drop_fattened(image, disparity)
    expected = np.zeros((H, W), bool)
    expected[:, EDGE - carried : EDGE] = True
    np.testing.assert_array_equal(flagged, expected)
    # mirrored (the foreground on the left) and transposed (a step along the columns): the same band
    np.testing.assert_array_equal(drop_fattened(image[:, ::-1], disparity[:, ::-1]), expected[:, ::-1])
    np.testing.assert_array_equal(drop_fattened(image.transpose(1, 0, 2), disparity.T), expected.T)


def test_a_step_on_the_edge_or_beyond_reach_and_gaps_are_left_alone():
    image, disparity = _scene(np.random.default_rng(0), 0)
    assert not drop_fattened(image, disparity).any()  # the step is on the edge
    image, disparity = _scene(np.random.default_rng(1), 15)
    assert not drop_fattened(image, disparity, reach_px=12).any()  # the edge lies beyond reach
    assert drop_fattened(image, disparity, reach_px=16).sum() == H * 15
    image, disparity = _scene(np.random.default_rng(2), 4)
    disparity[:, EDGE - 10 : EDGE - 4] = np.nan  # unmatched pixels between the background and the band
    assert not drop_fattened(image, disparity, gap_px=4).any()
    assert drop_fattened(image, disparity, gap_px=6).sum() == H * 4


def _occluded_row(rise: float, gap: int = 5) -> np.ndarray:
    """One row (1, W): background disparity 10 up to column EDGE - gap, an unmatched strip of `gap` pixels, then a
    foreground `rise` pixels higher."""
    row = np.full((1, W), 10.0, np.float32)
    row[:, EDGE - gap : EDGE] = np.nan
    row[:, EDGE:] += rise
    return row


def test_the_matches_left_of_an_occluded_strip_are_flagged_and_nothing_else():
    flagged = beside_occlusions(_occluded_row(5.0), reach_px=12)
    expected = np.zeros((1, W), bool)
    expected[:, EDGE - 5 - 12 : EDGE - 5] = True  # the 12 matched pixels left of the strip
    np.testing.assert_array_equal(flagged, expected)
    # a strip whose disparity falls left to right (the right camera sees the lower side) or rises by less than
    # the step: nothing
    assert not beside_occlusions(_occluded_row(5.0)[:, ::-1], reach_px=12).any()
    assert not beside_occlusions(_occluded_row(1.0), reach_px=12).any()
    # no strip, a step between neighbours (fattening's case), or the filter off: nothing
    assert not beside_occlusions(_occluded_row(5.0, gap=0), reach_px=12).any()
    assert not beside_occlusions(_occluded_row(5.0), reach_px=0).any()
    # a strip near the row's start flags what there is; unmatched pixels stay unflagged
    row = _occluded_row(5.0)
    row[:, : EDGE - 10] = np.nan
    np.testing.assert_array_equal(np.flatnonzero(beside_occlusions(row, reach_px=12)), np.arange(EDGE - 10, EDGE - 5))
