"""The disparities a pair really holds: a coarse match that narrows SGBM's search before the full one.

The search range a survey derives from its rig spans every disparity its height range can produce (the floor less
3 cm to 40 cm above the water by default): on the POV-Ray development flume's breakwater pair 112 disparities, of
which the scene fills about 55. SGBM's time grows with the disparities it searches, so the pair is first matched
at a quarter of its size over the same range (0.025 CPU-s at 1728x1152), and the full match searches only what that
coarse match found, with a margin, within the rig's range.
"""

from __future__ import annotations

import dataclasses
import logging

import cv2
import numpy as np

from .matching import MatchOptions, sgbm_disparity

log = logging.getLogger("jaxstereo")

COARSE_SCALE = 4  # the coarse match's images are this many times smaller on each side
COARSE_MARGIN_PX = 16  # full-size pixels kept beyond the coarse match's extremes (4 coarse pixels)
COARSE_TAIL = 5e-4  # the share of coarse matches at each end taken as outliers
MIN_COARSE_SHARE = 0.05  # fewer coarse matches than this share of the pixels cannot bound the scene
MIN_NARROWED_COUNT = 48  # a search this narrow is not narrowed further
MIN_COARSE_SIDE_PX = 64  # nor a pair whose coarse images would be smaller than this


def scene_search(left: np.ndarray, right: np.ndarray, search: tuple[int, int],
                 options: MatchOptions | None = None) -> tuple[int, int]:
    """SGBM's `(first disparity, count)` pixels for the rectified pair `left`, `right` (h, w[, 3]) uint8: the
    disparities a coarse match (grey, `COARSE_SCALE` times smaller, SGBM both ways over `search` scaled) finds,
    less the `COARSE_TAIL` share at each end, with `COARSE_MARGIN_PX` on either side, the count a multiple of 16,
    all within `search` (first, count). `search` itself where it is already narrow (`MIN_NARROWED_COUNT`), the
    pair small (`MIN_COARSE_SIDE_PX`) or the coarse match too sparse to bound the scene (`MIN_COARSE_SHARE` of the
    pixels). `options` are SGBM's settings (the survey's; default `MatchOptions()`), run both ways without the
    filters."""
    options = options or MatchOptions()
    first, count = int(search[0]), int(search[1])
    h, w = left.shape[:2]
    if count <= MIN_NARROWED_COUNT or min(h, w) < COARSE_SCALE * MIN_COARSE_SIDE_PX:
        return first, count
    size = (w // COARSE_SCALE, h // COARSE_SCALE)
    coarse = [cv2.resize(image, size, interpolation=cv2.INTER_AREA) for image in (left, right)]
    coarse = [cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image for image in coarse]
    lo = int(np.floor(first / COARSE_SCALE))
    top = int(np.ceil((first + count) / COARSE_SCALE))
    span = max(16, int(np.ceil((top - lo) / 16.0)) * 16)
    # Both ways: a left match is kept where the right image matches back to it (on a pair whose surface's disparity
    # rises from 70 to 100 px, one way found 1 % of its matches at 40-48 px, in the strip the right image does not
    # see; both ways 68.5 px at the least)
    checked = dataclasses.replace(options, two_way=True, check_rows=1, fattening_reach_px=0, occlusion_reach_px=0)
    found = sgbm_disparity(coarse[0], coarse[1], lo, span, checked)
    # A match within a pixel of either end of the range (its sub-pixel value included) is where SGBM's cost fell
    # off the range (no texture, or a disparity beyond it), not a disparity found: on the development flume's
    # oblique pair 1 % of the one-way coarse matches lay on the range's first disparity.
    found = found[(found >= lo + 1) & (found <= lo + span - 2)]  # NaN: False
    if found.size < MIN_COARSE_SHARE * size[0] * size[1]:
        log.info("coarse match too sparse (%d pixels) to narrow the disparity search", found.size)
        return first, count
    d_lo, d_hi = np.quantile(found, (COARSE_TAIL, 1.0 - COARSE_TAIL)) * COARSE_SCALE
    start = max(first, int(np.floor(d_lo)) - COARSE_MARGIN_PX)
    stop = min(first + count, int(np.ceil(d_hi)) + COARSE_MARGIN_PX)
    narrowed = max(16, int(np.ceil((stop - start) / 16.0)) * 16)
    if narrowed >= count:
        return first, count
    start = max(first, min(start, first + count - narrowed))  # the multiple of 16 kept inside the rig's range
    return start, narrowed
