"""Correspondences for the water-level refinement from the dense matching: many, spread over the image.

The refinement needs correspondences everywhere, the faintly textured floor included, where a feature
detector finds few. The dense matching of `reconstruct` (one rectification, colour SGBM, each match put
on its exact epipolar curve at the guessed level) gives one match per textured pixel; one match per cell
of a regular grid over the left image is kept. SGBM measures a match along the rectified row only, and
its sub-pixel values lean towards whole pixels (a bias that does not average out on a flat floor, and
that the level's sensitivity to the floor triples), so each kept match is then measured in both image
directions by Lucas-Kanade on a 31 x 31 window (OpenCV's pyramidal tracker, one level), forward and
back: matches that move more than 1.5 px from SGBM's, or do not come back within 0.2 px, are dropped.
On the POV-Ray flume's board this halves the error (0.16 px RMS against 0.28 px) and removes the bias.

A window that large averages the disparity over its whole area, which a rough surface bends: on the flume's
rubble (Dn50 36 mm, about 60 px) the 31 px window put the dry stage's rock 0.9 mm low (median, with a
1.3 mm spread), a bias that grows with height and that a refinement freeing the right camera's pose took
for a change of convergence (the level with a dry DEM as control moved +3 mm with 6,000 correspondences).
Where SGBM's disparity departs from a plane over the large window by more than `ROUGH_RELIEF_PX` (RMS),
the match is measured on a 15 x 15 window instead (rock: 0.3 mm, spread 0.5 mm; the board, whose relief is
matching noise of 0.2-0.3 px, keeps the large window).

That test misses rock whose SGBM disparities happen to lie near a plane over 31 px: on a POV-Ray flume of other rocks
under 0.12 m of water (`experiments/povray_flume.py --level 0.12 --seed 3`) the 31 px window put the emerged rock's
correspondences 1.5 mm low (median against the true surface; the dry survey's DEM there 0.4 mm low), and the level
refined with that DEM as control came out 2.1 mm off with a standard deviation of 0.7 mm (the development flume:
-0.2 mm). Where the control is a survey's DEM, the correspondences are therefore measured as the survey measures
its points (`estimator="survey"`): along the rows, the survey's own sub-pixel disparities (`refine_disparity`), whose
small patch follows the relief; across them, Lucas-Kanade on the rectified pair, as above (the rows' offset does not
depend on the relief), with the same forward-and-back checks. The DEM and the correspondences then share their
estimator and its bias on the relief, which the control's difference cancels: level errors +0.26 mm (std 0.30) and
+0.23 mm (std 0.32) on the two flumes. Against the floor's exact plane the Lucas-Kanade window stays: the survey's
values there put the level 1.3 and 0.5 mm off (Lucas-Kanade: 0.1 and -0.1 mm).
"""

from __future__ import annotations

import cv2
import jax
import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from .._calibration.rig import Rig
from .._geometry.camera import Camera
from .._geometry.interface import Interface
from .._geometry.precision import float64
from .matching import refine_disparity
from .rectify import Rectification, rectified_rays, rectify, waterline_disparity


@jax.jit
def _real_pixels(rect: Rectification, left: Camera, right: Camera, rl, rr):
    """Real pixels (n, 2) of both sides of rectified matches."""
    out = []
    for side, cam, px in ((0, left, rl), (1, right, rr)):
        origin, direction, surface = rectified_rays(rect, cam, side, px)
        out.append(cam.project(surface if rect.mode == "water" else origin + direction))
    return out[0], out[1]


def spread_over_grid(pixels: np.ndarray, size: tuple[int, int], max_points: int) -> np.ndarray:
    """Indices of at most `max_points` of `pixels` (n, 2), one per cell of a regular grid over an image of
    `size` (width, height): in each cell the one nearest its centre."""
    w, h = size
    cell = max(1.0, float(np.sqrt(w * h / max(max_points, 1))))
    ij = np.floor(pixels / cell).astype(np.int64)
    flat = ij[:, 1] * (int(w / cell) + 2) + ij[:, 0]
    centre = (ij + 0.5) * cell
    order = np.lexsort((np.sum((pixels - centre) ** 2, axis=1), flat))
    chosen = order[np.unique(flat[order], return_index=True)[1]]
    if chosen.size > max_points:
        chosen = chosen[np.linspace(0, chosen.size - 1, max_points).astype(int)]
    return np.sort(chosen)


