"""Photometric check of dense matches: a match whose colours disagree far more than its neighbours' is dropped.

SGBM's block and its smoothness penalty carry a foreground disparity a few pixels past an occluding edge
(onto the background it hides in the other image), and on rubble they settle on wrong minima where the
texture repeats. Such matches pass the left-right check, yet the left pixel and the right pixel they pair
show different surfaces. Their colour residual then stands out against the residual of correct matches
nearby, which is set by the local texture, the JPEG noise and the sampling (about 17 grey levels over
three channels on the POV-Ray flume's fine board texture, 6 on its painted or grey rock).
"""

from __future__ import annotations

import cv2
import numpy as np

from .._geometry.errors import JaxStereoError
from .channels import channel_list

RESIDUAL_WINDOW_PX = 3  # the residual is averaged over this square around each pixel
SCALE_BLOCK_PX = 128  # the local scale is the median residual of the matches in blocks this wide
MAX_RESIDUAL_RATIO = 2.5  # a match is dropped beyond this multiple of the local scale


def photometric_residual(left: np.ndarray, right: np.ndarray, disparity: np.ndarray,
                         row_offset: np.ndarray | None = None) -> np.ndarray:
    """Each match's colour residual: |left - right| summed over the channels at the matched positions
    (the right image sampled bilinearly at `u - d`, `v + row_offset`), averaged over a
    `RESIDUAL_WINDOW_PX` square (h, w) float32 grey levels; NaN where `disparity` is NaN.

    **Arguments:** rectified `left`, `right` images (grey (h, w) or colour (h, w, 3), uint8), `disparity`
    (h, w) pixels (`x_right = x_left - d`), `row_offset` (h, w) pixels or None (the match's row in the
    right image relative to its own).
    """
    if left.shape != right.shape or left.shape[:2] != disparity.shape:
        raise JaxStereoError(f"images {left.shape} / {right.shape} and disparity {disparity.shape} differ in size")
    h, w = disparity.shape
    valid = np.isfinite(disparity)
    columns = np.arange(w, dtype=np.float32)[None, :] - np.where(valid, disparity, 0.0).astype(np.float32)
    rows = np.broadcast_to(np.arange(h, dtype=np.float32)[:, None], (h, w))
    if row_offset is not None:
        rows = rows + np.where(valid, row_offset, 0.0).astype(np.float32)
    sampled = cv2.remap(right.astype(np.float32), columns, np.ascontiguousarray(rows, dtype=np.float32),
                        cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    difference = np.abs(np.subtract(left, sampled, out=sampled, dtype=np.float32), out=sampled)  # uint8 - float32
    if difference.ndim == 3:
        difference = sum(channel_list(difference))
    weight = valid.astype(np.float32)
    box = (RESIDUAL_WINDOW_PX, RESIDUAL_WINDOW_PX)
    total = cv2.boxFilter(difference * weight, -1, box, normalize=False)
    count = cv2.boxFilter(weight, -1, box, normalize=False)
    residual = total / np.maximum(count, 1.0)
    residual[~valid] = np.nan
    return residual


def local_residual_scale(residual: np.ndarray, block: int = SCALE_BLOCK_PX) -> np.ndarray:
    """The median residual of the matches in each `block` x `block` square, interpolated bilinearly between
    the squares' centres (h, w) float32. Squares with fewer matches than an eighth of their pixels take
    the median over the whole image. The median (of residuals quantised to 1/4 grey level and capped at 256) is robust to the
    mismatches it is meant to expose, as long as they are a minority of the square."""
    h, w = residual.shape
    valid = np.isfinite(residual)
    if not valid.any():
        raise JaxStereoError("no match to take the photometric residual's scale from")
    rows, cols = -(-h // block), -(-w // block)
    levels = 1024
    # Each pixel's histogram bin in its square, the pixels without a match in a last bin of their own (dropped):
    # whole images at a time, no index lists (twice as fast on a 1728x1152 image).
    quantised = np.fmin(np.rint(residual * 4), levels - 1)  # fmin: NaN (no match) becomes the top level ...
    quantised[~valid] = levels  # ... and then the extra bin
    cell = (np.arange(h, dtype=np.int32)[:, None] // block) * cols + np.arange(w, dtype=np.int32)[None, :] // block
    key = cell * (levels + 1) + quantised.astype(np.int32)
    histogram = np.bincount(key.ravel(), minlength=rows * cols * (levels + 1)).reshape(rows * cols, levels + 1)
    histogram = histogram[:, :levels]
    counts = histogram.sum(axis=1)
    medians = np.argmax(np.cumsum(histogram, axis=1) >= (counts[:, None] + 1) / 2, axis=1) / 4.0
    enough = counts >= block * block / 8
    if not enough.all():  # the whole image's median, for the squares with too few matches only
        medians = np.where(enough, medians, float(np.median(residual[valid])))
    grid = medians.reshape(rows, cols).astype(np.float32)
    # Bilinear between square centres: resize to the padded image, whose squares are exactly `block` wide.
    scale = cv2.resize(grid, (cols * block, rows * block), interpolation=cv2.INTER_LINEAR)
    return scale[:h, :w]


def photometric_outliers(left: np.ndarray, right: np.ndarray, disparity: np.ndarray,
                         row_offset: np.ndarray | None = None,
                         max_ratio: float = MAX_RESIDUAL_RATIO) -> np.ndarray:
    """The matches (h, w) bool whose `photometric_residual` exceeds `max_ratio` times the
    `local_residual_scale`, and at least one grey level (so that noise-free images keep their matches).

    The default ratio, 2.5, lies above the 99.9th percentile of the ratio on a surface where every match
    is right (the POV-Ray flume's sloping boards, nadir and oblique: 2.1); on its rubble the 90th
    percentile is 5.4 and the matches beyond 2.5 are 24 % of them, with a mean error of 6 mm against
    1.7 mm for the rest.
    """
    if not max_ratio > 0:
        raise JaxStereoError(f"the photometric residual ratio must be positive, got {max_ratio}")
    residual = photometric_residual(left, right, disparity, row_offset)
    scale = local_residual_scale(residual)
    with np.errstate(invalid="ignore"):
        return residual > np.maximum(max_ratio * scale, 1.0)
