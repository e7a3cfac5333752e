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
    raw = matcher.compute(left, right)
    disparity = raw.astype(np.float32) / 16.0
    invalid = raw <= (min_disparity - 1) * 16
    # Pixels whose support window leaves either image are unreliable too.
    valid_left = left.reshape(left.shape[0], left.shape[1], -1).max(axis=-1) > 0
    disparity[invalid | ~valid_left] = np.nan
    return disparity


def refine_disparity(left: np.ndarray, right: np.ndarray, disparity: np.ndarray, window: int = 7,
                     iterations: int = 3) -> np.ndarray:
    """Sub-pixel refinement of a disparity map by dense Lucas-Kanade steps on the rectified pair.

    SGBM's parabola fit locks disparities towards integers (a bias that does not average out on
    surfaces of nearly constant disparity, such as a flume floor). Each step warps the right image by
    the current disparity and solves, over a `window` x `window` box around every pixel, the
    least-squares shift that best aligns it with the left image. Steps are limited to half a pixel.

    **Arguments:** rectified `left`, `right` images; `disparity` (h, w) pixels, NaN for no match
    (`x_right = x_left - d`).

    **Returns:** the refined disparity (h, w), NaN where the input was NaN or the texture too weak.
    """
    L = _grey_float(left)
    Rimg = _grey_float(right)
    h, w = L.shape
    u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    d = np.nan_to_num(disparity, nan=0.0).astype(np.float32)
    map_y = v
    valid = np.isfinite(disparity)
    gx_full = cv2.Sobel(Rimg, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8)
    box = (window, window)
    for _ in range(iterations):
        map_x = u - d
        warped = cv2.remap(Rimg, map_x, map_y, cv2.INTER_LINEAR)
        gx = cv2.remap(gx_full, map_x, map_y, cv2.INTER_LINEAR)
        r = L - warped
        sxx = cv2.boxFilter(gx * gx, -1, box, normalize=False)
        sxr = cv2.boxFilter(gx * r, -1, box, normalize=False)
        # I_R(u - d - delta) ~ warped - delta * gx  =>  delta = -sum(r gx) / sum(gx^2)
        ok = sxx > 1e-4 * window * window
        step = np.where(ok, -sxr / np.where(ok, sxx, 1.0), 0.0)
        d += np.clip(step, -0.5, 0.5)
        valid &= ok
    d[~valid] = np.nan
    return d


def _grey_float(image: np.ndarray) -> np.ndarray:
    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
    return grey.astype(np.float32)
