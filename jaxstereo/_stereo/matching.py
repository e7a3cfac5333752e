"""Dense matching of a rectified pair with OpenCV's semi-global block matching (SGBM)."""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import cv2
import numpy as np

from .._geometry.errors import JaxStereoError
from .channels import channel_list
from .exposure import match_exposure
from .fattening import beside_occlusions, drop_fattened
from .row_bands import map_row_bands


@dataclasses.dataclass(frozen=True)
class MatchOptions:
    """SGBM settings.

    **Fields:** `block_size` (odd, pixels); `mode` ("3way", "sgbm", "hh"); `uniqueness` ratio (%);
    `disp12_max_diff` left-right consistency tolerance (pixels); `speckle_window` and `speckle_range`
    (pixels) for the speckle filter; `margin_px` added to the disparity range derived from the rig;
    `two_way` also match the right image against the left (a second SGBM run) and keep only the matches
    both runs agree on within `disp12_max_diff` (see `sgbm_disparity`); `check_rows` the second run matches the
    pair with each `check_rows` rows averaged into one (1: at full size; see `_mirrored_disparity`);
    `fattening_reach_px` drop the disparities carried from a foreground over the background beside it, up to
    this many pixels from the foreground's outline (see `drop_fattened`; 0: keep them); `occlusion_reach_px`
    drop this many matched pixels beside each strip the right camera cannot see, on the background's side (see
    `beside_occlusions`; 0: keep them); `match_exposure` map the right image's grey levels onto the left's, one
    gain and one offset per channel, before matching (see `exposure.py`; no map is applied where the cameras
    already agree);
    `narrow_search` search only the disparities a coarse match of the pair finds, with a margin, within the range
    given (see `scene_range.py`).
    """

    block_size: int = 5
    mode: str = "3way"
    uniqueness: int = 10
    disp12_max_diff: int = 1
    speckle_window: int = 100
    speckle_range: int = 2
    margin_px: int = 8
    two_way: bool = True
    check_rows: int = 2
    fattening_reach_px: int = 12
    occlusion_reach_px: int = 12
    match_exposure: bool = True
    narrow_search: bool = True

    def __post_init__(self):
        if self.block_size < 1 or self.block_size % 2 == 0:
            raise JaxStereoError(f"block_size must be an odd positive number of pixels, got {self.block_size}")
        if self.mode not in ("3way", "sgbm", "hh"):
            raise JaxStereoError(f"SGBM mode must be 3way, sgbm or hh, got {self.mode!r}")
        if self.check_rows < 1:
            raise JaxStereoError(f"check_rows must be a whole number of rows >= 1, got {self.check_rows}")
        for name in ("fattening_reach_px", "occlusion_reach_px"):
            if getattr(self, name) < 0:
                raise JaxStereoError(f"{name} must be 0 (off) or a number of pixels, got {getattr(self, name)}")


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

    SGBM's own left-right check derives the right image's disparities from the left's cost volume, so a
    foreground's disparity that its smoothness carried over the background beside it (where the right image
    sees the foreground instead: an occlusion) often passes it. With `options.two_way` the right image is
    matched on its own (both images mirrored, so that it is the reference) and a left match is kept only when
    the right pixel it lands on matched back to within `disp12_max_diff` pixels. On the POV-Ray flume's
    rubble this drops about 6 % of the matches, among them bands 10 to 15 px wide of rock disparity beside
    the rocks, and the submerged cloud-to-surface MAE falls from 2.3 to 2.2 mm. That second run matches the
    pair with its rows averaged in pairs (`options.check_rows`, see `_mirrored_disparity`).

    Where both runs carried a foreground's disparity over a weakly textured background alike, the step
    sits beside the image's edge it belongs to; with `options.fattening_reach_px` the band between is
    dropped (`drop_fattened`: on the flume's stage III hole a 6 px band of rock disparity over the hole's
    floor, 28 mm too high; the rubble's submerged MAE 2.16 -> 2.14 mm, p95 6.28 -> 6.16 mm).

    Beyond a strip of the left image that the right camera cannot see (the background left of a foreground),
    both runs carry the foreground's disparity into the background as a ramp, with no step to find; with
    `options.occlusion_reach_px` the matches that far left of the strip are dropped (`beside_occlusions`). On
    the POV-Ray flume's dry rubble, against true disparities, 31 % of them are off by more than 1 px against 7 %
    of the others, and the pair's share off by more than 1 px falls from 9.6 to 7.2 % (8.6 % of the matches
    dropped); the wet rubble's submerged cloud-to-surface MAE falls from 1.82 to 1.64 mm, its p95 from 5.72 to
    4.86 mm (grey rock: 1.68 -> 1.51 mm, 5.11 -> 4.36 mm).
    """
    if left.shape != right.shape:
        raise JaxStereoError(f"rectified images differ in shape: {left.shape} vs {right.shape}")
    disparity = _one_way(left, right, min_disparity, num_disparities, options)
    if options.two_way:
        _cross_check(disparity, _mirrored_disparity(left, right, min_disparity, num_disparities, options),
                     options.disp12_max_diff)
    dropped = beside_occlusions(disparity, options.occlusion_reach_px)
    if options.fattening_reach_px > 0:
        dropped |= drop_fattened(left, disparity, options.fattening_reach_px)
    disparity[dropped] = np.nan
    return disparity


def _mirrored_disparity(left, right, min_disparity, num_disparities, options):
    """The right image's disparities (h, w) float32, indexed by right pixel (`x_left = x_right + d`), NaN where
    unmatched: SGBM with the right image as the reference (both images mirrored, so that it is the left one).

    With `options.check_rows` k > 1 the pair is matched with each k rows averaged into one (`INTER_AREA`) and
    the disparities are repeated over the rows they came from; the rows past the last whole group stay unmatched.
    Columns, and with them the disparities' resolution, stay whole: the check compares disparities to a pixel.
    Two rows into one halve the run's cost (0.17 -> 0.08 s on the POV-Ray flume's 1728x1152 wet rubble pair),
    and the check it makes is as strict: there 2.7 % fewer of the left run's matches pass it (those it drops
    and the full-size run kept: 3.6 %; the other way: 1.0 %), and the survey's rubble figures are as good or
    better (submerged MAE 1.38 -> 1.35 mm, p95 4.37 -> 4.18 mm; docs/speed.md, round 69).
    """
    h, w = left.shape[:2]
    k = options.check_rows if h >= 2 * options.check_rows else 1  # an image too short to pair its rows: full size
    if k > 1:
        rows = h // k * k
        left, right = (cv2.resize(image[:rows], (w, rows // k), interpolation=cv2.INTER_AREA)
                       for image in (left, right))
    mirrored = [cv2.flip(image, 1) for image in (right, left)]  # 12x faster than a reversed numpy copy
    back = _one_way(*mirrored, min_disparity, num_disparities, options)[:, ::-1]
    if k == 1:
        return back
    whole = np.full((h, w), np.nan, np.float32)
    whole[:rows] = np.repeat(back, k, axis=0)
    return whole


def _one_way(left, right, min_disparity, num_disparities, options):
    """One SGBM run with `left` as the reference (see `sgbm_disparity`)."""
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
    valid_left = np.logical_or.reduce(channel_list(left > 0))
    columns = np.arange(left.shape[1], dtype=np.float32)[None, :]
    outside = columns - disparity < bs // 2
    disparity[invalid | ~valid_left | outside] = np.nan
    return disparity


def _cross_check(disparity, right_disparity, tolerance_px):
    """Drop (in place) the matches of `disparity` (h, w) whose right pixel (column rounded) has no match of its
    own in `right_disparity` (h, w, indexed by right pixel, same sign convention) or one that disagrees by
    more than `tolerance_px`. Whole rows at a time, no index lists (u - d is exact in float32: whole columns
    less sixteenths)."""
    w = disparity.shape[1]
    with np.errstate(invalid="ignore"):  # NaN: no match, and outside
        right_column = np.rint(np.arange(w, dtype=np.float32) - disparity)
        inside = (right_column >= 0) & (right_column < w)
    back = np.take_along_axis(right_disparity, np.where(inside, right_column, 0).astype(np.intp), axis=1)
    with np.errstate(invalid="ignore"):
        disparity[~(inside & (np.abs(back - disparity) <= tolerance_px))] = np.nan


def refine_disparity(left: np.ndarray, right: np.ndarray, disparity: np.ndarray, row_offset: np.ndarray | None = None,
                     window: int = 47, small_window: int | None = 9, sigma_window: int = 5,
                     subpixel: bool = True, with_sigma: bool = True, waterline: np.ndarray | None = None,
                     match_levels: bool = True) -> Subpixel:
    """Sub-pixel disparities by Lucas-Kanade over a `window` x `window` patch, from whole-pixel bases, and
    each disparity's standard deviation from the fit's own residuals.

    SGBM's sub-pixel values come from a 5 x 5 block and carry about 0.3 px of noise on fine texture. Here
    each pixel's disparity is the least-squares shift of its patch, linearised about the whole-pixel
    disparities floor(d) and floor(d) + 1 of the pixels in the patch (right image sampled at whole pixels,
    never interpolated: interpolation blurs fine texture by an amount that depends on the fraction, and
    dense steps from fractional starts mix the neighbours' own shifts), each pixel's two linearisations weighted
    by its SGBM fraction inside the patch's sums. On a surface inclined to the image that one shift is the
    disparity where the patch's gradient energy lies, not at its centre: it is moved to the centre along the
    plane fitted to the patch's SGBM disparities (`_disparity_plane`, `_energy_centroid`). It is kept only
    where those disparities lie within `MAX_SPREAD_PX` of that plane (standard deviation: a smooth surface,
    inclined or not, not an edge), it stays within 1 px of SGBM's, and SGBM's own `sigma_window` block fits it
    within `BLOCK_FIT_SIGMAS` standard deviations (`_fits_block`: a patch across relief or an edge can pull the
    fit off a correct match; the block, which SGBM's cost chose, says so); elsewhere SGBM's value is kept.
    With a `small_window`, the same fit over that smaller patch replaces the large one's where the two differ by
    more than `WINDOW_AGREEMENT` standard deviations of their difference (or only the small one is kept): a
    curved surface (rubble) whose relief the large patch averages over. On the POV-Ray flume's rubble the 31 px
    patch smooths rocks 0.6 Dn50 wide; a 15 px small patch there brought the wet and dry surveys' median
    difference from 1.65 to 1.3 mm, while the flat board keeps the large patch. A 9 px small patch (the default
    since round 50) brings the wet rubble's submerged cloud-to-surface MAE from 1.64 to 1.50 mm (grey rock 1.51
    to 1.39), and on the same flume resampled to 0.75 of its pixels, where the patches span more of each rock,
    from 2.47 to 2.07 mm (1.94 from 2.29); the nadir board's RMSE moves from 1.14 to 1.17 mm. (11 px: 1.52 and
    2.18 mm; 7 px: 1.54 and 2.02 mm, the board 1.23 mm. Both patches smaller, 15 and 7 px: the rubble 1.44 mm
    but the board 1.85 mm, as the agreement test then has no patch large enough for its weak texture.) The large
    patch is 47 px since round 53 (31 before; the box sums cost the same, the bands' overlap a little more): a
    smooth surface averages more noise, and on curved ones the patch is planar less often, so that the 9 px one
    takes over there. On the POV-Ray flume the boards' submerged RMSE falls from 1.17 to 0.97 mm (nadir) and from
    0.66 to 0.52 mm (oblique), the wet rubble's submerged MAE from 1.50 to 1.42 mm (grey rock 1.39 to 1.32), the
    wet and dry surveys' median difference from 0.97 to 0.93 mm; on its dry rubble, against true disparities, the
    share of pixels off by more than 1 px stays (6.84 against 6.83 %) and the others' mean error falls from 0.153
    to 0.145 px. (63 px: the boards 0.92 and 0.47 mm, the rubble 1.40 mm, but the nadir board's deepest layer
    predicted 0.69 of its RMS error; see `MATCH_NOISE_SCALE`.)
    Every refined value is then bounded: it stays within `MOVE_SIGMAS` of SGBM's own standard deviations
    (`sigma_sgbm`, its block's least-squares one, see below) of SGBM's value or within `MIN_MOVE_PX`, whichever is
    more, and a small patch's within `MAX_MOVE_PX` too (half a pixel: SGBM chose the whole pixel by its paths'
    aggregated cost, which a patch of 81 pixels across curved relief is not placed to overrule); a fit beyond its
    bound is moved back onto it, and its standard deviation is at least SGBM's (taken as the bound's own, it
    predicted 1.47 times the oblique board's RMS error in a 5 cm layer; as the fit's, 0.71 of the nadir board's
    deepest layer, both before the floor below; SGBM's: 0.79-0.98 and 0.93-1.34 of the two boards' layers). On a real
    photographed pair (Middlebury's Motorcycle, 741x500, matched as the survey does) the fits that moved 0.5-1 px
    from SGBM's values, most of them the small patch's, were closer to the truth in 30 % of those pixels only:
    unbounded, the step left 5.76 % of the pixels off by more than 1 px and the others 0.204 px off on average
    (SGBM's own values 5.13 % and 0.201 px); bounded, 5.35 % and 0.194 px. On the POV-Ray flume's dry rubble, where
    SGBM's values are noisier, it changes little (6.83 % and 0.145 px unbounded, 6.77 % and 0.144 px bounded; SGBM
    7.21 % and 0.238 px), nor the flume's survey figures. (Measured before the floor below was added: bounded at one
    standard deviation, the Motorcycle 5.25 % and 0.185 px, but the nadir board's submerged RMSE 1.25 mm against
    0.97; the half pixel for the large patch too: the Motorcycle 5.30 % and 0.192 px, the board 1.07 mm.) The floor
    is for images with little noise, where SGBM's block fits its values well and its standard deviation is small
    while its values still lock onto whole pixels: without it the project's own rendered board
    (`tests/stereo/test_reconstruct.py`) had a 5 cm layer 1.14 mm off (bound 0.5 mm); 0.2 px left the submerged RMSE
    of its deep-water rig 1.03 mm (bound 1.0); 0.3 px meets both.
    A match that no patch fit could refine and whose own SGBM disparity lies off the plane of its patch
    (further from the plane's value at the centre than `OFF_PLANE_SPREADS` times the patch's spread and than
    `MAX_SPREAD_PX`) is flagged `off_surface`: its neighbours define a smooth surface it does not lie on, and the
    images did not let the fit move it there. It is judged by the small patch's plane where that patch is
    planar, else by the large one's, so that a small bump on a plane, whose matches the small patch follows, is
    not flagged (judged by the large patch first, a 63 px one flagged the top of a bump 1.2 px high and 9 px
    wide on a plane).
    On the POV-Ray flume's nadir board the 0.3 % of points that kept SGBM's values were 10 mm off RMS (97 % of
    them by more than 3 mm); 0.03 % of its matches are flagged, and dropping them brings the board's submerged
    RMSE from 1.20 to 1.15 mm (the oblique board's from 0.65 to 0.64 mm); on the rubble 0.01 % are flagged.
    With a `waterline` (the water plane's own disparity at each pixel, `rectify.waterline_disparity`), a patch
    whose matches lie on both sides of the water keeps its fitted value but not the fit's standard deviation
    alone: the disparity changes its slope where the surface leaves the water (refraction flattens what lies
    below), and the fit's std assumes one shift and one plane. There the std is at least the fit's combined with
    the large patch's offset from the small one's, averaged over the small patch (`_window_offset`; SGBM's
    block's std without a small patch). On the POV-Ray flume's nadir board, within 15 mm of the water level,
    the fitted values were off by 1.2-1.4 mm RMS against stds of 0.7-1.0 mm (72-85 % within 2 sigma; the rest
    of the board 0.6-1.1 mm, 94 %). The 15 px small patch's own std, taken there until round 50, covered 87-98
    % (93.5 % in all, RMS std 1.16 mm against an RMS error of 1.15); the 9 px patch's own std is larger than
    the error it was a stand-in for (the 5 cm layer holding the waterline predicted 1.41 times its RMS error),
    and the offset covers 92.1 % (RMS std 1.31 mm against 1.18; the oblique board's band 96.3 %, 0.92 against
    0.65 mm). SGBM's block std there was 2-3 times the error; dropping the fit for the small patch or SGBM's
    value covered the error too but raised the boards' submerged RMSE from 1.20 to 1.29 mm (nadir) and from 0.65
    to 0.82 mm (oblique).
    Rows follow `row_offset` (rounded) where the exact epipolar curve leaves them. The work runs on bands of
    rows on a thread per core (`map_row_bands`), with the whole image's values (1.2 -> 0.73 s on the development
    flume's 1728x1152 pair, 2 cores), each band within `MAX_BAND_PIXELS` (its memory, not the image's size,
    sets the step's peak memory), and each on the rectangle around its matches alone (0.75 -> 0.66 CPU-s there).
    On the POV-Ray flume's nadir board the survey's error normal to the board is 1.15 mm RMS under water
    (SGBM's own sub-pixel values: 3.09 mm; 1.33 mm when the spread was taken about the patch's mean, which on
    the inclined board left 1 % of the pixels to SGBM's values). On its dry rubble, against disparities
    ray-cast from the true surface through the true rig, 9.52 % of the pixels are off by more than 1 px
    (SGBM's own values 9.62 %) and the others by 0.182 px on average (SGBM 0.246 px).

    With `match_levels` (the default) the right image's grey levels are first mapped onto the left's at the matches
    `disparity` holds (`exposure.match_exposure`: per channel a monotone map of the levels, then the smooth gain of
    the lenses' shading; nothing changes where the cameras agree), as the survey maps them before it matches
    (`MatchOptions.match_exposure`; it passes its mapped image and False). The fit compares grey levels as they are:
    on Middlebury's Motorcycle pair (741x500, its right image about 1 % darker, by a level less, and shaded
    otherwise), after one plain OpenCV SGBM run (colour, 5 x 5, 3-way; `experiments/real_pair.py`'s second table) the
    step with the levels as they are left 8.03 % of the pixels off by more than 1 px and the others 0.231 px off on
    average (SGBM's own values 7.79 % and 0.204 px); mapped, 7.93 % and 0.198 px (grey: 8.03 % and 0.233 px as they
    are, 7.94 % and 0.204 px mapped, SGBM 7.75 % and 0.202 px). Searched over 0-80 px, with its right image 10 %
    darker and 8 levels brighter: 8.67 % and 0.276 px as they are, 8.07 % and 0.197 px mapped (SGBM 7.96 % and 0.204
    px); both images saved as JPEG (quality 75): 11.56 % and 0.262 px, mapped 11.17 % and 0.237 px (SGBM 11.20 % and
    0.265 px). (Each image's local mean taken out instead, a Gaussian of 2 px, which also undoes differences that
    vary over a rock, brought the Motorcycle to 7.98 % and 0.182 px but the POV-Ray flume's wet rubble's submerged
    cloud-to-surface MAE from 1.38 to 1.62 mm: the shading across each rock is texture the fit uses.)

    The standard deviation is the least-squares one, `sqrt(s2 / sum(g^2))` with `s2` the patch's residual
    variance at the estimate (linearised about the lower whole-pixel bases) and `g` the right image's
    horizontal gradient: over the `window` patch where the refined value is kept (times `MATCH_NOISE_SCALE`),
    over a `sigma_window` patch (SGBM's block) at SGBM's value elsewhere, and everywhere when `subpixel` is
    False (times `SGBM_NOISE_SCALE`).

    The two sub-pixel estimators are compared too: SGBM's own value minus the refined one, averaged over the
    `window` around each pixel and less the part SGBM's own noise explains, is their systematic disagreement.
    Neither is known to be right on a given texture (Lucas-Kanade is better on fine speckle, SGBM's own values
    on rubble seen at coarse resolution), so it counts as an error of the survey.

    **Arguments:** rectified `left`, `right` images (grey or RGB, uint8); `disparity` (h, w) pixels, NaN for
    no match (`x_right = x_left - d`); `row_offset` (h, w) pixels or None; `window`, `small_window` (None:
    the large one only) odd patch widths, pixels; `subpixel` False keeps SGBM's
    values; `with_sigma` False skips the standard deviation and the disagreement; `waterline` (h, w) pixels or
    None (a dry survey, or one rectified in air); `match_levels` False fits the right image's levels as they are
    (images other than uint8 always are).

    **Returns:** a `Subpixel`: the refined `disparity` (h, w), its standard deviation `sigma` (h, w) and the
    estimators' `disagreement` (h, w), all pixels, NaN where the input was NaN; `sigma` and `disagreement` are
    None when `with_sigma` is False (`disagreement` is zero without `subpixel`); the matches `off_surface` (h, w)
    bool (their `disparity` is SGBM's; None without `subpixel`).
    """
    if match_levels and left.dtype == np.uint8 and right.dtype == np.uint8 and np.isfinite(disparity).any():
        right, _ = match_exposure(left, right, disparity)
    Rimg = _channels(right)
    h, w = disparity.shape
    valid = np.isfinite(disparity)
    gradient = cv2.Sobel(Rimg, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8).reshape(Rimg.shape)
    # keeps the float32 sums' k terms small
    shift = float(np.median(np.floor(disparity[valid].astype(np.float32)))) if valid.any() else 0.0
    v = np.arange(h, dtype=np.float32)[:, None] - np.float32(h // 2)  # rows from the image's centre
    u = np.arange(w, dtype=np.float32)[None, :] - np.float32(w // 2)  # columns from the image's centre
    settings = (window, small_window, sigma_window, subpixel, with_sigma)

    def band(start: int, stop: int) -> Subpixel:  # what depends on the band's rows alone is made there, on its thread
        # Only the rectangle around the band's matches, `halo` pixels wider, is worked on: every sum there runs over
        # matches alone, and there is no match outside it (no output either: NaN). The columns left of the search
        # range's first disparity never match (their right pixel is outside the right image): 12 % of the
        # development flume's.
        extent = _match_extent(valid[start:stop], halo)
        if extent is None:
            return _embedded(None, (stop - start, w), (0, 0, 0, 0), subpixel, with_sigma)
        r0, r1, c0, c1 = extent
        rows_, cols_ = slice(start + r0, start + r1), slice(c0, c1)
        valid_ = valid[rows_, cols_]
        d0 = np.where(valid_, disparity[rows_, cols_], 0.0).astype(np.float32)
        # The right image is sampled at whole pixels through cv2.remap's nearest-neighbour lookup (a gather,
        # clamped at the borders), on row `rows` and column u - k.
        rows = np.broadcast_to(np.arange(start + r0, start + r1, dtype=np.float32)[:, None], d0.shape)
        if row_offset is not None:
            rows = np.clip(np.rint(rows + np.where(valid_, row_offset[rows_, cols_], 0.0)), 0, h - 1).astype(np.float32)
        above = None if waterline is None else valid_ & (d0 > waterline[rows_, cols_])  # matches above the water
        fit = _refine_rows(_channels(left[rows_, cols_]), Rimg, gradient, d0, valid_, rows, u[:, cols_], v[rows_],
                           shift, *settings, above=above)
        return _embedded(fit, (stop - start, w), extent, subpixel, with_sigma)

    # Each result depends on the pixels within two windows' half-widths (a window's sums, then `_disagreement`'s
    # window over them): bands of rows extended by that much give the whole image's values.
    halo = 2 * (max(window, small_window or 0, sigma_window) // 2)
    return Subpixel(*map_row_bands(band, h, halo, width=w))


def _match_extent(valid: np.ndarray, halo: int) -> tuple[int, int, int, int] | None:
    """The rows `r0:r1` and columns `c0:c1` of `valid` (b, w) bool that hold all its True pixels and `halo` pixels
    around them (within `valid`), as `(r0, r1, c0, c1)`; None when none is True."""
    rows = np.flatnonzero(valid.any(axis=1))
    if rows.size == 0:
        return None
    columns = np.flatnonzero(valid.any(axis=0))
    b, w = valid.shape
    return (max(int(rows[0]) - halo, 0), min(int(rows[-1]) + 1 + halo, b),
            max(int(columns[0]) - halo, 0), min(int(columns[-1]) + 1 + halo, w))


def _embedded(fit: Subpixel | None, shape: tuple[int, int], extent, subpixel: bool, with_sigma: bool) -> Subpixel:
    """`fit`, `_refine_rows`' result on the rectangle `extent` `(r0, r1, c0, c1)` of a band of `shape` (b, w),
    placed in the whole band: NaN (False for `off_surface`) outside it, where there is no match. `fit` None: no
    match in the band."""
    r0, r1, c0, c1 = extent
    present = (True, with_sigma, with_sigma, subpixel)  # which of the fields `_refine_rows` returns
    fields = []
    for k, there in enumerate(present):
        if not there:
            fields.append(None)
            continue
        whole = np.zeros(shape, bool) if k == 3 else np.full(shape, np.nan, np.float32)
        if fit is not None:
            whole[r0:r1, c0:c1] = fit[k]
        fields.append(whole)
    return Subpixel(*fields)


def _refine_rows(L, Rimg, gradient, d0, valid, rows, u, v, shift: float, window: int, small_window: int | None,
                 sigma_window: int, subpixel: bool, with_sigma: bool, above=None) -> Subpixel:
    """`refine_disparity` on a rectangle of the left image (b rows, w columns): its pixels `L` (b, w, c) float32,
    SGBM's disparities `d0` (b, w) (0 where not `valid`), the right image's rows `rows` (b, w) to sample (whole,
    absolute) in the whole right image `Rimg` (h, W, c) and its horizontal `gradient`, the rectangle's columns `u`
    (1, w) and rows `v` (b, 1) from the image's centre, the sums' disparity `shift` (px), and the matches `above`
    the water (b, w) bool, or None."""
    columns = u + np.float32(Rimg.shape[1] // 2)  # whole numbers, exact in float32
    weight = valid.astype(np.float32)
    base = np.floor(d0)
    fraction = d0 - base
    products = []
    for k, residuals in ((base, with_sigma or subpixel), (base + 1, False)):  # residual terms: lower base only
        if not (subpixel or residuals):
            continue
        g, sampled = (_gather(image, columns - k, rows) for image in (gradient, Rimg))
        products.append(_fit_products(g, L - sampled, k - np.float32(shift), weight, residuals))
        del g, sampled  # (b, w, c) each: freed before the next base's, and before the window sums
    channels = L.shape[2]
    sigma_sgbm = None
    block = _window_fit(products[0], (sigma_window, sigma_window), channels) if products else None  # SGBM's own
    block_at_sgbm = _evaluate(block, d0 - shift) if products else None  # (S_gg, s2) at SGBM's values
    if with_sigma or subpixel:
        gg, s2 = block_at_sgbm
        sigma_sgbm = SGBM_NOISE_SCALE * np.sqrt(s2 / np.maximum(gg, 1e-12))
    if not subpixel:
        zero = None if sigma_sgbm is None else np.zeros_like(d0)
        return Subpixel(_masked(d0, valid), _masked(sigma_sgbm, valid), _masked(zero, valid))
    plane_terms = _plane_terms(d0, weight, shift, u, v)
    above = None if above is None else above.astype(np.float32)
    # Each pixel's equation is linearised about both of its whole-pixel bases, weighted by its SGBM fraction,
    # before the window sums: blending the two windows' solutions with the centre pixel's fraction instead
    # carried that one fraction's noise (SGBM's, 0.3 px) into the result, times the two linearisations'
    # difference (on the POV-Ray flume's nadir board, 0.09 px of pixel-to-pixel noise: 1.85 mm RMS
    # under water where the blend inside the sums gives 1.29 mm).
    blended = [(1 - fraction) * a + fraction * b for a, b in zip(products[0][:3], products[1][:3])]
    lower = products[0]
    del products  # the upper base's terms live on in `blended` only
    large = _refine_in_windows(lower, blended, (block, block_at_sgbm[1]), d0, shift, plane_terms, valid, window,
                               channels, with_sigma, u, v, above)
    refined, sigma_refined, keep, straddles = large.refined, large.sigma, large.kept, large.straddles
    off_plane = large.off_plane
    kink = None  # the large patch's offset from the small one's where the water cuts it, see below
    use_small = None
    if small_window is not None and small_window < window:
        # Where the surface is curved within the large window (rubble), its fit averages over the relief; the
        # small window's fit is taken where the two disagree by more than their difference's noise.
        small_fit = _refine_in_windows(lower, blended, (block, block_at_sgbm[1]), d0, shift, plane_terms, valid,
                                       small_window, channels, True, u, v, above)
        small, sigma_small, keep_small = small_fit.refined, small_fit.sigma, small_fit.kept
        large_sigma = sigma_refined if sigma_refined is not None else np.zeros_like(small)
        noise_variance = np.maximum(sigma_small**2 - large_sigma**2, 0.0)  # of the two fits' difference (px^2)
        noise = np.sqrt(noise_variance)
        use_small = keep_small & (~keep | ~(np.abs(refined - small) <= WINDOW_AGREEMENT * noise))
        if with_sigma and straddles is not None:
            kink = _window_offset(small, refined, keep & keep_small, noise_variance, small_window)
        refined = np.where(use_small, small, refined)
        if sigma_refined is not None:
            sigma_refined = np.where(use_small, sigma_small, sigma_refined)
        if straddles is not None:
            straddles = np.where(use_small, small_fit.straddles, straddles)
        keep = keep | use_small
        off_plane = small_fit.off_plane | (~small_fit.planar & off_plane)  # the most local plane judges
    # Bounded: a kept value stays within MOVE_SIGMAS of SGBM's standard deviations (or MIN_MOVE_PX) of its value,
    # the small patch's within MAX_MOVE_PX too
    bound = np.maximum(MOVE_SIGMAS * sigma_sgbm, np.float32(MIN_MOVE_PX))
    if use_small is not None:
        bound = np.where(use_small, np.minimum(bound, np.float32(MAX_MOVE_PX)), bound)
    clamped = keep & (np.abs(refined - d0) > bound)
    refined = d0 + np.clip(refined - d0, -bound, bound)
    if sigma_refined is not None:  # where the fit disagreed with SGBM's value, it is only as sure as SGBM's
        sigma_refined = np.where(clamped, np.maximum(sigma_refined, sigma_sgbm), sigma_refined)
    sigma = disagreement = None
    if with_sigma:
        sigma = np.where(keep, sigma_refined, sigma_sgbm)
        if straddles is not None:  # a patch across the waterline: see `refine_disparity`
            least = np.hypot(sigma, kink) if kink is not None else sigma_sgbm
            sigma = np.where(keep & straddles, np.maximum(sigma, least), sigma)
        disagreement = _disagreement(d0, refined, keep, sigma_sgbm, window, sigma_window)
    return Subpixel(_masked(np.where(keep, refined, d0), valid), _masked(sigma, valid), _masked(disagreement, valid),
                    ~keep & off_plane)


WINDOW_AGREEMENT = 3.0  # the large window's value stands where the small one's is within 3 sigma of it
# How far a refined value may move from SGBM's: MOVE_SIGMAS standard deviations of SGBM's own (`sigma_sgbm`, its
# block's) or MIN_MOVE_PX, whichever is more, and the small patch's value no more than MAX_MOVE_PX (see
# `refine_disparity`).
MOVE_SIGMAS = 2.0
MIN_MOVE_PX = 0.3
MAX_MOVE_PX = 0.5


class _WindowFit(NamedTuple):
    """`_refine_in_windows`'s result, (h, w) each: the `refined` disparities (px), their standard deviations
    `sigma` (None without `with_sigma`), where they are `kept`, where the patch's matches lie on both sides of
    the water (`straddles`; None without a waterline), where the patch's SGBM disparities lie on a plane
    (`planar`) and where the pixel's own SGBM disparity lies off that plane (`off_plane`), all bool but the
    first two."""

    refined: np.ndarray
    sigma: np.ndarray | None
    kept: np.ndarray
    straddles: np.ndarray | None
    planar: np.ndarray
    off_plane: np.ndarray


def _refine_in_windows(lower, blended, block, d0, shift, plane_terms, valid, window: int, channels: int,
                       with_sigma: bool, u, v, above=None) -> _WindowFit:
    """Lucas-Kanade over `window` x `window` patches (see `refine_disparity`), as a `_WindowFit`. A value is
    kept where the patch is planar: its SGBM disparities lie within `MAX_SPREAD_PX` of their plane
    (`plane_terms`, see `_plane_terms`) and it is at least half matched; and the refined value stays within 1
    px of SGBM's and fits SGBM's own block (`block`: its window fit and its residual variance at SGBM's values;
    `_fits_block`). The pixel's own SGBM disparity is off the plane where it lies further from the plane's
    value at the patch's centre than `OFF_PLANE_SPREADS` times the patch's spread, and than `MAX_SPREAD_PX`.
    `straddles` the water where the patch has matches on both sides of it (`above` (h, w) float32, 1 for a
    match above it; None: no water). `lower` are the fit's per-pixel terms at the lower whole-pixel bases (with
    the residual terms, `_fit_products`) and `blended` the first three terms of both bases, blended by each
    pixel's SGBM fraction."""
    box = (window, window)
    count, slope, spread, centre = _disparity_plane(plane_terms, window, u, v)
    fit = _window_fit(blended, box, channels)
    sigma_refined = None
    if with_sigma:
        # The residual at the patch's own least-squares shift (before the move along the plane, which leaves
        # the fit's noise as it is). The matched pixels' count is the plane's: the same weights' window sums.
        gg, s2 = _evaluate(_window_fit(lower, box, channels, count), fit[2])
        sigma_refined = MATCH_NOISE_SCALE * np.sqrt(s2 / np.maximum(gg, 1e-12))
    # The patch's one shift is its pixels' disparities averaged with their gradient energy as weights: on a
    # surface inclined to the image (disparity `slope` px per px) it is the disparity at the energy's centroid,
    # not at the patch's centre. Moved back to the centre along the plane:
    centroid = _energy_centroid(blended[0], fit[0], box, u, v)
    refined = fit[2] + shift - (slope[0] * centroid[0] + slope[1] * centroid[1])
    planar = valid & (spread <= MAX_SPREAD_PX) & (count >= 0.5 * window * window)
    keep = planar & (np.abs(refined - d0) < 1.0) & _fits_block(*block, refined - shift)
    off_plane = planar & (np.abs(d0 - shift - centre) > np.maximum(OFF_PLANE_SPREADS * spread, MAX_SPREAD_PX))
    straddles = None
    if above is not None:
        emerged = cv2.boxFilter(above, -1, box, normalize=False)  # whole numbers, exact in float32
        straddles = (emerged > 0.5) & (emerged < count - 0.5)
    return _WindowFit(refined, sigma_refined, keep, straddles, planar, off_plane)


def _plane_terms(d0, weight, shift: float, u, v):
    """Per-pixel terms (float32, (h, w) each) of the plane fit to SGBM's disparities `d0` (h, w) px where
    `weight` (h, w) is 1: with `m` the weight, `d` the disparity less `shift` px and `u`, `v` the column and row
    from the image's centre (`u` (1, w), `v` (h, 1) given), `(m, m u, m v, m u u, m v v, m u v, m d, m d u, m d v,
    m d d)`; see `_disparity_plane`."""
    d = np.where(weight > 0, d0 - np.float32(shift), np.float32(0.0))
    wu, wv = weight * u, weight * v
    return (weight, wu, wv, wu * u, wv * v, wu * v, d, d * u, d * v, d * d)


def _disparity_plane(terms, window: int, u, v):
    """The plane fitted to the SGBM disparities of each `window` x `window` patch (`terms` from `_plane_terms`,
    `u` (1, w) the columns and `v` (h, 1) the rows from the image's centre): the patch's number of matched pixels
    (h, w), the plane's slopes `(d/du, d/dv)` (two (h, w) arrays, px per px), the disparities' standard deviation
    about it (h, w) px and the plane's disparity at the patch's centre (h, w) px, less the sums' shift, all
    float32. (The central moments are differences of sums up to 1e9 in float32: about 1e-3 of the coordinates'
    own, far below what the test and the slopes need.)"""
    box = (window, window)
    n, su, sv, suu, svv, suv, sd, sdu, sdv, sdd = (cv2.boxFilter(a, -1, box, normalize=False) for a in terms)
    m = np.maximum(n, np.float32(1.0))
    mu, mv, md = su / m, sv / m, sd / m
    # The central moments overwrite the sums they come from, and each array goes once it is used: the same float32
    # operations in the same order, about half the memory (the sub-pixel step's peak; a fresh process pays for
    # every page it touches first).
    cuu, cvv, cuv, cdu, cdv, cdd = suu, svv, suv, sdu, sdv, sdd
    cuu -= su * mu
    cvv -= sv * mv
    cuv -= su * mv
    cdu -= sd * mu
    cdv -= sd * mv
    cdd -= sd * md
    del su, sv, sd, suu, svv, suv, sdu, sdv, sdd
    det = cuu * cvv
    det -= cuv * cuv
    ok = det > np.float32(1e-3) * cuu * cvv  # a patch with its matched pixels on one line has no plane
    det[~ok] = 1.0
    a = (cvv * cdu - cuv * cdv) / det
    b = (cuu * cdv - cuv * cdu) / det
    del det, cuu, cvv, cuv
    a[~ok] = 0.0
    b[~ok] = 0.0
    residual = cdd
    residual -= a * cdu
    residual -= b * cdv
    del cdu, cdv
    np.maximum(residual, 0.0, out=residual)
    centre = np.subtract(u, mu, out=mu)
    centre *= a
    centre += md
    centre += b * (v - mv)
    residual /= m
    return n, (a, b), np.sqrt(residual, out=residual), centre


def _energy_centroid(gg, s_gg, box, u, v):
    """Where each patch's gradient energy lies: the offsets (du, dv) px ((h, w) each, float32) of its centroid,
    weighted by the per-pixel energy `gg` (h, w), from the patch's centre; `s_gg` (h, w) the energy's window sum;
    `u` (1, w) the columns and `v` (h, 1) the rows from the image's centre."""
    total = np.maximum(s_gg, np.float32(1e-12))
    du = cv2.boxFilter(gg * u, -1, box, normalize=False) / total - u
    dv = cv2.boxFilter(gg * v, -1, box, normalize=False) / total - v
    return du, dv


def _fits_block(block, s2_sgbm, refined):
    """Where the refined disparities (h, w, relative to the sums' `k`) fit SGBM's own block (`block`: its window
    fit, see `_window_fit`) about as well as SGBM's values do (`s2_sgbm`: the block's residual variance there):
    the block's residual sum of squares at the refined value exceeds the one at SGBM's by at most
    `(c sigma)^2 S_gg`, with `c = BLOCK_FIT_SIGMAS` and `sigma` SGBM's standard deviation as `refine_disparity`
    counts it (the block's least-squares one times `SGBM_NOISE_SCALE`). The rise is
    `S_gg ((refined - m)^2 - (sgbm - m)^2)` with `m` the block's own best fit: where SGBM's value is that best
    fit, the refined one must lie within `c sigma` of it."""
    _, s2_refined = _evaluate(block, refined)
    rise = (s2_refined - s2_sgbm) * np.maximum(block[4] - 1, 1)  # rss = s2 (n - 1)
    return rise <= (BLOCK_FIT_SIGMAS * SGBM_NOISE_SCALE) ** 2 * s2_sgbm


class Subpixel(NamedTuple):
    """`refine_disparity`'s result: `disparity`, `sigma` and `disagreement` (h, w) pixels, and the matches `off_surface`
    (h, w) bool (see there; None without `subpixel`)."""

    disparity: np.ndarray
    sigma: np.ndarray | None
    disagreement: np.ndarray | None
    off_surface: np.ndarray | None = None


def _window_mean(values, where, window: int):
    """The mean of `values` (h, w) over each `window` x `window` square, taken where `where` (h, w bool) holds, 0
    where it holds nowhere in the square; and the count of those pixels, at least 1 (h, w), both float32."""
    box = (window, window)
    count = np.maximum(cv2.boxFilter(where.astype(np.float32), -1, box, normalize=False), np.float32(1.0))
    return cv2.boxFilter(np.where(where, values, np.float32(0.0)), -1, box, normalize=False) / count, count


def _window_offset(small, large, both, noise_variance, window: int):
    """How far the large patch's fit lies from the small one's around a pixel (pixels, (h, w), >= 0): the mean of
    `small - large` over each `window` x `window` square, taken where `both` fits were kept, less the part the
    small fit's own noise explains (`noise_variance` (h, w) px^2, the variance of `small - large` at each pixel,
    averaged over the same pixels: the fits of neighbouring small patches share most of their pixels, so their
    noise does not average out over the square); 0 where no pixel of the square kept both. Across a kink of the
    disparity (the waterline) what is left is the large patch's bias. With the noise left in, a 47 px large patch
    over a 9 px small one predicted 1.6 times the oblique board's measured RMS error in the 5 cm layer holding the
    waterline (1.37 times the nadir board's); with it taken out, 1.2 and 0.9 times, 95 and 92 % of the points within
    2 sigma."""
    mean, _ = _window_mean(small - large, both, window)
    # Beyond 1 px^2 the variance takes out all the mean can hold (the fits stay within 1 px of SGBM's): clipped, so
    # that the box filter's running sums keep their precision
    noise, _ = _window_mean(np.minimum(noise_variance, np.float32(1.0)), both, window)
    return np.sqrt(np.maximum(mean**2 - noise, 0.0))


def _disagreement(sgbm, refined, keep, sigma_sgbm, window: int, block: int):
    """SGBM's value minus the refined one, averaged over each `window` where the refined value was kept, shrunk
    by the variance SGBM's own noise leaves in that mean (its errors are correlated over a `block`-wide
    square): a systematic offset between the estimators, zero where none shows (h, w) pixels."""
    mean, count = _window_mean(sgbm - refined, keep, window)
    spread = np.minimum(sigma_sgbm, np.float32(1.0))  # beyond 1 px a match is dropped anyway
    noise = cv2.boxFilter(keep * spread**2, -1, (window, window), normalize=False) / count * block**2 / count
    return np.sign(mean) * np.sqrt(np.maximum(mean**2 - noise, 0.0))


# Least-squares standard deviations assume independent pixel noise; JPEG blocks, demosaicing and the Sobel
# gradient correlate neighbouring pixels. The factors were measured on the POV-Ray development flume's boards
# (predicted against measured error per 5 cm layer, see `experiments/uncertainty.py`). The Lucas-Kanade one was
# 4.0 while the two linearisations were blended after the window sums (their noise was not in the formula);
# with the blend inside the sums no single factor fits both rigs within 30 %: the nadir board asks for 1.9 or
# more (its predicted RMS 0.72-0.89 of the measured at 1.9), the oblique for 1.85 or less (1.02-1.31 at 1.9).
# 2.0 errs on the side of the larger error bars. The factor holds for 31 and 47 px patches (over 47 px the nadir
# board's layers predicted 0.72-0.91 of their RMS error, the oblique board's 0.87-1.31), not over 63 px: the
# errors shrink less than the least-squares std as the patch grows (0.97 and 0.92 mm against 1.17 mm on the nadir
# board at 47 and 63 px against 31), and there the nadir board's deepest layer predicted 0.69 of its RMS error
# while the oblique board's layers predicted up to 1.35 times theirs, much of it the estimators' disagreement,
# which a 63 px mean no longer shrinks to zero.
MATCH_NOISE_SCALE = 2.0
SGBM_NOISE_SCALE = 1.4
# On the POV-Ray flume's dry breakwater (true disparities ray-cast from its 1 mm surface), where the patch fit
# moved more than 0.5 px from SGBM's value SGBM was the closer in 62 % of the pixels, in 94-99 % where the move
# raised SGBM's own 5 x 5 block's misfit by half or more: a patch across a rock's relief or edge pulls the
# fit off a correct match. Kept only within 3 sigma of the block's fit, the share of pixels off by more than
# 1 px is SGBM's own (9.77 %, SGBM 9.74 %; 9.90 % without the check) and the others' mean error 0.186 px
# (SGBM 0.247, 0.194 without). 2 sigma dropped good moves on the boards, whose JPEG noise is correlated (the
# nadir board 1.49 mm RMS under water, 1.33 at 3 sigma, 1.29 without); 4.3 sigma let more rubble through (its
# submerged MAE 1.88 mm against 1.82 at 3 sigma, 1.96 without). All measured before the patches were judged
# about their plane.
BLOCK_FIT_SIGMAS = 3.0
# A patch whose SGBM disparities spread more about their plane (std) straddles an edge or relief: SGBM's value
# stays. About their mean instead, the inclined nadir board's 31 px patches spread 0.5-0.6 px without an edge
# (its disparity changes 1.35 px across one): 1 % of its pixels kept SGBM's values, 6.7 mm RMS against 1.06.
MAX_SPREAD_PX = 0.5
# A match whose own SGBM disparity lies off the plane of its planar patch by more than this many spreads (and more
# than `MAX_SPREAD_PX`), and that no patch fit could refine, is off the surface: see `refine_disparity`.
OFF_PLANE_SPREADS = 3.0


def _fit_products(g, r, k, weight, residuals: bool):
    """Per-pixel terms (summed over channels) of the patch fit `r + g (d - k) = 0` at base `k` (h, w):
    `(gg, ggk, rg, weight)`, and with `residuals` also `(rr, rgk, ggkk)` for the fit's residual."""
    gg = _channel_dot(g, g) * weight
    rg = _channel_dot(r, g) * weight
    terms = (gg, gg * k, rg, weight)
    if residuals:
        terms += (_channel_dot(r, r) * weight, rg * k, gg * k * k)
    return terms


def _channel_dot(a, b):
    """The sum over the last axis of `a * b` (h, w, c) -> (h, w), channel by channel (twice as fast as einsum
    for three channels, the same sums in the same order)."""
    total = a[..., 0] * b[..., 0]
    for c in range(1, a.shape[-1]):
        total += a[..., c] * b[..., c]
    return total


def _window_fit(products, box, channels: int, count=None):
    """Window sums of the fit's terms `products` (`_fit_products`': `(gg, ggk, rg, weight, ...)`, or the first three
    alone) and its least-squares shift `d` (relative to the sums' `k`): `(S_gg, S_ggk, d, S_rg, n samples, S_rr,
    S_rgk, S_ggkk)` (the last three with the residual terms; n None without the weight). `count`, the weight's
    window sum when it is known already, is not summed again."""
    gg, ggk, rg = (cv2.boxFilter(a, -1, box, normalize=False) for a in products[:3])
    if count is None and len(products) > 3:
        count = cv2.boxFilter(products[3], -1, box, normalize=False)
    d = (ggk - rg) / np.maximum(gg, 1e-12)
    rest = [cv2.boxFilter(a, -1, box, normalize=False) for a in products[4:]]
    return (gg, ggk, d, rg, None if count is None else count * channels, *rest)


def _evaluate(fit, d):
    """`(S_gg, s2)`: the gradient energy and the residual variance of the window fit at shift `d` (h, w)."""
    gg, ggk, _, rg, n, rr, rgk, ggkk = fit
    rss = rr + 2 * d * rg - 2 * rgk + d * d * gg - 2 * d * ggk + ggkk
    return gg, np.maximum(rss, 0.0) / np.maximum(n - 1, 1)


def _gather(image: np.ndarray, columns: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """`image[rows, columns]` (h, w, c) float32 for whole-pixel float32 maps (h, w), clamped at the borders."""
    out = cv2.remap(image, columns.astype(np.float32), rows, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(*rows.shape, image.shape[2])


def _masked(values, valid):
    if values is None:
        return None
    out = values.astype(np.float32)
    out[~valid] = np.nan
    return out


def _channels(image: np.ndarray) -> np.ndarray:
    """float32 (h, w, c) of a grey or colour image."""
    image = image.astype(np.float32)
    return image[..., None] if image.ndim == 2 else image
