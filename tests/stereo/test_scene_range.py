"""The disparity search narrowed by a coarse match (`scene_search`), on pairs with known disparities."""

import cv2
import numpy as np
import pytest

from jaxstereo._stereo.matching import MatchOptions, sgbm_disparity
from jaxstereo._stereo.scene_range import scene_search

SEARCH = (40, 128)  # the rig's range: disparities 40 to 167 px


def _inclined_pair(d_top=70.0, d_bottom=100.0, shape=(480, 640), seed=5):
    """A textured surface whose disparity grows linearly from `d_top` (first row) to `d_bottom` (last row), as a
    sloping bed seen by a nadir rig: the left and right images (h, w) uint8 and the true disparity (h, w) px."""
    h, w = shape
    rng = np.random.default_rng(seed)
    texture = cv2.GaussianBlur(rng.normal(0.0, 1.0, (h, w + 200)).astype(np.float32), (0, 0), 1.2)
    texture = np.clip(128 + 40 * texture / texture.std(), 0, 255).astype(np.float32)
    truth = np.repeat(np.linspace(d_top, d_bottom, h)[:, None], w, axis=1)
    columns = np.arange(w, dtype=np.float32)[None, :]
    rows = np.repeat(np.arange(h, dtype=np.float32)[:, None], w, axis=1)
    left = texture[:, :w]
    # x_right = x_left - d: the right image at column x shows the surface point at left column x + d
    right = cv2.remap(texture, (columns + truth).astype(np.float32), rows, cv2.INTER_CUBIC)
    return np.rint(left).astype(np.uint8), np.clip(np.rint(right), 0, 255).astype(np.uint8), truth


def test_the_search_narrows_to_the_scene_and_the_matches_stay():
    left, right, truth = _inclined_pair()
    first, count = scene_search(left, right, SEARCH)
    assert count % 16 == 0 and SEARCH[0] <= first and first + count <= SEARCH[0] + SEARCH[1]
    assert first <= 70 - 8 and first + count > 100 + 8  # the scene's 70-100 px and a margin
    assert count <= 64  # of 128: 30 px of scene, 16 px either side, rounded up to 16
    full, narrowed = (sgbm_disparity(left, right, *search, MatchOptions()) for search in (SEARCH, (first, count)))
    both = np.isfinite(full) & np.isfinite(narrowed)
    assert both.sum() > 0.99 * np.isfinite(full).sum()
    # the same matches: SGBM's paths see fewer disparities, so its sub-pixel values may differ a little
    assert np.mean(np.abs(full - narrowed)[both] > 0.1) < 0.01
    off_full, off_narrowed = (np.mean(np.abs(d - truth)[np.isfinite(d)] > 1) for d in (full, narrowed))
    assert off_narrowed <= off_full + 1e-3


@pytest.mark.parametrize("case", ["narrow search", "small pair", "no texture"])
def test_the_search_is_kept_where_a_coarse_match_cannot_bound_the_scene(case):
    left, right, _ = _inclined_pair()
    search = SEARCH
    if case == "narrow search":
        search = (60, 48)
    elif case == "small pair":
        left, right = left[:200, :300], right[:200, :300]
    else:
        left, right = np.full_like(left, 128), np.full_like(right, 128)
    assert scene_search(left, right, search) == search


def test_matches_at_the_ends_of_the_coarse_range_do_not_widen_it():
    """A dark band down the left edge, where SGBM's cost has nothing to choose by and it falls to an end of the
    range: those are not disparities found, and the search still narrows to the textured scene."""
    left, right, _ = _inclined_pair()
    left[:, :120] = 1  # not black (black is outside the image for SGBM's checks), but flat
    right[:, :120] = 1
    first, count = scene_search(left, right, SEARCH)
    assert first <= 62 and first + count > 108 and count <= 64
