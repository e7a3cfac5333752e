"""SGBM matching: the two-way consistency check and the fattening filter, on a pair with known disparities."""

import cv2
import numpy as np

import pytest

from jaxstereo import JaxStereoError
from jaxstereo._stereo.matching import MatchOptions, _cross_check, _mirrored_disparity, _one_way, sgbm_disparity

D_BACKGROUND, D_FOREGROUND = 12, 20
SQUARE = (40, 120, 90, 170)  # rows y0:y1, columns x0:x1 of the foreground square in the left image


def _texture(rng, amplitude, blur, shape):
    t = cv2.GaussianBlur(rng.normal(0.0, 1.0, shape).astype(np.float32), (0, 0), blur)
    return amplitude * t / t.std()


def _square_over_fine_speckle(seed=3):
    """A strongly textured square (disparity 20 px) over a faint pixel-scale speckle (12 px), and the truth (h, w).

    The speckle is the kind of surface (sand, the fine grain of an underlayer) over which SGBM's smoothness
    carries a foreground's disparity into the background beside it, where the right image does not see it."""
    rng = np.random.default_rng(seed)
    h, w = 160, 240
    background = 128 + _texture(rng, 4.0, 0.7, (h, w + 40))
    foreground = 128 + _texture(rng, 50.0, 1.5, (h, w + 40))
    left = background[:, :w].copy()
    right = background[:, D_BACKGROUND : D_BACKGROUND + w].copy()  # x_right = x_left - d
    y0, y1, x0, x1 = SQUARE
    left[y0:y1, x0:x1] = foreground[y0:y1, x0:x1]
    right[y0:y1, x0 - D_FOREGROUND : x1 - D_FOREGROUND] = foreground[y0:y1, x0:x1]
    truth = np.full((h, w), float(D_BACKGROUND))
    truth[y0:y1, x0:x1] = D_FOREGROUND
    return np.clip(left, 0, 255).astype(np.uint8), np.clip(right, 0, 255).astype(np.uint8), truth


def test_two_way_check_removes_matches_the_one_way_check_lets_through():
    left, right, truth = _square_over_fine_speckle()
    counts = {}
    for two_way in (False, True):
        # the strips beside occlusions kept: the check alone is measured
        d = sgbm_disparity(left, right, 0, 48, MatchOptions(two_way=two_way, occlusion_reach_px=0))
        found = np.isfinite(d)
        wrong = found & (np.abs(d - truth) > 1.5)
        counts[two_way] = (int(wrong.sum()), int((found & ~wrong).sum()))
    (wrong_one, right_one), (wrong_two, right_two) = counts[False], counts[True]
    assert wrong_one > 1000  # the case is hard: SGBM's own left-right check passes many wrong matches
    assert wrong_two < 0.4 * wrong_one
    assert right_two > 0.97 * right_one  # and the correct ones stay


@pytest.mark.parametrize("seed", [3, 4])
def test_the_check_on_rows_averaged_in_pairs_drops_the_wrong_matches_the_full_size_check_drops(seed):
    """The second run on the pair with its rows averaged in pairs (half its cost): on the pixel-scale speckle,
    the texture that rows averaged weaken most, it passes no more wrong matches than the full-size run (105 and
    122 against 108 and 124, of 1045 and 1024 one way) and keeps 98.8 % of the correct ones."""
    left, right, truth = _square_over_fine_speckle(seed)
    counts = {}
    for rows in (1, 2):
        d = sgbm_disparity(left, right, 0, 48, MatchOptions(check_rows=rows, occlusion_reach_px=0))
        found = np.isfinite(d)
        wrong = found & (np.abs(d - truth) > 1.5)
        counts[rows] = (int(wrong.sum()), int((found & ~wrong).sum()))
    (wrong_full, right_full), (wrong_pairs, right_pairs) = counts[1], counts[2]
    assert wrong_full < 200
    assert wrong_pairs <= 1.05 * wrong_full
    assert right_pairs > 0.98 * right_full


def test_the_mirrored_run_on_rows_in_pairs_is_the_full_size_run_of_the_averaged_pair():
    """Against a reference built another way (OpenCV's resize to half the rows, nearest-neighbour back): the
    same disparities; an odd last row has no pair and stays unmatched, and a one-row pair is matched at full size."""
    left, right, _ = _square_over_fine_speckle()
    options = MatchOptions()
    h, w = left.shape
    small = [cv2.flip(cv2.resize(image, (w, h // 2), interpolation=cv2.INTER_AREA), 1) for image in (right, left)]
    expected = cv2.resize(np.ascontiguousarray(_one_way(*small, 0, 48, options)[:, ::-1]), (w, h),
                          interpolation=cv2.INTER_NEAREST)
    np.testing.assert_array_equal(_mirrored_disparity(left, right, 0, 48, options), expected)
    assert np.isfinite(expected).mean() > 0.7
    odd = _mirrored_disparity(left[:-1], right[:-1], 0, 48, options)
    assert odd.shape == (h - 1, w) and np.isnan(odd[-1]).all()
    np.testing.assert_array_equal(odd[:-1], _mirrored_disparity(left[:-2], right[:-2], 0, 48, options))
    # a single row has no pair: matched at full size, not refused by OpenCV's resize
    assert _mirrored_disparity(left[:1], right[:1], 0, 48, options).shape == (1, w)


def test_check_rows_below_one_is_refused():
    with pytest.raises(JaxStereoError, match="check_rows"):
        MatchOptions(check_rows=0)


def test_sgbm_fattening_beside_a_textured_square_is_dropped():
    """The analytic pair above: the two-way check leaves a few hundred background pixels with the
    square's disparity; at the square's outline the filter drops most of them and few correct matches."""
    left, right, truth = _square_over_fine_speckle()
    counts = {}
    for reach in (0, 12):
        d = sgbm_disparity(left, right, 0, 48, MatchOptions(fattening_reach_px=reach))
        found = np.isfinite(d)
        wrong = found & (np.abs(d - truth) > 1.5)
        counts[reach] = (int(wrong.sum()), int((found & ~wrong).sum()))
    (wrong_before, right_before), (wrong_after, right_after) = counts[0], counts[12]
    assert wrong_before > 200
    assert wrong_after < 0.5 * wrong_before
    assert right_after > 0.98 * right_before


def test_cross_check_against_a_numpy_reference():
    rng = np.random.default_rng(0)
    left = rng.uniform(0.0, 30.0, (20, 50)).astype(np.float32)
    left[rng.random(left.shape) < 0.1] = np.nan
    right = rng.uniform(0.0, 30.0, (20, 50)).astype(np.float32)
    right[rng.random(right.shape) < 0.1] = np.nan
    # make about half of the pairs consistent
    for v, u in zip(*np.nonzero(np.isfinite(left))):
        ur = int(np.rint(u - left[v, u]))
        if 0 <= ur < 50 and rng.random() < 0.5:
            right[v, ur] = left[v, u] + rng.uniform(-0.9, 0.9)
    expected = left.copy()
    for v, u in zip(*np.nonzero(np.isfinite(left))):
        ur = int(np.rint(u - left[v, u]))
        if not (0 <= ur < 50 and abs(right[v, ur] - left[v, u]) <= 1.0):
            expected[v, u] = np.nan
    got = left.copy()
    _cross_check(got, right, 1.0)
    np.testing.assert_array_equal(got, expected)
    assert 0.2 < np.isfinite(got).mean() < 0.8
