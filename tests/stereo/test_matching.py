"""SGBM matching: the two-way consistency check and the fattening filter, on a pair with known disparities."""

import cv2
import numpy as np

from jaxstereo._stereo.matching import MatchOptions, _cross_check, sgbm_disparity

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
