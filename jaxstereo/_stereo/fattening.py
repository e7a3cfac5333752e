"""Foreground fattening: disparity steps that SGBM placed beside the image edge they belong to.

Where a foreground (a rock) stands over a background of weak texture (a sandy floor, a hole's bottom under
water), SGBM's smoothness carries the foreground's disparity several pixels over the background beside it.
Both images do it alike, so a two-way check passes those matches. What gives them away is the image: a
depth step lies on an edge of the image (the rock's outline), while a carried-over step sits in the weak
texture, with the outline a few pixels further into the foreground's side. The pixels between the two
have the foreground's disparity and the background's colour; they are dropped (not re-matched: the
background is the part the data does not determine).

Where the foreground hides part of the background from the right camera (an occlusion: the strip left of a
rock or of a hole's upslope wall in the left image), the carried-over disparity lies beyond the occluded strip,
which the two-way check empties: no step, no outline, but a ramp of the background's matches rising toward the
foreground's disparity (`beside_occlusions`).
"""

from __future__ import annotations

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from .channels import channel_list
from .row_bands import map_row_bands


def drop_fattened(image: np.ndarray, disparity: np.ndarray, reach_px: int = 12, step_px: float = 1.5,
                  gap_px: int = 4, edge_ratio: float = 2.0) -> np.ndarray:
    """The pixels (h, w) bool whose disparity was carried over from a foreground beside them, along rows
    and then along columns.

    A step is a change of more than `step_px` between two matched pixels of a row (or column) at most
    `gap_px` unmatched pixels apart. The image's edge strength is the colour difference between
    neighbouring pixels (averaged over three lines). Where the strongest edge within `reach_px` pixels
    on the step's higher-disparity side is more than `edge_ratio` times the strongest edge at the step,
    and as many times the median edge over `reach_px` pixels on the other side (the background's texture
    and noise: a weak texture's own ripples are not an outline), the pixels from the step to that edge are
    flagged.

    **Arguments:** the rectified reference `image` (h, w) or (h, w, c) of `disparity` (h, w) pixels, NaN
    for no match.
    """
    if image.shape[:2] != disparity.shape:
        raise ValueError(f"image {image.shape[:2]} and disparity {disparity.shape} differ in size")
    pixels = image.reshape(image.shape[0], image.shape[1], -1).astype(np.float32)
    rows = _in_bands(pixels, disparity, reach_px, step_px, gap_px, edge_ratio)
    remaining = np.where(rows, np.nan, disparity)
    # The colour pixels go in as a transposed view, not a transposed copy: the edge strength read from it is the
    # only contiguous array the column pass makes of them (on the development flume, 0.11 -> 0.08 s with int32)
    columns = _in_bands(np.swapaxes(pixels, 0, 1), np.ascontiguousarray(remaining.T),
                        reach_px, step_px, gap_px, edge_ratio).T
    return rows | columns


def _in_bands(pixels, disparity, *settings):
    """`_along_rows` on bands of rows, on a thread per core; a row's edges are averaged with its neighbours',
    one row of halo."""
    def band(start: int, stop: int) -> tuple:
        return (_along_rows(pixels[start:stop], disparity[start:stop], *settings),)

    return map_row_bands(band, disparity.shape[0], 1, width=disparity.shape[1])[0]


def edge_strength(pixels: np.ndarray) -> np.ndarray:
    """Colour difference (h, w) between each pixel and its left neighbour (0 in the first column), averaged
    with the rows above and below: the edge between columns u - 1 and u is at index u."""
    h, w = pixels.shape[:2]
    edge = np.zeros((h, w), np.float32)
    edge[:, 1:] = np.sqrt(sum(c * c for c in channel_list(pixels[:, 1:] - pixels[:, :-1])))
    smooth = edge.copy()
    if h >= 3:
        smooth[1:-1] = (edge[:-2] + edge[1:-1] + edge[2:]) / 3
    return smooth


