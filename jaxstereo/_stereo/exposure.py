"""The right camera's grey levels mapped onto the left's, so that the pair is matched on like levels.

Two cameras of a rig rarely record a scene alike: their exposure, gain, black level, white balance and tone curve
differ, while SGBM's cost, the sub-pixel fit and the photometric check all compare grey levels as they are. After a
first match, each channel's levels at the matched pixels of both images (the same scene points, so their
distributions differ by the cameras alone) are compared quantile by quantile over their central 80 %, and the right
image's levels are mapped onto the left's through those quantiles: a monotone map that undoes a gain (exposure,
white balance), an offset (black level) and a tone curve of another shape alike. Where it moves a level by a grey
level or more the pair is matched again on the mapped image; where the cameras agree nothing changes, and it costs
about 10 ms. The map is the same over the whole image; what varies over it (each lens's vignetting, met at two
places of its frame) is then fitted as a smooth gain at the same matches (`shading.py`) and applied with it. (Fitted
to the images' whole distributions instead, the map also followed what one camera sees and the other does not: on
the POV-Ray flume's wet rubble, whose cameras agree, it moved levels by up to 5 and the submerged cloud-to-surface
MAE went from 1.64 to 1.88 mm. The tails are left out for the same reason: the darkest 2 % of the grey rock's
matched levels differ by 2.4 levels between its agreeing cameras, the central 80 % by 0.7 at most over the flume's
eight wet and dry pairs.)

The survey is sensitive to such differences well below what an eye sees: on that rubble (stage I, wet) with the
right image 1 % darker the submerged MAE was 2.27 mm (painted and grey rock alike), 0.5 % darker 1.85 and 1.77 mm;
mapped, 1.65 and 1.51 mm, 1.66 and 1.50 mm (1.64 and 1.51 as rendered). Darker per channel (gains 0.90 / 0.85 /
0.80 on R / G / B, 4 grey levels added), SGBM kept two thirds of the points and the MAE was 4.48 mm; mapped, 1.69
mm. With a gamma of 1.3 on the right image: 4.17 mm, mapped 1.83 mm. See `docs/povray-flume.md`, round 46.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from .shading import ShadingField, fit_shading

QUANTILES = np.linspace(0.10, 0.90, 41)  # the central 80 % of the matched levels (see `fit_exposure`)
MIN_LEVEL_CHANGE = 1.0  # grey levels: a map that moves no level of the images' range this far is not applied
MIN_QUANTILES = 10  # below this many unclipped quantile pairs a channel is left as it is
SAMPLE_STEP_PX = 4  # the matches compared: one pixel in this many along rows and columns


@dataclasses.dataclass(frozen=True)
class ExposureMatch:
    """The map applied to the right rectified image's grey levels, per channel, and the smooth gain over it.

    **Fields:** `table` (256, channels) float64, the level each right level is mapped to (the identity for a
    channel left as it is); `gain`, `offset` (channels,) the straight line that fits it best (offset in grey
    levels) and `residual` (channels,) how far the map is from that line, RMS grey levels over the compared
    quantiles (a tone curve that differs in shape, not only by exposure; NaN where a channel could not be
    fitted); `levels_mapped` whether any channel's levels are changed; `shading` the gain that varies over the
    image (`shading.py`; None where it could not be fitted). `applied`: whether the right image is changed.
    """

    table: np.ndarray
    gain: tuple[float, ...]
    offset: tuple[float, ...]
    residual: tuple[float, ...]
    levels_mapped: bool
    shading: ShadingField | None = None

    @property
    def applied(self) -> bool:
        return self.levels_mapped or (self.shading is not None and self.shading.applied)

    def as_dict(self) -> dict:
        shading = self.shading
        return {"gain": list(self.gain), "offset_levels": list(self.offset), "fit_rms_levels": list(self.residual),
                "levels_mapped": self.levels_mapped,
                "shading_gain_range": None if shading is None else [shading.low, shading.high],
                "shading_applied": shading is not None and shading.applied, "applied": self.applied}


def matched_pixels(disparity: np.ndarray, width: int, step: int = SAMPLE_STEP_PX) -> tuple[np.ndarray, ...]:
    """The matches `disparity` (h, w, pixels, NaN: no match; `x_right = x_left - d`) holds on every `step`-th row
    and column whose right pixel (column rounded) lies inside a right image `width` pixels wide: their `rows`, left
    `columns` and `right_columns` (n,) each."""
    d = disparity[::step, ::step]
    rows, columns = np.nonzero(np.isfinite(d))
    rows, columns = rows * step, columns * step
    right_columns = np.rint(columns - disparity[rows, columns]).astype(np.intp)
    inside = (right_columns >= 0) & (right_columns < width)
    return rows[inside], columns[inside], right_columns[inside]


def matched_levels(left: np.ndarray, right: np.ndarray, disparity: np.ndarray,
                   step: int = SAMPLE_STEP_PX) -> tuple[np.ndarray, np.ndarray]:
    """The grey levels of matched pixels in both rectified images (h, w[, c] uint8): the left pixel and the right
    pixel its `disparity` points to (see `matched_pixels`). Two (n, c) uint8 arrays (c = 1 for grey images)."""
    rows, columns, right_columns = matched_pixels(disparity, right.shape[1], step)
    shape = (-1, 1 if left.ndim == 2 else left.shape[2])
    return left[rows, columns].reshape(shape), right[rows, right_columns].reshape(shape)


def level_quantiles(levels: np.ndarray, fractions: np.ndarray = QUANTILES) -> np.ndarray:
    """The quantiles at `fractions` of each column of `levels` (n, c) uint8, (c, len(fractions)), from its
    histogram, each whole level spread evenly over its unit-wide bin (no steps at whole levels); NaN where there
    is no level."""
    rows = []
    for column in levels.T:
        counts = np.bincount(column, minlength=256).astype(np.float64)
        if counts.sum() == 0:
            rows.append(np.full(len(fractions), np.nan))
            continue
        cumulative = np.concatenate([[0.0], np.cumsum(counts)]) / counts.sum()  # at the bins' edges, level - 0.5
        rows.append(np.interp(fractions, cumulative, np.arange(257) - 0.5))
    return np.array(rows)


def fit_exposure(left_levels: np.ndarray, right_levels: np.ndarray) -> ExposureMatch:
    """Per channel, the map of the right image's grey levels onto the left's: the quantiles (`QUANTILES`) of the
    right image's matched pixels `right_levels` (n, c uint8) joined to those of the same scene points in the left
    image, `left_levels` (n, c), linearly between them and, beyond the end ones, along the straight line that fits
    them best (least squares; its gain, offset and RMS distance are reported). Both sets show the same scene
    points, so their distributions differ by the cameras alone. Quantiles within a level of 0 or 255, where either
    image clips, are left out. A channel with fewer than `MIN_QUANTILES` of them, or whose map moves no level
    between its end quantiles by `MIN_LEVEL_CHANGE`, is left as it is."""
    levels = np.arange(256, dtype=np.float64)
    tables, gain, offset, residual = [], [], [], []
    for lq, rq in zip(level_quantiles(left_levels), level_quantiles(right_levels)):
        use = np.isfinite(lq) & np.isfinite(rq) & (np.minimum(lq, rq) > 0.5) & (np.maximum(lq, rq) < 254.5)
        use[1:] &= np.diff(rq) > 1e-6  # knots strictly increasing
        table, a, b, rms = levels, 1.0, 0.0, float("nan")
        if use.sum() >= MIN_QUANTILES:
            rq, lq = rq[use], lq[use]
            a, b = np.polyfit(rq, lq, 1)
            rms = float(np.sqrt(np.mean((a * rq + b - lq) ** 2)))
            table = np.interp(levels, rq, lq)  # beyond the end knots: their level and the line's slope
            table += a * (np.minimum(levels - rq[0], 0.0) + np.maximum(levels - rq[-1], 0.0))
            if np.max(np.abs(table - levels)[int(np.ceil(rq[0])):int(rq[-1]) + 1]) < MIN_LEVEL_CHANGE:
                table, a, b = levels, 1.0, 0.0
        tables.append(table), gain.append(float(a)), offset.append(float(b)), residual.append(rms)
    table = np.stack(tables, axis=-1)
    return ExposureMatch(table, tuple(gain), tuple(offset), tuple(residual), bool(np.any(table != levels[:, None])))


def apply_exposure(image: np.ndarray, match: ExposureMatch) -> np.ndarray:
    """`image` (h, w[, c] uint8) with `match`'s map of the levels and its smooth gain applied, rounded once and
    clipped to 1-255; levels at 0 (rectification's border, outside the camera's view) stay at 0."""
    if not match.applied:
        return image
    if not match.shading or not match.shading.applied:
        table = np.clip(np.rint(match.table), 1, 255).astype(np.uint8)
        table[0] = 0
        return cv2.LUT(image, np.ascontiguousarray(table[:, 0]) if image.ndim == 2 else table.reshape(1, 256, -1))
    planes = image[..., None] if image.ndim == 2 else image
    gain = match.shading.image()
    out = np.empty(planes.shape, np.uint8)
    for c in range(planes.shape[2]):
        levels = match.table[:, c].astype(np.float32)[planes[..., c]] * gain
        out[..., c] = np.where(planes[..., c] == 0, 0, np.clip(np.rint(levels), 1, 255))
    return out[..., 0] if image.ndim == 2 else out


def match_exposure(left: np.ndarray, right: np.ndarray, disparity: np.ndarray) -> tuple[np.ndarray, ExposureMatch]:
    """The `right` rectified image (h, w[, c] uint8) with its grey levels mapped onto the `left`'s at the matches
    `disparity` (h, w) pixels holds (see `fit_exposure`), then multiplied by the smooth gain that takes the mapped
    levels to the left's there (`fit_shading`), and what was applied."""
    rows, columns, right_columns = matched_pixels(disparity, right.shape[1])
    shape = (-1, 1 if left.ndim == 2 else left.shape[2])
    left_levels, right_levels = left[rows, columns].reshape(shape), right[rows, right_columns].reshape(shape)
    match = fit_exposure(left_levels, right_levels)
    mapped = np.take_along_axis(match.table, right_levels.astype(np.intp), axis=0)  # (n, c) the mapped levels
    bright = float(np.max(level_quantiles(left_levels, np.array([QUANTILES[-1]])))) if len(left_levels) else 0.0
    shading = fit_shading(left_levels, mapped, rows, right_columns, (right.shape[1], right.shape[0]), bright,
                          MIN_LEVEL_CHANGE)
    match = dataclasses.replace(match, shading=shading)
    return apply_exposure(right, match), match
