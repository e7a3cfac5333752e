"""Dense matching of a rectified pair with OpenCV's semi-global block matching (SGBM)."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from ._errors import JaxStereoError


@dataclasses.dataclass(frozen=True)
class MatchOptions:
    """SGBM settings.

    **Fields:** `block_size` (odd, pixels); `mode` ("3way", "sgbm", "hh"); `uniqueness` ratio (%);
    `disp12_max_diff` left-right consistency tolerance (pixels); `speckle_window` and `speckle_range`
    (pixels) for the speckle filter; `margin_px` added to the disparity range derived from the rig.
    """

    block_size: int = 5
    mode: str = "3way"
    uniqueness: int = 10
    disp12_max_diff: int = 1
    speckle_window: int = 100
    speckle_range: int = 2
    margin_px: int = 8

    def __post_init__(self):
        if self.block_size < 1 or self.block_size % 2 == 0:
            raise JaxStereoError(f"block_size must be an odd positive number of pixels, got {self.block_size}")
        if self.mode not in ("3way", "sgbm", "hh"):
            raise JaxStereoError(f"SGBM mode must be 3way, sgbm or hh, got {self.mode!r}")


_MODES = {"3way": cv2.STEREO_SGBM_MODE_SGBM_3WAY, "sgbm": cv2.STEREO_SGBM_MODE_SGBM, "hh": cv2.STEREO_SGBM_MODE_HH}


def disparity_search_range(d_min: float, d_max: float, margin_px: int) -> tuple[int, int]:
    """SGBM's `(minDisparity, numDisparities)` covering [d_min, d_max] with a margin; numDisparities % 16 == 0."""
    lo = int(np.floor(d_min)) - margin_px
    span = int(np.ceil(d_max)) + margin_px - lo
    num = max(16, int(np.ceil(span / 16.0)) * 16)
    return lo, num


def sgbm_disparity(left: np.ndarray, right: np.ndarray, min_disparity: int, num_disparities: int,
                   options: MatchOptions = MatchOptions()) -> np.ndarray:
    """Disparity (h, w) float32 in pixels of the left rectified image (`x_right = x_left - d`); NaN where
    no reliable match was found (failed uniqueness, left-right check or speckle filter).
    """
    if left.shape != right.shape:
        raise JaxStereoError(f"rectified images differ in shape: {left.shape} vs {right.shape}")
    channels = 1 if left.ndim == 2 else left.shape[2]
    bs = options.block_size
    matcher = cv2.StereoSGBM_create(
        minDisparity=min_disparity, numDisparities=num_disparities, blockSize=bs,
        P1=8 * channels * bs * bs, P2=32 * channels * bs * bs, disp12MaxDiff=options.disp12_max_diff,
        uniquenessRatio=options.uniqueness, speckleWindowSize=options.speckle_window,
        speckleRange=options.speckle_range, mode=_MODES[options.mode],
    )
    # SGBM leaves the first minDisparity + numDisparities columns of the left image unmatched, though their
    # matches lie in the right image from column d on: pad both images on the left by numDisparities columns,
    # then drop the matches that land in the padding (their true match is outside the right image).
    pad = num_disparities
    border = [cv2.copyMakeBorder(im, 0, 0, pad, 0, cv2.BORDER_CONSTANT, value=0) for im in (left, right)]
    raw = matcher.compute(border[0], border[1])[:, pad:]
    disparity = raw.astype(np.float32) / 16.0
    invalid = raw <= (min_disparity - 1) * 16
    # Pixels whose support window leaves either image are unreliable too.
    valid_left = left.reshape(left.shape[0], left.shape[1], -1).max(axis=-1) > 0
    columns = np.arange(left.shape[1], dtype=np.float32)[None, :]
    outside = columns - disparity < bs // 2
    disparity[invalid | ~valid_left | outside] = np.nan
    return disparity


def refine_disparity(left: np.ndarray, right: np.ndarray, disparity: np.ndarray, row_offset: np.ndarray | None = None,
                     window: int = 7, iterations: int = 4, max_shift_px: float = 0.5) -> np.ndarray:
    """Sub-pixel refinement of a disparity map along each match's epipolar curve, bounded and cost-checked.

    SGBM's parabola fit locks disparities towards integers. Each step warps the right image by the current
    disparity (and by `row_offset`, the vertical position of the exact epipolar curve, when the
    rectification is not exact) and solves, over a `window` x `window` box around every pixel, the
    least-squares horizontal shift that best aligns it with the left image (zero-mean grey levels, so
    that a brightness difference between the views does not pull it). A refined value is kept only
    where it stays within `max_shift_px` of SGBM's, the texture is strong enough to determine it, and
    its window's matching cost (sum of squared differences) is no higher than at SGBM's own value;
    elsewhere SGBM's value (moved onto the curve) is kept. It therefore cannot drift off a match.

    **Arguments:** rectified `left`, `right` images (grey or RGB, uint8); `disparity` (h, w) pixels, NaN
    for no match (`x_right = x_left - d`); `row_offset` (h, w) pixels or None.

    **Returns:** the refined disparity (h, w), NaN where the input was NaN.
    """
    L = _zero_mean(_grey_float(left), window)
    Rimg = _zero_mean(_grey_float(right), window)
    h, w = L.shape
    u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    valid = np.isfinite(disparity)
    d0 = np.where(valid, disparity, 0.0).astype(np.float32)
    map_y = v if row_offset is None else v + np.where(valid, row_offset, 0.0).astype(np.float32)
    gx_full = cv2.Sobel(Rimg, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8)
    box = (window, window)
    d = d0.copy()
    sxx = np.zeros_like(L)
    for _ in range(iterations):
        map_x = u - d
        warped = cv2.remap(Rimg, map_x, map_y, cv2.INTER_LINEAR)
        gx = cv2.remap(gx_full, map_x, map_y, cv2.INTER_LINEAR)
        r = L - warped
        sxx = cv2.boxFilter(gx * gx, -1, box, normalize=False)
        sxr = cv2.boxFilter(gx * r, -1, box, normalize=False)
        # I_R(u - d - delta) ~ warped - delta * gx  =>  delta = -sum(r gx) / sum(gx^2)
        ok = sxx > _MIN_GRADIENT_ENERGY * window * window
        step = np.where(ok, -sxr / np.where(ok, sxx, 1.0), 0.0)
        d = np.clip(d + np.clip(step, -0.5, 0.5), d0 - max_shift_px, d0 + max_shift_px)
    textured = sxx > _MIN_GRADIENT_ENERGY * window * window
    better = _window_cost(L, Rimg, u - d, map_y, box) <= _window_cost(L, Rimg, u - d0, map_y, box)
    refined = np.where(textured & better, d, d0)
    refined[~valid] = np.nan
    return refined


_MIN_GRADIENT_ENERGY = 1.0  # grey levels^2 per pixel: below it a window does not fix a shift


def _window_cost(L, Rimg, map_x, map_y, box):
    warped = cv2.remap(Rimg, map_x, map_y, cv2.INTER_LINEAR)
    return cv2.boxFilter((L - warped) ** 2, -1, box, normalize=False)


def _zero_mean(image: np.ndarray, window: int) -> np.ndarray:
    return image - cv2.blur(image, (2 * window + 1, 2 * window + 1))


def _grey_float(image: np.ndarray) -> np.ndarray:
    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
    return grey.astype(np.float32)
