"""The right camera's grey levels mapped onto the left's at matched pixels, against known response differences."""

import dataclasses

import numpy as np
import pytest

from jaxstereo._stereo.exposure import MIN_LEVEL_CHANGE, apply_exposure, fit_exposure, match_exposure, matched_levels

SHIFT = 9  # px: x_right = x_left - SHIFT


def _scene(seed=0, h=120, w=200):
    """A colour texture (h, w + SHIFT, 3) uint8 whose levels cover 20-235, as a scene's do."""
    rng = np.random.default_rng(seed)
    return rng.integers(20, 236, (h, w + SHIFT, 3)).astype(np.uint8)


def _pair(scene, respond=None):
    """The left and the right image of `scene` (the right one through the response `respond`, levels -> levels,
    rounded), and the true disparity of every left pixel that the right image sees."""
    left, right = scene[:, :-SHIFT], scene[:, SHIFT:].astype(np.float64)
    if respond is not None:
        right = respond(right)
    right = np.clip(np.rint(right), 0, 255).astype(np.uint8)
    disparity = np.full(left.shape[:2], float(SHIFT), np.float32)
    disparity[:, :SHIFT] = np.nan
    return np.ascontiguousarray(left), right, disparity


def test_matched_levels_pair_each_left_pixel_with_the_right_pixel_it_matched():
    left, right, disparity = _pair(_scene())
    disparity[5, 40] = np.nan
    a, b = matched_levels(left, right, disparity, step=1)
    assert a.shape == b.shape == (np.isfinite(disparity).sum(), 3)
    assert np.array_equal(a, b)  # the same scene points, the same levels
    grey = matched_levels(left[..., 0], right[..., 0], disparity, step=2)
    assert grey[0].shape[1] == 1 and np.array_equal(*grey)


def test_cameras_that_agree_are_left_as_they_are():
    rng = np.random.default_rng(1)
    # JPEG-like noise of about a grey level between the two views of the same points
    left, right, disparity = _pair(_scene(), lambda r: r + rng.normal(0.0, 1.0, r.shape))
    match = fit_exposure(*matched_levels(left, right, disparity))
    assert not match.applied and match.gain == (1.0, 1.0, 1.0) and match.offset == (0.0, 0.0, 0.0)
    assert apply_exposure(right, match) is right
    assert max(match.residual) < 0.5  # grey levels: the noise averages out over the quantiles (0.33)
    left, right, disparity = _pair(_scene(1, 240, 360), lambda r: r + rng.normal(0.0, 1.0, r.shape))
    mapped, whole = match_exposure(left, right, disparity)
    assert not whole.applied and mapped is right  # nor a gain varying over the image
    assert 0.995 < whole.shading.low <= whole.shading.high < 1.005


def test_an_exposure_and_white_balance_difference_is_undone():
    gains, black = np.array([0.9, 0.8, 1.05]), 6.0  # per channel (none clips), and a raised black level
    left, right, disparity = _pair(_scene(2), lambda r: gains * r + black)
    mapped, match = match_exposure(left, right, disparity)
    assert match.applied
    assert np.allclose(match.gain, 1 / gains, rtol=0.01) and np.allclose(match.offset, -black / gains, atol=1.0)
    matched = np.isfinite(disparity)
    error = mapped[:, : -SHIFT].astype(float) - left[:, SHIFT:]  # each matched pixel against its left pixel
    assert matched[:, SHIFT:].all() and np.abs(error).max() <= 2  # rounding twice, and the darkened levels merged (1)
    assert np.abs(error).mean() < 0.5  # 0.15


def test_a_tone_curve_of_another_shape_is_followed_and_reported():
    gamma = 1.3
    left, right, disparity = _pair(_scene(3), lambda r: 255 * (r / 255) ** gamma)
    match = fit_exposure(*matched_levels(left, right, disparity))
    low, high = np.quantile(right, [0.1, 0.9])  # the levels the map joins; beyond them it follows the best line
    levels = np.arange(int(np.ceil(low)), int(high) + 1)
    inverse = 255 * (levels / 255) ** (1 / gamma)
    assert np.abs(match.table[levels] - inverse[:, None]).max() < 1.0  # grey levels (0.83): the curve, not a line
    assert min(match.residual) > 2.0  # the best straight line is off by more (2.9): a response of another shape


def test_clipped_levels_do_not_bend_the_map():
    """A right camera exposed a third longer saturates its brightest levels: those quantiles are left out, and
    the map still undoes the gain over the levels it kept."""
    gain = 4 / 3
    left, right, disparity = _pair(_scene(4), lambda r: gain * r)
    assert (right == 255).mean() > 0.15
    match = fit_exposure(*matched_levels(left, right, disparity))
    assert np.allclose(match.gain, 1 / gain, rtol=0.01) and np.allclose(match.offset, 0.0, atol=1.0)  # 0.750, 0.03


@pytest.mark.parametrize("grey", [False, True])
def test_the_rectified_images_black_border_stays_black(grey):
    left, right, disparity = _pair(_scene(5), lambda r: 0.7 * r)
    right[:, -12:] = 0  # outside the right camera's view after rectification
    if grey:
        left, right = left[..., 1].copy(), right[..., 1].copy()
    mapped, match = match_exposure(left, right, disparity)
    assert match.applied and mapped.shape == right.shape and mapped.dtype == np.uint8
    assert (mapped[:, -12:] == 0).all() and (mapped[:, :-12] > 0).all()
    assert abs(float(np.median(mapped[:, :-12])) - float(np.median(left[:, SHIFT:-12]))) <= 2 * MIN_LEVEL_CHANGE


def test_a_gain_that_varies_smoothly_over_the_image_is_undone():
    """The right image darker toward its left edge and its corners (a vignetting the left camera meets elsewhere):
    no one map of the levels undoes it; the smooth gain fitted at the matches does, to about a grey level."""
    h, w = 240, 360
    columns, rows = np.meshgrid(np.arange(w + SHIFT) - SHIFT, np.arange(h))  # the right image's own columns
    x, y = 2 * columns / (w - 1) - 1, 2 * rows / (h - 1) - 1
    field = np.exp(-0.04 + 0.03 * x - 0.02 * x * x - 0.015 * y * y)[..., None]  # 0.90-0.97 over the image
    left, right, disparity = _pair(_scene(6, h, w), lambda r: r * field[:, SHIFT:])
    mapped, match = match_exposure(left, right, disparity)
    assert match.shading.applied
    error = mapped[:, :-SHIFT].astype(float) - left[:, SHIFT:]
    assert np.abs(error).mean() < 0.6 and np.percentile(np.abs(error), 99) <= 2  # grey levels (0.17, 1)
    levels_only = apply_exposure(right, dataclasses.replace(match, shading=None))
    assert np.abs(levels_only[:, :-SHIFT].astype(float) - left[:, SHIFT:]).mean() > 1.5  # one map is not enough (2.06)