def _along_rows(pixels, disparity, reach, step, gap, ratio):
    """`drop_fattened` along the rows only (h, w) bool."""
    h, w = disparity.shape
    found = np.isfinite(disparity)
    edge = edge_strength(pixels)
    # For each matched pixel b, the previous matched pixel a of its row (within the gap) and the jump.
    columns = np.arange(w, dtype=np.int32)[None, :]  # int32: half the memory traffic of the default int64
    index = np.where(found, columns, np.int32(-1))
    previous = np.full((h, w), -1, np.int32)
    previous[:, 1:] = np.maximum.accumulate(index, axis=1)[:, :-1]
    before = np.take_along_axis(disparity, np.maximum(previous, 0), axis=1)
    with np.errstate(invalid="ignore"):
        jump = disparity - before
        steps = found & (previous >= 0) & (columns - previous <= gap + 1) & (np.abs(jump) > step)
    v, b = np.nonzero(steps)
    a, jump = previous[v, b], jump[v, b]
    at_step = np.zeros(v.shape, np.float32)  # the strongest edge between a and b (indices a + 1 .. b)
    for k in range(1, gap + 2):
        inside = a + k <= b
        at_step = np.where(inside, np.maximum(at_step, edge[v, np.minimum(a + k, w - 1)]), at_step)
    padded = np.pad(edge, ((0, 0), (reach + 1, reach + 1)))
    windows = sliding_window_view(padded, reach, axis=1)  # windows[v, i] = edge[v, i - reach - 1 ...]
    starts, stops = [], []
    rising = jump > 0  # the foreground is on the right: the band runs from b to the edge, exclusive
    if rising.any():
        vr, br = v[rising], b[rising]
        window = windows[vr, br + reach + 2]  # edges at b + 1 .. b + reach
        background = np.median(windows[vr, a[rising] + 2], axis=1)  # edges at a - reach + 1 .. a
        k = np.argmax(window, axis=1)
        strong = window[np.arange(k.size), k] > ratio * np.maximum(at_step[rising], background)
        starts.append(np.stack([vr, br], 1)[strong])
        stops.append((br + k)[strong])  # the edge at index b + 1 + k: the band ends at b + k
    falling = jump < 0  # the foreground is on the left: from the edge to a
    if falling.any():
        vf, af = v[falling], a[falling]
        window = windows[vf, af + 2]  # edges at a - reach + 1 .. a
        background = np.median(windows[vf, b[falling] + reach + 2], axis=1)  # edges at b + 1 .. b + reach
        k = np.argmax(window, axis=1)
        strong = window[np.arange(k.size), k] > ratio * np.maximum(at_step[falling], background)
        first = af - reach + 1 + k  # the edge between first - 1 and first: the band starts at first
        starts.append(np.stack([vf, np.maximum(first, 0)], 1)[strong])
        stops.append(af[strong])
    flagged = np.zeros((h, w + 1), np.int32)
    for start, stop in zip(starts, stops):
        np.add.at(flagged, (start[:, 0], start[:, 1]), 1)
        np.add.at(flagged, (start[:, 0], np.minimum(stop + 1, w)), -1)
    return (np.cumsum(flagged, axis=1, dtype=np.int32)[:, :w] > 0) & found


def beside_occlusions(disparity: np.ndarray, reach_px: int = 12, step_px: float = 1.5) -> np.ndarray:
    """The matched pixels (h, w) bool within `reach_px` pixels on the background's side of an occluded strip.

    In the left image the background just left of a foreground (larger disparity on the right) is hidden from
    the right camera; the two-way check leaves that strip unmatched. SGBM's cost aggregation carries the
    foreground's disparity over the strip into the background's first pixels beyond it, as a ramp that the
    images alike share: on the POV-Ray flume's stage III hole the floor's matches within about 12 px of its
    upslope wall's occluded strip read 3-12 mm too high, and the damage's depth normal to the slope is measured
    there. A strip is an unmatched run of a row between two matches whose disparity rises by more than `step_px`
    across it (left to right); the `reach_px` matched pixels left of it are flagged.

    **Arguments:** `disparity` (h, w) pixels of the left rectified image, NaN for no match (`x_right = x_left -
    d`); `reach_px` (0: flag none) and `step_px` pixels.
    """
    h, w = disparity.shape
    if reach_px <= 0 or w < 3:
        return np.zeros((h, w), bool)
    found = np.isfinite(disparity)
    columns = np.arange(w, dtype=np.int32)[None, :]
    previous = np.full((h, w), -1, np.int32)  # the previous matched column of each pixel's row
    previous[:, 1:] = np.maximum.accumulate(np.where(found, columns, np.int32(-1)), axis=1)[:, :-1]
    before = np.take_along_axis(disparity, np.maximum(previous, 0), axis=1)
    with np.errstate(invalid="ignore"):
        rising = found & (previous >= 0) & (columns - previous > 1) & (disparity - before > step_px)
    v, b = np.nonzero(rising)
    a = previous[v, b]  # the last match left of the strip: the band runs from a - reach_px + 1 to a
    flagged = np.zeros((h, w + 1), np.int32)
    np.add.at(flagged, (v, np.maximum(a - reach_px + 1, 0)), 1)
    np.add.at(flagged, (v, a + 1), -1)
    return (np.cumsum(flagged, axis=1, dtype=np.int32)[:, :w] > 0) & found
