"""Dense matching of a rectified pair with OpenCV's semi-global block matching (SGBM)."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from .._geometry.errors import JaxStereoError


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
                     window: int = 31, max_spread_px: float = 0.5) -> np.ndarray:
    """Sub-pixel disparities by Lucas-Kanade over a `window` x `window` patch, from whole-pixel bases.

    SGBM's sub-pixel values come from a 5 x 5 block and carry about 0.3 px of noise on fine texture. Here
    each pixel's disparity is the least-squares shift of its patch, linearised about the whole-pixel
    disparities floor(d) and floor(d) + 1 of the pixels in the patch (right image sampled at whole pixels,
    never interpolated: interpolation blurs fine texture by an amount that depends on the fraction, and
    dense steps from fractional starts mix the neighbours' own shifts), and the two estimates weighted by
    SGBM's fraction. It is kept only where the patch's SGBM disparities agree within `max_spread_px`
    (standard deviation; a smooth surface, not an edge) and it stays within 1 px of SGBM's; elsewhere
    SGBM's value is kept. Rows follow `row_offset` (rounded) where the exact epipolar curve leaves them.
    On the POV-Ray flume's board: 0.18 px RMS against SGBM's 0.29 px, bias 0.01 px against 0.04.

    **Arguments:** rectified `left`, `right` images (grey or RGB, uint8); `disparity` (h, w) pixels, NaN for
    no match (`x_right = x_left - d`); `row_offset` (h, w) pixels or None.

    **Returns:** the refined disparity (h, w), NaN where the input was NaN.
    """
    L = _channels(left)
    Rimg = _channels(right)
    h, w = L.shape[:2]
    valid = np.isfinite(disparity)
    d0 = np.where(valid, disparity, 0.0).astype(np.float64)
    v, u = np.mgrid[0:h, 0:w]
    rows = v if row_offset is None else np.clip(np.rint(v + np.where(valid, row_offset, 0.0)).astype(np.int64), 0, h - 1)
    gradient = cv2.Sobel(Rimg, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8).reshape(Rimg.shape)
    box = (window, window)
    weight = valid.astype(np.float32)
    base = np.floor(d0).astype(np.int64)
    estimates = []
    for k in (base, base + 1):
        cols = np.clip(u - k, 0, w - 1)
        g = gradient[rows, cols]
        r = L - Rimg[rows, cols]
        gg, rg = (g * g).sum(axis=-1) * weight, (r * g).sum(axis=-1) * weight
        sums = [cv2.boxFilter(a.astype(np.float32), -1, box, normalize=False) for a in (gg, gg * k, rg)]
        estimates.append((sums[1] - sums[2]) / np.maximum(sums[0], 1e-6))
    fraction = d0 - base
    refined = (1 - fraction) * estimates[0] + fraction * estimates[1]
    count = cv2.boxFilter(weight, -1, box, normalize=False)
    mean = cv2.boxFilter((d0 * weight).astype(np.float32), -1, box, normalize=False) / np.maximum(count, 1)
    square = cv2.boxFilter((d0 * d0 * weight).astype(np.float32), -1, box, normalize=False) / np.maximum(count, 1)
    smooth = np.sqrt(np.maximum(square - mean * mean, 0.0)) <= max_spread_px
    keep = valid & smooth & (count >= 0.5 * window * window) & (np.abs(refined - d0) < 1.0)
    out = np.where(keep, refined, d0).astype(np.float32)
    out[~valid] = np.nan
    return out


def _channels(image: np.ndarray) -> np.ndarray:
    """float32 (h, w, c) of a grey or colour image."""
    image = image.astype(np.float32)
    return image[..., None] if image.ndim == 2 else image
