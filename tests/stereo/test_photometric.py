"""The photometric check of dense matches, against numpy references and a pair with known disparities."""

import cv2
import numpy as np
import pytest

from jaxstereo import JaxStereoError
from jaxstereo._stereo.photometric import local_residual_scale, photometric_outliers, photometric_residual


def _bilinear(image, x, y):
    """numpy reference: image (h, w, c) sampled bilinearly at (x, y), coordinates clamped to the image."""
    h, w = image.shape[:2]
    x = np.clip(x, 0, w - 1)
    y = np.clip(y, 0, h - 1)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    top = image[y0, x0] * (1 - fx) + image[y0, x1] * fx
    bottom = image[y1, x0] * (1 - fx) + image[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


def test_residual_matches_a_numpy_reference():
    rng = np.random.default_rng(0)
    left = rng.integers(0, 256, (40, 60, 3), dtype=np.uint8)
    right = cv2.GaussianBlur(rng.integers(0, 256, (40, 60, 3), dtype=np.uint8), (0, 0), 1.5)
    disparity = rng.uniform(3.0, 9.0, (40, 60)).astype(np.float32)
    disparity[5:9, 20:30] = np.nan
    offset = rng.uniform(-0.4, 0.4, (40, 60)).astype(np.float32)
    got = photometric_residual(left, right, disparity, offset)

    v, u = np.mgrid[0:40, 0:60]
    valid = np.isfinite(disparity)
    sampled = _bilinear(right.astype(np.float64), u - np.nan_to_num(disparity), v + np.where(valid, offset, 0.0))
    difference = np.where(valid, np.abs(left - sampled).sum(axis=2), 0.0)
    expected = np.full((40, 60), np.nan)
    for i in range(1, 39):
        for j in range(1, 59):
            if valid[i, j]:
                window = valid[i - 1 : i + 2, j - 1 : j + 2]
                expected[i, j] = difference[i - 1 : i + 2, j - 1 : j + 2][window].mean()
    inner = np.zeros_like(valid)
    inner[1:-1, 1:-1] = True
    np.testing.assert_array_equal(np.isnan(got), ~valid)
    # cv2.remap's bilinear weights are fixed point (OpenCV 4: 1/32 px): each channel's sample may be off by up to
    # 1/64 of its neighbours' difference along each axis
    step = max(np.abs(np.diff(right.astype(float), axis=a)).max() for a in (0, 1))
    np.testing.assert_allclose(got[inner & valid], expected[inner & valid], atol=3 * 2 * step / 64 + 0.01)


def test_local_scale_is_the_block_median():
    rng = np.random.default_rng(1)
    residual = rng.gamma(2.0, 3.0, (256, 384)).astype(np.float32)
    residual[:128, :128] *= 4  # one block four times noisier
    residual[rng.random(residual.shape) < 0.05] = np.nan
    scale = local_residual_scale(residual, block=128)
    for bi in range(2):
        for bj in range(3):
            block = residual[bi * 128 : (bi + 1) * 128, bj * 128 : (bj + 1) * 128]
            centre = scale[bi * 128 + 64, bj * 128 + 64]
            assert centre == pytest.approx(np.nanmedian(block), abs=0.25)  # quantised to 1/4 grey level


def test_local_scale_of_a_sparsely_matched_block_is_the_whole_images_median():
    rng = np.random.default_rng(3)
    residual = rng.gamma(2.0, 3.0, (256, 384)).astype(np.float32)
    residual[:128, 128:256] *= 10  # a block ten times noisier than the rest...
    sparse = np.zeros((128, 128), bool)
    sparse[::4, ::4] = True  # ...with a sixteenth of its pixels matched: fewer than an eighth
    residual[:128, 128:256][~sparse] = np.nan
    scale = local_residual_scale(residual, block=128)
    assert scale[64, 128 + 64] == pytest.approx(np.nanmedian(residual), abs=0.05)  # its own median is about 50
    assert scale[128 + 64, 64] == pytest.approx(np.nanmedian(residual[128:, :128]), abs=0.25)  # a full block's own


def _textured_pair(seed=2):
    """A background plane at disparity 12 and a foreground square at 20, both with random colour texture;
    the exact disparity map (h, w) and the images (h, w, 3)."""
    rng = np.random.default_rng(seed)
    h, w = 200, 320
    background = cv2.GaussianBlur(rng.integers(0, 256, (h, w + 40, 3)).astype(np.float32), (0, 0), 1.2)
    foreground = cv2.GaussianBlur(rng.integers(0, 256, (h, w + 40, 3)).astype(np.float32), (0, 0), 1.2)
    d_bg, d_fg = 12, 20
    u = np.arange(w)
    left = background[:, u + 20].copy()
    right = background[:, u + 20 + d_bg].copy()
    rows, cols = slice(60, 140), slice(140, 220)
    left[rows, cols] = foreground[rows, 20 + np.arange(140, 220)]
    right[rows, 140 - d_fg : 220 - d_fg] = foreground[rows, 20 + np.arange(140, 220)]
    disparity = np.full((h, w), float(d_bg), np.float32)
    disparity[rows, cols] = d_fg
    noise = rng.normal(0.0, 2.0, (2, h, w, 3))
    return [np.clip(im + n, 0, 255).astype(np.uint8) for im, n in zip((left, right), noise)], disparity


def test_fattened_foreground_is_dropped_and_correct_matches_kept():
    (left, right), disparity = _textured_pair()
    fattened = disparity.copy()
    # Left pixels 132-139 of the square's rows see background that the square hides in the right image; SGBM
    # carries the square's disparity onto them.
    fattened[60:140, 132:140] = 20.0
    fattened[:, :40] = np.nan  # matches that would fall outside the right image
    out = photometric_outliers(left, right, fattened)
    band = np.zeros_like(out)
    band[60:140, 132:140] = True
    correct = np.isfinite(fattened) & ~band
    assert out[band].mean() >= 0.9
    assert out[correct].mean() <= 0.005
    assert not out[~np.isfinite(fattened)].any()


def test_residual_is_small_at_the_true_disparity_and_large_off_it():
    (left, right), disparity = _textured_pair(seed=3)
    disparity[:, :40] = np.nan
    shifted = disparity + 3.0  # every match 3 px off
    residual_right = photometric_residual(left, right, disparity)
    residual_wrong = photometric_residual(left, right, shifted)
    assert np.nanmedian(residual_wrong) > 5 * np.nanmedian(residual_right)


def test_bad_arguments_are_refused():
    (left, right), disparity = _textured_pair()
    with pytest.raises(JaxStereoError, match="positive"):
        photometric_outliers(left, right, disparity, max_ratio=0.0)
    with pytest.raises(JaxStereoError, match="differ in size"):
        photometric_residual(left, right[:-1], disparity)
    with pytest.raises(JaxStereoError, match="no match"):
        local_residual_scale(np.full((10, 10), np.nan, np.float32))