@float64
def dense_correspondences(left_image: np.ndarray, right_image: np.ndarray, rig: Rig, level_guess: float,
                          max_points: int | None = None, estimator: str = "lucas-kanade"
                          ) -> tuple[np.ndarray, np.ndarray]:
    """Correspondences (real pixels) from the dense matching at the guessed water level, spread over the image.

    **Arguments:** the wet pair (uint8 RGB or grey, the rig's size); the rig; `level_guess` metres;
    `max_points` at most this many, one per grid cell (None: `DEM_CORRESPONDENCES` with the survey's estimator,
    `CORRESPONDENCES` with Lucas-Kanade); `estimator` "lucas-kanade" (a 31 or 15 px window on the
    real images, for a control that is an exact plane: the floor) or "survey" (along the rows the survey's own
    sub-pixel disparities, for a control that is a survey's DEM; see the module's docstring).

    **Returns:** `(left_pixels, right_pixels)`, each (n, 2) float64 pixels, measured in both directions.
    """
    from .reconstruct import (
        ReconstructOptions,
        _at,
        _chunked,
        _interface_for,
        _match,
        _pairs_from_disparity,
        _row_offset_table,
        _row_offsets,
        _search_range,
    )

    if estimator not in ("lucas-kanade", "survey"):
        raise ValueError(f"estimator must be 'lucas-kanade' or 'survey', got {estimator!r}")
    if max_points is None:
        max_points = DEM_CORRESPONDENCES if estimator == "survey" else CORRESPONDENCES
    interface: Interface = _interface_for(rig, level_guess)
    z_range = (-0.03, float(interface.level) + 0.4)
    rect = rectify(rig.left, rig.right, interface, "water")
    options = ReconstructOptions()
    search = _search_range(rect, rig, interface, z_range, options)
    matched = _match(rect, rig, left_image, right_image, search, options, None)[0]
    disparity = matched.disparity
    offset = _row_offsets(_row_offset_table(rect, rig, interface, rect.size, search), disparity, search)
    rl, rr, v, u, flat = _pairs_from_disparity(disparity)
    if rl.shape[0] == 0:
        return np.zeros((0, 2)), np.zeros((0, 2))
    rr[:, 1] += _at(offset, flat)
    pick = spread_over_grid(rl, rect.size, max_points)
    rough = ~(plane_residual_rms(disparity, v[pick], u[pick], KLT_WINDOW) <= ROUGH_RELIEF_PX)  # NaN: rough
    w, h = rig.image_size
    if estimator == "survey":
        # the survey's right image is the exposure-mapped one (`match_levels=False`), as `reconstruct` fits it
        along = _at(refine_disparity(matched.left, matched.right, disparity, offset, options.subpixel_window,
                                     options.subpixel_small_window, sigma_window=options.match.block_size,
                                     waterline=waterline_disparity(rect), match_levels=False).disparity, flat[pick])
        rl, rr = measured_as_the_survey(matched.left, matched.right, rl[pick], rr[pick], along, rough)
        pl, pr = _chunked(_real_pixels, (rect, rig.left, rig.right), rl, rr)
        inside = np.all((pl >= 0) & (pl <= [w - 1, h - 1]) & (pr >= 0) & (pr <= [w - 1, h - 1]), axis=1)
        return pl[inside], pr[inside]
    pl, pr = _chunked(_real_pixels, (rect, rig.left, rig.right), rl[pick], rr[pick])  # fixed size: compiled once
    margin = KLT_WINDOW // 2 + 1
    inside = np.all((pl >= margin) & (pl <= [w - 1 - margin, h - 1 - margin]) & (pr >= margin)
                    & (pr <= [w - 1 - margin, h - 1 - margin]), axis=1)
    kept = [measure_both_ways(left_image, right_image, pl[inside & ~r], pr[inside & ~r], window)
            for r, window in ((rough, KLT_WINDOW), (~rough, KLT_WINDOW_ROUGH))]
    return np.concatenate([k[0] for k in kept]), np.concatenate([k[1] for k in kept])


def plane_residual_rms(disparity: np.ndarray, v: np.ndarray, u: np.ndarray, window: int) -> np.ndarray:
    """How far the disparity departs from a plane about each pixel: the RMS (k,) pixels of the matched
    disparities of `disparity` (h, w, NaN unmatched) in the `window` x `window` box centred on row `v`,
    column `u` (k,) about their least-squares plane; NaN where fewer than half the box is matched."""
    half = window // 2
    padded = np.pad(disparity.astype(np.float64), half, constant_values=np.nan)
    patches = sliding_window_view(padded, (window, window))[v, u].reshape(len(v), -1)
    y, x = (a.ravel() for a in np.mgrid[-half : half + 1, -half : half + 1].astype(np.float64))
    design = np.stack([np.ones_like(x), x, y], axis=1)  # (window^2, 3)
    matched = np.isfinite(patches)
    d = np.where(matched, patches, 0.0)
    normal = np.einsum("kp,pi,pj->kij", matched.astype(np.float64), design, design)
    enough = matched.sum(axis=1) >= window * window / 2
    normal[~enough] = np.eye(3)
    coef = np.linalg.solve(normal, np.einsum("kp,pi->ki", d, design)[..., None])[..., 0]
    residual = np.where(matched, d - coef @ design.T, 0.0)
    rms = np.sqrt(np.sum(residual**2, axis=1) / np.maximum(matched.sum(axis=1), 1))
    return np.where(enough, rms, np.nan)


