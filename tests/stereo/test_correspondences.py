"""The refinement's correspondences: which Lucas-Kanade window each match is measured with."""

import numpy as np

from jaxstereo._stereo.correspondences import measured_as_the_survey, plane_residual_rms


def test_plane_residual_is_zero_on_a_plane_and_the_lstsq_residual_elsewhere():
    rng = np.random.default_rng(1)
    h, w, window = 60, 80, 31
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    plane = 200.0 + 0.3 * u - 0.1 * v
    rough = plane + 0.004 * (u - 40.0) ** 2 + rng.normal(0.0, 0.2, (h, w))
    rough[rng.random((h, w)) < 0.2] = np.nan  # unmatched pixels
    rows, cols = np.array([30, 20, 40, 2]), np.array([40, 25, 60, 2])
    assert np.allclose(plane_residual_rms(plane, rows, cols, window)[:3], 0.0, atol=1e-9)
    got = plane_residual_rms(rough, rows, cols, window)
    half = window // 2
    for k, (r, c) in enumerate(zip(rows[:3], cols[:3])):  # numpy reference: lstsq on the box's matched pixels
        patch = rough[r - half : r + half + 1, c - half : c + half + 1]
        dy, dx = np.mgrid[-half : half + 1, -half : half + 1]
        ok = np.isfinite(patch)
        design = np.stack([np.ones(ok.sum()), dx[ok], dy[ok]], axis=1)
        coef, *_ = np.linalg.lstsq(design, patch[ok], rcond=None)
        assert abs(got[k] - np.sqrt(np.mean((patch[ok] - design @ coef) ** 2))) < 1e-9
    # The curvature (0.004 px/px^2 over +-15 px: 0.27 px RMS from a plane) with the noise (0.2 px): about 0.33 px.
    assert 0.28 < got[0] < 0.40
    # In the corner the box lies mostly outside the image: fewer than half its pixels, no value.
    assert np.isnan(got[3])


def test_measured_as_the_survey_takes_columns_from_the_disparity_and_rows_from_the_images():
    """A rectified pair whose right image is the left one moved 0.35 px down (a row offset, as an imperfect rig
    leaves) and 12 px left: the rows come from Lucas-Kanade within 0.05 px, the columns are the disparity given (the
    survey's), and a match without one, or tracked off the image, is dropped."""
    import cv2

    rng = np.random.default_rng(4)
    left = cv2.GaussianBlur(rng.uniform(0, 255, (240, 320)).astype(np.float32), (0, 0), 1.5)
    shift = np.float32([[1, 0, -12.0], [0, 1, 0.35]])
    right = cv2.warpAffine(left, shift, (320, 240), flags=cv2.INTER_CUBIC)
    left, right = (np.clip(im, 0, 255).astype(np.uint8) for im in (left, right))
    left_px = np.array([[100.0, 80.0], [150.0, 120.0], [200.0, 160.0], [250.0, 100.0], [5.0, 120.0]])
    start = left_px - [12.0, 0.0]  # SGBM's whole-pixel match on the rectified row
    disparity = np.array([12.1, 11.9, np.nan, 12.0, 12.0])  # as the survey measured it (px)
    rough = np.array([False, True, False, False, False])
    kept_left, kept_right = measured_as_the_survey(left, right, left_px, start, disparity, rough)
    assert kept_left.tolist() == left_px[[0, 1, 3]].tolist()  # no disparity: dropped; off the image: dropped
    assert np.allclose(kept_right[:, 0], kept_left[:, 0] - disparity[[0, 1, 3]])
    assert np.allclose(kept_right[:, 1], kept_left[:, 1] + 0.35, atol=0.05)  # 0.38 measured
