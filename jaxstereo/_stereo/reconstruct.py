"""Dense reconstruction of a partly submerged scene from one wet stereo pair.

Pipeline: rectify once (through the water with the first-order virtual cameras when the scene is
wet, in air when dry or refraction is ignored), match with colour SGBM, move each match onto its
exact epipolar curve and refine it along that curve, and triangulate each match with the chosen model:

- `exact`: a match whose in-air triangulation lies above the water is an emerged point; otherwise
  both rays are refracted exactly (vector Snell) and the point is their least-squares intersection.
- `first-order`: under-water matches are triangulated from the virtual cameras (the paper's method).
- `none`: every match triangulated in air, refraction ignored.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import jax
import jax.numpy as jnp
import numpy as np

from .._calibration.rig import Rig, rig_to_dict
from .._geometry.camera import Camera
from .._geometry.errors import JaxStereoError
from .._geometry.first_order import _virtual_camera
from .._geometry.interface import Interface, check_camera_above
from .._geometry.precision import float64
from .._geometry.refraction import intersect_plane
from .._geometry.triangulate import triangulate_rays
from .._geometry.vectors import norm3
from .epipolar import disparity_bounds, exact_row_offset, triangulate_exact
from .match_ahead import MatchAhead, Matched, MatchPlan, match_rectifying
from .matching import MatchOptions, Subpixel, disparity_search_range, refine_disparity
from .photometric import MAX_RESIDUAL_RATIO, photometric_outliers
from .rectify import Rectification, rectification_maps, rectified_rays, rectify_checked, waterline_disparity
from .row_bands import map_row_bands
from .survey import Survey
from .table_cache import cached_tables, table_key
from .uncertainty import SharedErrors, load_point_covariances, point_covariances, shared_covariance_table, shared_errors

log = logging.getLogger("jaxstereo")

MODELS = ("exact", "first-order", "none")
CHUNK = 1 << 15  # points per compiled call: small enough to stay in cache (2x faster than 1 << 18 on 2 cores)


@dataclasses.dataclass(frozen=True)
class ReconstructOptions:
    """Reconstruction settings.

    **Fields:** `model` ("exact", "first-order", "none"); `z_range_m` (z_min, z_max) of the scene in the
    world frame: it bounds the disparity search and every point (default: 3 cm below z = 0 to 40 cm
    above the water, or above z = 0 when dry); `match` SGBM options; `colour` match on the three colour
    channels (grey images work either way); `max_ray_gap_px` drop matches whose two rays pass further
    apart than this many pixels at the point's distance; `subpixel` refine SGBM's disparities by
    Lucas-Kanade over `subpixel_window` px patches from whole-pixel bases, where the surface is smooth, and
    over `subpixel_small_window` px patches (None: never) where it is curved within the large one (see
    `refine_disparity`; on the POV-Ray flume's boards the RMSE falls from 2.9 to 2.1 mm (nadir) and from 1.8
    to 1.1 mm (oblique), on its rubble the submerged MAE from 2.3 to 2.0 mm; the small patch of 9 px, not 15,
    takes the rubble's from 1.64 to 1.50 mm, the large patch of 47 px, not 31, the boards' to 0.97 and 0.52 mm
    and the rubble's to 1.42 mm), and drop the matches off the smooth surface around them that no
    patch fit could refine (`Subpixel.off_surface`; counted as `dropped_off_surface`); without it, SGBM's own
    sub-pixel values; `max_sigma_disparity_px` drop matches whose disparity's standard deviation (from the
    matching itself, see `refine_disparity`) exceeds this: the images do not place them; `uncertainty` propagate
    each point's covariance (`Survey.cov`, see `jaxstereo._stereo.uncertainty`);
    `max_photometric_ratio` drop matches whose colour residual exceeds this multiple of their neighbours'
    (see `photometric_outliers`; on the POV-Ray flume's rubble the submerged MAE falls from 3.5 to 2.3 mm
    and its p95 from 11.5 to 6.8 mm, a quarter of the armoured slope's matches dropped; its boards lose
    0.1 %); None keeps them;
    `water_level_std_m` the water level's standard deviation (metres) for the points' covariance (default:
    the one `refine` recorded for the rig's own level, else 0: a level given as a number is exact).
    """

    model: str = "exact"
    z_range_m: tuple[float, float] | None = None
    match: MatchOptions = MatchOptions()
    colour: bool = True
    max_ray_gap_px: float = 1.0
    max_sigma_disparity_px: float = 1.0
    uncertainty: bool = True
    subpixel: bool = True
    subpixel_window: int = 47
    subpixel_small_window: int | None = 9
    water_level_std_m: float | None = None
    max_photometric_ratio: float | None = MAX_RESIDUAL_RATIO

    def __post_init__(self):
        if self.model not in MODELS:
            raise JaxStereoError(f"model must be one of {', '.join(MODELS)}, got {self.model!r}")
        if not self.max_ray_gap_px > 0:
            raise JaxStereoError(f"max_ray_gap_px must be positive, got {self.max_ray_gap_px}")
        for name in ("subpixel_window", "subpixel_small_window"):
            value = getattr(self, name)
            if value is not None and (value < 3 or value % 2 == 0):
                raise JaxStereoError(f"{name} must be an odd number of pixels, at least 3, got {value}")
        if not self.max_sigma_disparity_px > 0:
            raise JaxStereoError(f"max_sigma_disparity_px must be positive, got {self.max_sigma_disparity_px}")
        if self.max_photometric_ratio is not None and not self.max_photometric_ratio > 0:
            raise JaxStereoError(f"max_photometric_ratio must be positive (or None), got {self.max_photometric_ratio}")
        if self.water_level_std_m is not None and not (np.isfinite(self.water_level_std_m)
                                                      and self.water_level_std_m >= 0):
            raise JaxStereoError(f"water_level_std_m must be a finite number >= 0 metres, got {self.water_level_std_m}")


def _check_inputs(left_image, right_image, rig: Rig, interface: Interface | None, z_range):
    w, h = rig.image_size
    for name, image in (("left", left_image), ("right", right_image)):
        if image.shape[1] != w or image.shape[0] != h:
            raise JaxStereoError(f"{name} image is {image.shape[1]}x{image.shape[0]} but the rig's cameras are {w}x{h}")
    if interface is not None:  # the centres in numpy: JAX's eager operations cost a fresh process 10-30 ms each
        check_camera_above(_center(rig.left), interface, "left camera")
        check_camera_above(_center(rig.right), interface, "right camera")
        if float(interface.level) < z_range[0]:
            raise JaxStereoError(
                f"water level {float(interface.level):.4g} m is below the whole scene (z from {z_range[0]:.4g} m): "
                "for a dry survey give no water level"
            )


def _center(camera: Camera) -> np.ndarray:
    """The camera's centre (3,) world metres, `Camera.center` computed in numpy."""
    return -np.asarray(camera.pose.R, np.float64).T @ np.asarray(camera.pose.t, np.float64)


def _interface_for(rig: Rig, water_level: float | None) -> Interface | None:
    if water_level is None:
        return rig.interface
    if not np.isfinite(water_level):
        raise JaxStereoError(f"water level must be a finite number of metres, got {water_level}")
    base = rig.interface
    if base is None:
        return Interface(float(water_level))
    return Interface(float(water_level), base.normal, float(base.n_air), float(base.n_water))


def _search_range(rect, rig: Rig, interface, z_range, options) -> tuple[int, int]:
    """SGBM's (first disparity, count) pixels: the disparities the height range can produce (exactly), and a
    margin."""
    bounds = disparity_bounds(rect, rig.left, rig.right, interface, *z_range)
    if bounds is None:
        raise JaxStereoError("no part of the scene's height range lies in front of the cameras")
    return disparity_search_range(*bounds, options.match.margin_px)


def _match(rect, rig: Rig, left_image, right_image, search, options,
           ahead: MatchAhead | None) -> tuple[Matched, bool]:
    """Rectify the pair and run SGBM over `search`; or take the match `ahead` made from an equal plan (see
    `match_ahead.py`), and otherwise tell it this one's plan. Returns the match and whether it was made ahead."""
    if ahead is not None:  # the key hashes jaxstereo's source: only for a head start
        key = table_key("match plan", (rect, rig.left, rig.right, search, repr(options.match), options.colour))
        matched = ahead.take(key, rig.image_size)
        if matched is not None:
            return matched, True
    maps = tuple(rectification_maps(rect, cam, side) for side, cam in enumerate((rig.left, rig.right)))
    matched = match_rectifying(left_image, right_image, maps, search, options.match, options.colour)
    if ahead is not None:
        ahead.keep(MatchPlan(key, maps, search, options.match, options.colour))
    return matched, False


def _pairs_from_disparity(disparity):
    """The matches of `disparity` (h, w) px, NaN for none, row by row: their left and right rectified pixels (n, 2)
    float64, rows `v` and columns `u` (n,), and `flat`, their index in the image's flattened pixels (n,): an image
    sampled at the matches is `image.reshape(h * w, ...)[flat]`, four times faster than `image[v, u]`."""
    flat = np.flatnonzero(np.isfinite(disparity))
    v, u = np.divmod(flat, disparity.shape[1])
    left = np.empty((flat.size, 2))
    left[:, 0], left[:, 1] = u, v
    right = np.empty((flat.size, 2))
    np.subtract(u, disparity.reshape(-1)[flat].astype(np.float64), out=right[:, 0])
    right[:, 1] = v
    return left, right, v, u, flat


def _at(image: np.ndarray, flat: np.ndarray) -> np.ndarray:
    """`image` (h, w, ...) at the pixels of flattened index `flat` (k,): (k, ...)."""
    return image.reshape(image.shape[0] * image.shape[1], *image.shape[2:])[flat]


def _chunked(fn, args, *columns):
    """`fn(*args, *chunk_columns)` over fixed-size chunks of the (n, k) `columns` (one compilation; the last
    chunk padded); numpy out, each output (n, ...)."""
    n = columns[0].shape[0]
    outs = None
    for start in range(0, n, CHUNK):
        stop = min(start + CHUNK, n)
        part = [c[start:stop] for c in columns]
        if stop - start < CHUNK:
            part = [np.pad(c, ((0, CHUNK - (stop - start)), (0, 0)), constant_values=1.0) for c in part]
        results = fn(*args, *part)  # numpy in: the compiled call transfers it (jnp.asarray dispatched a copy each)
        if outs is None:
            outs = [np.empty((n, *r.shape[1:]), r.dtype) for r in results]
        for out, r in zip(outs, results):
            out[start:stop] = np.asarray(r)[: stop - start]
    return outs


def _triangulate_model(rect: Rectification, left_cam: Camera, right_cam: Camera, interface: Interface | None,
                       model: str, rl, rr):
    """Triangulate rectified-pixel pairs with `model`; no undistortion needed.

    `exact`: a match whose in-air point lies above the water is emerged; otherwise both rays are refracted
    exactly. `first-order`: under-water points from the virtual cameras' rays. `none`: all in air.

    **Returns:** `(points, gap, submerged, ok)`: world points (n, 3), ray gaps (n,) metres, under water (n,),
    valid rays (n,).
    """
    if model == "exact" or interface is None:
        points, gap, submerged, ok = triangulate_exact(rect, left_cam, right_cam, interface, rl, rr)
    else:
        points, gap, submerged, ok = triangulate_exact(rect, left_cam, right_cam, None, rl, rr)
        if model == "first-order":
            rays = [rectified_rays(rect, cam, side, px) for side, cam, px in ((0, left_cam, rl), (1, right_cam, rr))]
            water = []
            for cam, (o, d, _) in zip((left_cam, right_cam), rays):
                hit, s = intersect_plane(o, d, interface.normal, interface.level)
                direction = hit - _virtual_camera(cam, interface).center
                water.append((hit, direction / jnp.linalg.norm(direction, axis=-1, keepdims=True), s > 0))
            p_water, gap_water = triangulate_rays(water[0][0], water[0][1], water[1][0], water[1][1])
            submerged = interface.height_of(points) < 0
            points = jnp.where(submerged[:, None], p_water, points)
            gap = jnp.where(submerged, gap_water, gap)
            ok = ~submerged | (water[0][2] & water[1][2])
        else:
            submerged = interface.height_of(points) < 0
    return points, gap, submerged, ok


def _triangulate_chunk(rect: Rectification, left_cam: Camera, right_cam: Camera, interface: Interface | None,
                       model: str, rl, rr):
    """`_triangulate_model`, and each point's distance from the left camera.

    **Returns:** `(points, gap, submerged, ok, distance)`: as `_triangulate_model`, and the distance (n,) metres.
    """
    points, gap, submerged, ok = _triangulate_model(rect, left_cam, right_cam, interface, model, rl, rr)
    return points, gap, submerged, ok, norm3(points - left_cam.center)


_triangulate_chunk_jit = jax.jit(_triangulate_chunk, static_argnums=4)


def _load_in_background(rect, rig: Rig, interface, model: str, with_covariances: bool, search) -> threading.Thread:
    """Trace the chunked triangulation and, `with_covariances`, the covariance table's interpolation (for the
    `search` range), and load them (JAX's persistent cache) or compile them, on dummy values in a thread of its
    own, while the main thread matches and refines the pair (numpy and OpenCV, mostly free of the GIL): in a fresh
    process that is some tenths of a second of tracing and loading taken off the command's time. Join it before
    triangulating; whatever fails here (nothing should) fails again, with its message, in the real call."""

    @float64
    def load():
        dummy = np.ones((CHUNK, 2))  # numpy, as the real calls pass: no eager operation to load
        try:
            jax.block_until_ready(_triangulate_chunk_jit(rect, rig.left, rig.right, interface, model, dummy, dummy))
            if with_covariances:
                load_point_covariances(rect.size, search)
        except Exception as err:  # noqa: BLE001 - only a head start: the real call raises it properly
            log.debug("loading the compiled functions ahead failed: %s", err)

    thread = threading.Thread(target=load, name="load-compiled", daemon=True)
    thread.start()
    return thread


OFFSET_GRID_PX = 32  # spacing of the exact row-offset table in u and v (pixels)
OFFSET_GRID_DISPARITY_PX = 4  # and in disparity


def _row_offset_table(rect, rig, interface, size: tuple[int, int], search) -> np.ndarray:
    """The exact epipolar curves' row offset in the right rectified image (pixels) on a table every
    `OFFSET_GRID_PX` pixels (rows, columns of the left rectified image, `size` (w, h)) and `OFFSET_GRID_DISPARITY_PX`
    of disparity over the `search` range (first, count): (nv, nu, nd) float64, 0 where no curve."""
    w, h = size
    us = np.arange(0, w - 1 + OFFSET_GRID_PX, OFFSET_GRID_PX, dtype=np.float64)
    vs = np.arange(0, h - 1 + OFFSET_GRID_PX, OFFSET_GRID_PX, dtype=np.float64)
    ds = np.arange(search[0], search[0] + search[1] + OFFSET_GRID_DISPARITY_PX, OFFSET_GRID_DISPARITY_PX,
                   dtype=np.float64)
    V, U, Dg = np.meshgrid(vs, us, ds, indexing="ij")

    def exact() -> dict:
        rl = np.stack([U.ravel(), V.ravel()], axis=-1)
        rr = np.stack([U.ravel() - Dg.ravel(), V.ravel()], axis=-1)
        (table,) = _chunked(exact_row_offset, (rect, rig.left, rig.right, interface), rl, rr)
        return {"offset": np.nan_to_num(table.reshape(V.shape), nan=0.0)}

    inputs = (rect, rig.left, rig.right, interface, (h, w), tuple(int(k) for k in search))
    return cached_tables("exact row offsets", inputs, exact)["offset"]


def _row_offsets(table: np.ndarray, disparity, search):
    """Row offset (h, w) of each match's exact epipolar curve in the right rectified image (NaN: no match).

    The offset is a smooth function of (u, v, disparity): computed exactly on a table (`_row_offset_table`) and
    interpolated (trilinearly) for every match.
    """
    h, w = disparity.shape
    columns = (np.arange(w, dtype=np.float32) / np.float32(OFFSET_GRID_PX))[None, :]

    def band(start: int, stop: int) -> tuple:  # each pixel on its own: bands of rows on threads, no halo
        d = disparity[start:stop]
        valid = np.isfinite(d)
        rows = (np.arange(start, stop, dtype=np.float32) / np.float32(OFFSET_GRID_PX))[:, None]
        layers = (np.where(valid, d, np.float32(search[0])) - np.float32(search[0])) / np.float32(
            OFFSET_GRID_DISPARITY_PX)
        offset = _trilinear(table, (rows, columns, layers))
        offset[~valid] = np.nan
        return (offset,)

    return map_row_bands(band, h, 0, width=w)[0]


def _trilinear(table: np.ndarray, coords) -> np.ndarray:
    """Trilinear interpolation of `table` (n0, n1, n2) at fractional indices `coords`, three arrays that
    broadcast together, clamped at the table's edges: float32 of their broadcast shape. (scipy's
    `map_coordinates(order=1, mode="nearest")` without importing scipy.ndimage, a third of a second of a fresh
    process; an image's rows (h, 1) and columns (1, w) are interpolated once each.)"""
    strides = (table.shape[1] * table.shape[2], table.shape[2], 1)
    base, fractions, steps = 0, [], []
    for axis, (n, x) in enumerate(zip(table.shape, coords)):
        x = np.clip(x, 0.0, n - 1.0)
        i = np.minimum(x.astype(np.int32), max(n - 2, 0))  # x >= 0: truncation is the floor
        base = base + i * np.int32(strides[axis])
        fractions.append((x - i).astype(np.float32))
        steps.append(strides[axis] if n > 1 else 0)
    flat = table.astype(np.float32).ravel()

    def along(axis: int, offset):
        """The table interpolated along axes `axis`.. at the corner `offset` of the axes before it."""
        if axis == 3:
            return flat[base + offset] if offset else flat[base]
        low, high = along(axis + 1, offset), along(axis + 1, offset + steps[axis])
        return low + fractions[axis] * (high - low)

    return along(0, 0)


@float64
def reconstruct(
    left_image: np.ndarray, right_image: np.ndarray, rig: Rig, water_level: float | None = None,
    options: ReconstructOptions = ReconstructOptions(), on_points: Callable[[Survey], None] | None = None,
    match_ahead: MatchAhead | None = None, on_error_rows: Callable[[dict, int, int], None] | None = None,
    on_stage: Callable[[str], None] | None = None,
) -> tuple[Survey, dict]:
    """Reconstruct a survey from one stereo pair: at most one point per left pixel, from one match.

    The pair is rectified once: through the water with the first-order virtual cameras when the scene
    is wet (the paper's step; with equal camera heights it is also exact for emerged points), in air
    otherwise. SGBM matches it (on colour), over the disparities the scene's height range can produce.
    With the exact model every match is then moved onto its exact epipolar curve (the row where its
    exact point projects; refraction bends it) and refined along it, and each pixel's one match is
    triangulated: in air when its in-air point lies above the water, through the exact refraction
    otherwise. Matches whose colours disagree far more than their neighbours' (`photometric_outliers`),
    matches whose rays miss each other by more than `max_ray_gap_px`, and points outside the height range
    are dropped.

    **Arguments:**

    - `left_image`, `right_image`: uint8 RGB (h, w, 3) or grey (h, w), the rig's image size.
    - `rig`: the calibrated rig (world frame, Z up).
    - `water_level`: water level (metres, world Z); None to use the rig's interface, or a dry survey
      when the rig has none. A tilted interface comes from the rig.
    - `options`: `ReconstructOptions`.
    - `on_points`: called with the survey as soon as its points are known, before their errors are propagated
      (a `Survey` without `cov` and the other error fields): the command line starts drawing its preview on
      another thread there.
    - `match_ahead`: the command line's head start on the matching (see `match_ahead.py`): its match is taken when
      it came from this reconstruction's own plan, and it is given the plan otherwise.
    - `on_error_rows`: called as `on_error_rows(fields, start, stop)` each time rows `start:stop` of the error
      fields (`cov`, `sigma_z_match`, `sigma_z_level`, `dz_subpixel`: the arrays the survey will hold) are known,
      in order, from the first row to the last: the command line writes them to the survey's file meanwhile.
    - `on_stage`: called with each stage's name as it starts (the summary's `seconds` keys less " (s)":
      "rectify+match", "sub-pixel", "triangulate", "uncertainty"), on the calling thread: a caller's progress.

    **Returns:** `(survey, summary)`; the summary holds point counts (and how many were dropped and why,
    those above the height range apart), the submerged fraction, the height range used (`height_range_m`), the
    disparities it allows (`disparity_search_px`) and those SGBM searched (`disparity_searched_px`, see
    `scene_range.py`), whether the match came from `match_ahead` (`matched_ahead`),
    the exact curves' row offsets from the rectified rows, seconds per stage, and `warnings` (sentences; a
    scene that rises past the height range's top).
    """
    timings = {}
    stage = on_stage or (lambda name: None)
    stage("rectify+match")
    t0 = time.perf_counter()
    interface = _interface_for(rig, water_level)
    level = float(interface.level) if interface is not None else None
    z_range = options.z_range_m or (-0.03, (level if level is not None else 0.0) + 0.4)
    _check_inputs(left_image, right_image, rig, interface, z_range)
    model = options.model if interface is not None else "none"
    mode = "water" if model != "none" else "air"
    rect = rectify_checked(rig.left, rig.right, interface, mode)
    search = _search_range(rect, rig, interface, z_range, options)
    loading = _load_in_background(rect, rig, interface, model, options.uncertainty, search)
    offsets = _row_offset_table(rect, rig, interface, rect.size, search) if model == "exact" else None
    (rect_l, rect_r, disparity, left_map, exposure, searched), ahead = _match(rect, rig, left_image, right_image,
                                                                        search, options, match_ahead)
    timings["rectify+match (s)"] = time.perf_counter() - t0

    stage("sub-pixel")
    t1 = time.perf_counter()
    offset = _row_offsets(offsets, disparity, search) if offsets is not None else None
    subpixel = refine_disparity(rect_l, rect_r, disparity, offset, options.subpixel_window,
                                options.subpixel_small_window, sigma_window=options.match.block_size,
                                subpixel=options.subpixel, with_sigma=options.uncertainty,
                                waterline=waterline_disparity(rect), match_levels=False)  # mapped, or as asked
    disparity, undetermined = _drop_undetermined(subpixel, options.max_sigma_disparity_px)
    disparity, off_surface = _drop_off_surface(disparity, subpixel)
    timings["sub-pixel (s)"] = time.perf_counter() - t1

    # The photometric check runs on a thread beside the triangulation (its matches are dropped from the points
    # after): each is numpy, OpenCV or XLA work that leaves the GIL and a core to the other.
    stage("triangulate")
    t2 = time.perf_counter()
    check = options.max_photometric_ratio is not None and np.isfinite(disparity).any()  # none: refused below
    with ThreadPoolExecutor(1, thread_name_prefix="photometric-check") as side:
        checking = (side.submit(photometric_outliers, rect_l, rect_r, disparity, offset, options.max_photometric_ratio)
                    if check else None)
        loading.join()
        kept = _triangulate_matches(rect, rig, interface, model, disparity, offset, z_range, options.max_ray_gap_px,
                                    dropped=checking.result if checking is not None else lambda: None)
    # The outliers are among no kept point: the disparity needs no NaN at them for the errors, read at the points
    photometric = int(np.count_nonzero(checking.result())) if checking is not None else 0
    timings["triangulate (s)"] = time.perf_counter() - t2  # with the photometric check beside it
    survey = _survey_of(kept, rect_l, left_map, rig, interface, options.model)
    if on_points is not None:
        on_points(survey)
    shared = None
    if options.uncertainty:
        stage("uncertainty")
        t3 = time.perf_counter()
        shared = shared_errors(rig, _level_std(rig, water_level, interface, options))
        errors = _point_errors(rect, rig, interface, shared, search, kept, subpixel._replace(disparity=disparity),
                               refracts=model != "none", on_rows=on_error_rows)
        survey = dataclasses.replace(survey, **errors)
        timings["uncertainty (s)"] = time.perf_counter() - t3
    under = _at(offset, kept.flat)[survey.submerged] if offset is not None else np.zeros(0)
    summary = {
        "points": len(survey),
        "submerged_fraction": float(survey.submerged.mean()),
        "model": options.model,
        "water_level_m": survey.water_level,
        "rectification": mode,
        "disparity_search_px": [search[0], search[0] + search[1]],
        "disparity_searched_px": [searched[0], searched[0] + searched[1]],
        "matched_ahead": ahead,
        "exposure_right_to_left": exposure.as_dict() if exposure is not None else None,
        "height_range_m": [float(z_range[0]), float(z_range[1])],
        **kept.counts,
        "dropped_undetermined": undetermined,
        "dropped_off_surface": off_surface,
        "dropped_photometric": photometric,
        "vertical_parallax_px_mean": float(np.mean(np.abs(under))) if under.size else 0.0,
        "vertical_parallax_px_max": float(np.max(np.abs(under))) if under.size else 0.0,
        "median_ray_gap_px": kept.median_gap_px,
        **(_uncertainty_summary(survey, shared, _at(subpixel.sigma, kept.flat)) if shared is not None else {}),
        "seconds": timings,
    }
    summary["warnings"] = _range_warnings(summary)
    return survey, summary


ABOVE_RANGE_SHARE = 1e-3  # a scene inside its height range leaves no match above it (the POV-Ray flume: none)


def _range_warnings(summary: dict) -> list[str]:
    """What the user should know about the height range: matches landing above its top mean the scene rises
    past it, and the pixels higher still were matched within the search or not at all."""
    above, matches = summary["dropped_above_height_range"], summary["matches"]
    if above <= ABOVE_RANGE_SHARE * matches:
        return []
    top = summary["height_range_m"][1]
    return [(f"{above} matches ({100 * above / matches:.1f} %) lie above the height range's top, z = {top:.3f} m: "
             f"the scene rises higher, and what lies above the search is missing or mismatched; widen the height "
             f"range (--z-range ZMIN ZMAX; z_range in a batch manifest)")]


def _drop_undetermined(subpixel: Subpixel, limit_px: float) -> tuple[np.ndarray, int]:
    """The disparities (h, w) with NaN where their standard deviation exceeds `limit_px`, and how many those were."""
    if subpixel.sigma is None:
        return subpixel.disparity, 0
    undetermined = subpixel.sigma > limit_px
    return np.where(undetermined, np.nan, subpixel.disparity), int(np.count_nonzero(undetermined))


def _drop_off_surface(disparity: np.ndarray, subpixel: Subpixel) -> tuple[np.ndarray, int]:
    """The disparities (h, w) with NaN where the match lies off the smooth surface around it (`Subpixel.off_surface`,
    see `refine_disparity`), and how many of those were still there."""
    if subpixel.off_surface is None:
        return disparity, 0
    off = subpixel.off_surface & np.isfinite(disparity)
    return np.where(off, np.nan, disparity), int(np.count_nonzero(off))


def _point_errors(rect, rig: Rig, interface, shared: SharedErrors, search, kept: _Kept, subpixel: Subpixel,
                  refracts: bool, on_rows=None) -> dict:
    """The kept points' error fields for the `Survey` (see `point_covariances`, and its `on_rows`): the submerged
    points' from the refracted sub-table when the model `refracts`, every point's from the in-air one otherwise."""
    table = shared_covariance_table(rect, rig, interface, shared, rect.size, search)
    return point_covariances(table, kept.v, kept.u, _at(subpixel.disparity, kept.flat), kept.submerged & refracts,
                             _at(subpixel.sigma, kept.flat), _at(subpixel.disagreement, kept.flat),
                             on_rows)  # float32, as used there


@dataclasses.dataclass(frozen=True)
class _Kept:
    """The matches that became points: their left rectified pixels (`v`, `u`, and `flat`, the index in the image's
    flattened pixels), points (k, 3) world metres, submerged flags (k,), the match counts and drops by reason, and
    the median ray gap (pixels)."""

    v: np.ndarray
    u: np.ndarray
    flat: np.ndarray
    points: np.ndarray
    submerged: np.ndarray
    counts: dict
    median_gap_px: float


def _triangulate_matches(rect, rig: Rig, interface, model: str, disparity, offset, z_range, max_ray_gap_px,
                         dropped: Callable[[], np.ndarray | None] = lambda: None) -> _Kept:
    """Triangulate every match (exactly, chunked); keep those whose rays meet within `max_ray_gap_px` and
    whose point lies in `z_range`, and that `dropped()` (called once the points are computed: (h, w) bool, or
    None) does not mark. The counts are those of the matches not marked, as if they had never been matched."""
    rl, rr, v, u, flat = _pairs_from_disparity(disparity)
    if offset is not None:
        rr[:, 1] += _at(offset, flat)
    if rl.shape[0] == 0:
        raise JaxStereoError("no matches survived: SGBM found no match in the expected depth range (no shared texture?)")
    points, gap, submerged, ok, distance = _chunked(
        _triangulate_chunk_jit, (rect, rig.left, rig.right, interface, model), rl, rr)
    marked = dropped()
    listed = np.ones(rl.shape[0], bool) if marked is None else ~_at(marked, flat)
    gap_px = gap * float(np.asarray(rect.K)[0, 0]) / np.maximum(distance, 1e-9)  # numpy: no eager slice to load
    # (n, 3) reduced column by column: 3x faster
    finite = listed & ok & np.isfinite(points[:, 0] + points[:, 1] + points[:, 2])
    meets = finite & (gap_px <= max_ray_gap_px)
    inside = (points[:, 2] >= z_range[0]) & (points[:, 2] <= z_range[1])
    keep = np.flatnonzero(meets & inside)
    if keep.size == 0:
        raise JaxStereoError("no matches survived: the images share no matchable texture in the expected depth range")
    counts = {"matches": int(np.count_nonzero(listed)), "dropped_rays_apart": int(np.sum(finite & ~meets)),
              "dropped_outside_height_range": int(np.sum(meets & ~inside)),
              "dropped_above_height_range": int(np.sum(meets & (points[:, 2] > z_range[1]))),
              "dropped_invalid_rays": int(np.sum(listed & ~finite))}
    every = max(1, keep.size // SUMMARY_SAMPLE)  # the summary's median, of a regular sample
    return _Kept(v[keep], u[keep], flat[keep], points.take(keep, axis=0), submerged[keep].astype(bool), counts,
                 float(np.median(gap_px[keep[::every]])))


def _survey_of(kept: _Kept, rect_l, left_map, rig: Rig, interface, model: str) -> Survey:
    """The survey of the kept points: colours from the left rectified image, pixels of the real left image."""
    colour = _at(rect_l, kept.flat)
    level = float(interface.level) if interface is not None else float("nan")
    pixels = np.empty((kept.flat.size, 2))
    pixels[:, 0], pixels[:, 1] = _at(left_map[0], kept.flat), _at(left_map[1], kept.flat)
    return Survey(
        points=kept.points,
        colors=(colour if colour.ndim == 2 else np.repeat(colour[:, None], 3, axis=1)).astype(np.uint8),
        pixels=pixels,
        submerged=kept.submerged,
        rig_json=json.dumps(rig_to_dict(rig.with_interface(interface)), default=float),
        model=model,
        water_level=level,
    )


def _level_std(rig: Rig, water_level: float | None, interface: Interface | None, options) -> float:
    """The water level's std (metres): `options.water_level_std_m` when given; else, for the rig's own level,
    the std `refine` recorded with it; else 0 (a level given as a number is taken as exact)."""
    if interface is None:
        return 0.0
    if options.water_level_std_m is not None:
        return float(options.water_level_std_m)
    if water_level is None and isinstance(rig.calibration, dict):
        refined = rig.calibration.get("refine", {}).get("parameters", {}).get("water level (m)")
        if refined is not None:
            return float(refined[1])
    return 0.0


SUMMARY_SAMPLE = 100_000


def _uncertainty_summary(survey: Survey, shared: SharedErrors, sigma_d) -> dict:
    """Median vertical std (mm) of emerged and submerged points, total and from matching alone; the median
    disparity std (px); the shared parameters' std and which of them the rig recorded."""
    every = max(1, len(survey) // SUMMARY_SAMPLE)  # medians of a regular sample: the summary's few digits
    out = {"median_sigma_disparity_px": float(np.median(sigma_d[::every]))}
    submerged = survey.submerged[::every]
    sigma_z = np.sqrt(survey.cov[::every, 2])
    for name, sel in (("emerged", ~submerged), ("submerged", submerged)):
        if sel.any():
            out[f"median_sigma_z_{name}_mm"] = 1e3 * float(np.median(sigma_z[sel]))
            out[f"median_sigma_z_match_{name}_mm"] = 1e3 * float(np.median(survey.sigma_z_match[::every][sel]))
    out["shared_std"] = {k: v for k, v in shared.std.items()}
    out["shared_recorded"] = shared.recorded
    return out