# Correspondences drawn for `refine` (at most; one per cell of a grid over the image): `CORRESPONDENCES` with the
# floor as control (Lucas-Kanade), `DEM_CORRESPONDENCES` against a dry survey's DEM (the survey's estimator). There
# the level rests on how the wet pair's submerged points sit on the DEM, and which 2000 pixels are drawn moved it by
# more than its std says: on six POV-Ray flumes (round 71) the DEM-controlled level was +0.22, -0.27, +0.08, +0.16,
# -0.64 and -0.53 mm off from 2000 (RMS 0.37 mm, two past the scorecard's 0.5 mm, at 2.0 and 2.2 std); from 4000,
# 6000, 8000 and 12000, 0.29, 0.29, 0.32 and 0.31 mm RMS (Z4, 8 cm of water, 0.48-0.60 mm low at every count: the two
# surveys' relative bias, README's Known limits). The dense matching has them all at hand: 6000 cost the command 0.6
# s more (10.1 -> 10.7 s). The floor's correspondences are each fitted in a window of their own, and more of them
# would narrow a std that already stops short of some floors' errors (round 68).
CORRESPONDENCES = 2000
DEM_CORRESPONDENCES = 6000
KLT_WINDOW = 31
KLT_WINDOW_ROUGH = 15
ROUGH_RELIEF_PX = 0.5
KLT_MAX_MOVE_PX = 1.5
KLT_ROUND_TRIP_PX = 0.2


def measured_as_the_survey(left_rectified: np.ndarray, right_rectified: np.ndarray, left_pixels: np.ndarray,
                           right_pixels: np.ndarray, disparity: np.ndarray, rough: np.ndarray
                           ) -> tuple[np.ndarray, np.ndarray]:
    """Rectified matches measured as the survey measures them: the right pixel's column from the survey's sub-pixel
    `disparity` (k,) px, its row by Lucas-Kanade on the rectified pair (`_lucas_kanade`, a `KLT_WINDOW_ROUGH` window
    where `rough` (k,) bool, else `KLT_WINDOW`, from `right_pixels`); kept where both exist and the tracking passes
    its checks. **Arguments:** the rectified pair, the rectified `left_pixels` and `right_pixels` (k, 2).
    **Returns:** the kept rectified `(left_pixels, right_pixels)`."""
    right = right_pixels.copy()
    kept = np.zeros(len(left_pixels), bool)
    grey = _grey(left_rectified, right_rectified)
    for where, window in ((~rough, KLT_WINDOW), (rough, KLT_WINDOW_ROUGH)):
        index = np.flatnonzero(where)
        tracked, ok = _lucas_kanade(*grey, left_pixels[index], right_pixels[index], window)
        right[index, 1] = tracked[:, 1]
        kept[index] = ok
    right[:, 0] = left_pixels[:, 0] - disparity
    kept &= np.isfinite(disparity)
    return left_pixels[kept], right[kept]


def measure_both_ways(left_image: np.ndarray, right_image: np.ndarray, left_pixels: np.ndarray,
                      right_pixels: np.ndarray, window: int = KLT_WINDOW) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel right pixels of matches in both image directions: Lucas-Kanade on a `window` x `window`
    patch from the given right pixels, kept when it moved less than `KLT_MAX_MOVE_PX` and tracking back lands
    within `KLT_ROUND_TRIP_PX` of the left pixel. **Returns:** the kept `(left_pixels, right_pixels)`."""
    if left_pixels.shape[0] == 0:
        return left_pixels, right_pixels
    tracked, keep = _lucas_kanade(*_grey(left_image, right_image), left_pixels, right_pixels, window)
    return left_pixels[keep], tracked[keep]


def _grey(*images: np.ndarray) -> list[np.ndarray]:
    """Each image (h, w[, 3]) uint8 as grey (h, w)."""
    return [cv2.cvtColor(im, cv2.COLOR_RGB2GRAY) if im.ndim == 3 else im for im in images]


def _lucas_kanade(left_grey, right_grey, left_pixels, right_pixels, window: int) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's Lucas-Kanade tracker (one level) on a grey pair from `right_pixels` (k, 2), forward and back: the
    tracked right pixels (k, 2) float64 and whether each passes the checks (k,) bool (see `measure_both_ways`)."""
    if left_pixels.shape[0] == 0:
        return right_pixels.astype(np.float64), np.zeros(0, bool)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-3)
    options = dict(winSize=(window, window), maxLevel=0, criteria=criteria, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    a, b = left_pixels.astype(np.float32), right_pixels.astype(np.float32)
    fwd, ok_f, _ = cv2.calcOpticalFlowPyrLK(left_grey, right_grey, a, b.copy(), **options)
    back, ok_b, _ = cv2.calcOpticalFlowPyrLK(right_grey, left_grey, fwd, a.copy(), **options)
    keep = (ok_f.ravel() == 1) & (ok_b.ravel() == 1)
    keep &= np.linalg.norm(fwd - b, axis=1) < KLT_MAX_MOVE_PX
    keep &= np.linalg.norm(back - a, axis=1) < KLT_ROUND_TRIP_PX
    return fwd.astype(np.float64), keep
