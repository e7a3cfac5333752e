"""Dense reconstruction of a partly submerged scene from one wet stereo pair.

Pipeline: rectify (in air with the real cameras; through the water with the first-order virtual
cameras, where the two differ), match with SGBM, map matches back to real pixels, and triangulate
each match with the chosen model:

- `exact`: a match whose in-air triangulation lies above the water is an emerged point; otherwise
  both rays are refracted exactly (vector Snell) and the point is their least-squares intersection.
- `first-order`: under-water matches are triangulated from the virtual cameras (the paper's method).
- `none`: every match triangulated in air, refraction ignored.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from ._camera import Camera
from ._errors import JaxStereoError
from ._first_order import virtual_camera
from ._interface import Interface, check_camera_above
from ._matching import MatchOptions, disparity_search_range, refine_disparity, sgbm_disparity
from ._precision import float64
from ._rectify import (Rectification, real_to_rectified, rectification_maps, rectified_rays, rectified_to_real_jit,
                       rectify, remap)
from ._refraction import intersect_plane, project_refracted, refract_directions
from ._rig import Rig, rig_to_dict
from ._survey import Survey
from ._triangulate import triangulate_rays

log = logging.getLogger("jaxstereo")

MODELS = ("exact", "first-order", "none")
CHUNK = 1 << 15  # points per compiled call: small enough to stay in cache (2x faster than 1 << 18 on 2 cores)
PARALLAX_SAMPLES = 20000


@dataclasses.dataclass(frozen=True)
class ReconstructOptions:
    """Reconstruction settings.

    **Fields:** `model` ("exact", "first-order", "none"); `z_range_m` (z_min, z_max) of the scene in the
    world frame, used to bound the disparity search (default: 5 cm below z = 0 to 40 cm above the
    water); `match` SGBM options; `max_ray_gap_m` drop matches whose two rays pass further apart;
    `same_rectification_px` reuse the air matching under water when the two rectifications differ by
    less than this; `subpixel_window`, `subpixel_iterations` the Lucas-Kanade refinement of SGBM's
    disparities (0 iterations: SGBM's own sub-pixel values).
    """

    model: str = "exact"
    z_range_m: tuple[float, float] | None = None
    match: MatchOptions = MatchOptions()
    max_ray_gap_m: float = 0.01
    same_rectification_px: float = 0.05
    subpixel_window: int = 7
    subpixel_iterations: int = 3

    def __post_init__(self):
        if self.model not in MODELS:
            raise JaxStereoError(f"model must be one of {', '.join(MODELS)}, got {self.model!r}")


def _check_inputs(left_image, right_image, rig: Rig, interface: Interface | None, z_range):
    w, h = rig.image_size
    for name, image in (("left", left_image), ("right", right_image)):
        if image.shape[1] != w or image.shape[0] != h:
            raise JaxStereoError(f"{name} image is {image.shape[1]}x{image.shape[0]} but the rig's cameras are {w}x{h}")
    if interface is not None:
        check_camera_above(rig.left.center, interface, "left camera")
        check_camera_above(rig.right.center, interface, "right camera")
        if float(interface.level) < z_range[0]:
            raise JaxStereoError(
                f"water level {float(interface.level):.4g} m is below the whole scene (z from {z_range[0]:.4g} m): "
                "for a dry survey give no water level"
            )


def _disparity_range(rect: Rectification, z_lo: float, z_hi: float) -> tuple[float, float]:
    """Disparities of points at heights z_lo..z_hi seen anywhere in the left rectified image."""
    w, h = rect.size
    u, v = np.meshgrid(np.linspace(0, w - 1, 24), np.linspace(0, h - 1, 16))
    hom = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], axis=-1)
    K = np.asarray(rect.K)
    R = np.asarray(rect.R)
    d = (hom @ np.linalg.inv(K).T) @ R
    c0, c1 = np.asarray(rect.centers)
    disparities = []
    for z in (z_lo, z_hi):
        s = (z - c0[2]) / np.where(d[:, 2] == 0, np.nan, d[:, 2])
        X = c0 + s[:, None] * d
        ok = s > 0
        p = (X - c1) @ R.T @ K.T
        disparities.append((u.ravel() - p[:, 0] / p[:, 2])[ok])
    all_d = np.concatenate(disparities)
    if all_d.size == 0:
        raise JaxStereoError("no part of the scene's height range lies in front of the cameras")
    return float(np.nanmin(all_d)), float(np.nanmax(all_d))


def _grey(image):
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image


def _match(rect, rig, left_image, right_image, z_lo, z_hi, options):
    maps = [rectification_maps(rect, cam, side) for side, cam in enumerate((rig.left, rig.right))]
    rect_l = remap(left_image, maps[0])
    rect_r = remap(right_image, maps[1])
    d_min, d_max = _disparity_range(rect, z_lo, z_hi)
    lo, num = disparity_search_range(d_min, d_max, options.match.margin_px)
    disparity = sgbm_disparity(_grey(rect_l), _grey(rect_r), lo, num, options.match)
    if options.subpixel_iterations:
        disparity = refine_disparity(rect_l, rect_r, disparity, options.subpixel_window, options.subpixel_iterations)
    return maps, rect_l, rect_r, disparity, (lo, num)


def _pairs_from_disparity(disparity):
    v, u = np.nonzero(np.isfinite(disparity))
    d = disparity[v, u].astype(np.float64)
    left = np.stack([u, v], axis=-1).astype(np.float64)
    right = np.stack([u - d, v], axis=-1)
    return left, right, v, u


def _triangulate_chunk(rect: Rectification, left_cam: Camera, right_cam: Camera, interface: Interface, rl, rr,
                       max_gap, model: str, kind: str):
    """Triangulate rectified-pixel pairs and choose each match's point; no undistortion needed.

    A match whose in-air point lies above the water is emerged (in-air point); otherwise its point is
    the under-water triangulation of `model`. Matches from the "air" rectification keep only emerged
    points, those from the "water" one only submerged points ("both": all).

    **Returns:** `(points, gap, submerged, keep, left_pixels)`.
    """
    p_air, gap_air, p_water, gap_water, ok, left_pixels = _triangulate_models(rect, left_cam, right_cam, interface,
                                                                               rl, rr, model)
    above = interface.height_of(p_air) >= 0
    if model == "none":
        points, gap = p_air, gap_air
        keep = jnp.full(above.shape, kind in ("air", "both"))
    else:
        points = jnp.where(above[:, None], p_air, p_water)
        gap = jnp.where(above, gap_air, gap_water)
        keep = {"air": above, "water": ~above & ok, "both": above | ok}[kind]
    keep = keep & jnp.all(jnp.isfinite(points), axis=1) & (gap <= max_gap)
    return points, gap, ~above, keep, left_pixels


def _triangulate_models(rect: Rectification, left_cam: Camera, right_cam: Camera, interface: Interface, rl, rr,
                        model: str):
    """Triangulate rectified-pixel pairs in air and under water with `model`.

    **Returns:** `(p_air, gap_air, p_water, gap_water, ok_water, left_pixels)`; for model "none" the
    water part repeats the air part. `left_pixels` are the real left-image pixels of the matches.
    """
    rays = [rectified_rays(rect, cam, side, px) for side, cam, px in ((0, left_cam, rl), (1, right_cam, rr))]
    (o1, d1, _), (o2, d2, _) = rays
    p_air, gap_air = triangulate_rays(o1, d1, o2, d2)
    origin_l, dir_l, surface_l = rays[0]
    left_pixels = left_cam.project(surface_l if rect.mode == "water" else origin_l + dir_l)
    if model == "none":
        return p_air, gap_air, p_air, gap_air, jnp.ones_like(gap_air, dtype=bool), left_pixels
    water_rays = []
    for cam, (o, d, _) in zip((left_cam, right_cam), rays):
        hit, s = intersect_plane(o, d, interface.normal, interface.level)
        if model == "exact":
            direction, ok = refract_directions(d, interface.normal, interface.n_air, interface.n_water)
        else:  # first order: the ray from the virtual centre through the crossing point
            direction = hit - virtual_camera(cam, interface).center
            direction = direction / jnp.linalg.norm(direction, axis=-1, keepdims=True)
            ok = jnp.ones_like(s, dtype=bool)
        water_rays.append((hit, direction, ok & (s > 0) & jnp.isfinite(s)))
    (a1, b1, ok1), (a2, b2, ok2) = water_rays
    p_water, gap_water = triangulate_rays(a1, b1, a2, b2)
    return p_air, gap_air, p_water, gap_water, ok1 & ok2, left_pixels


_triangulate_chunk_jit = jax.jit(_triangulate_chunk, static_argnums=(7, 8))


def _triangulate(rect, rig, interface, rl, rr, max_gap, model, kind):
    """`_triangulate_chunk` in chunks of fixed size (one compilation per model and kind); numpy out."""
    n = rl.shape[0]
    outs = []
    for start in range(0, n, CHUNK):
        a = rl[start : start + CHUNK]
        b = rr[start : start + CHUNK]
        pad = CHUNK - a.shape[0]
        a = jnp.asarray(np.pad(a, ((0, pad), (0, 0)), constant_values=1.0))
        b = jnp.asarray(np.pad(b, ((0, pad), (0, 0)), constant_values=1.0))
        res = _triangulate_chunk_jit(rect, rig.left, rig.right, interface, a, b, max_gap, model, kind)
        outs.append([np.asarray(r)[: a.shape[0] - pad] for r in res])
    if not outs:
        return np.zeros((0, 3)), np.zeros(0), np.zeros(0, bool), np.zeros(0, bool), np.zeros((0, 2))
    return [np.concatenate([o[i] for o in outs]) for i in range(len(outs[0]))]


@float64
def reconstruct(
    left_image: np.ndarray, right_image: np.ndarray, rig: Rig, water_level: float | None = None,
    options: ReconstructOptions = ReconstructOptions(),
) -> tuple[Survey, dict]:
    """Reconstruct a survey from one stereo pair.

    **Arguments:**

    - `left_image`, `right_image`: uint8 RGB (h, w, 3) or grey (h, w), the rig's image size.
    - `rig`: the calibrated rig (world frame, Z up).
    - `water_level`: water level (metres, world Z); None to use the rig's interface, or a dry survey
      when the rig has none. A tilted interface comes from the rig.
    - `options`: `ReconstructOptions`.

    **Returns:** `(survey, summary)`; the summary holds point counts, the submerged fraction, the
    residual vertical parallax of the first-order rectification, and seconds per stage.
    """
    timings = {}
    t0 = time.perf_counter()
    interface = rig.interface
    if water_level is not None:
        normal = rig.interface.normal if rig.interface is not None else (0.0, 0.0, 1.0)
        n_air = float(rig.interface.n_air) if rig.interface is not None else 1.0
        n_water = float(rig.interface.n_water) if rig.interface is not None else 1.333
        if not np.isfinite(water_level):
            raise JaxStereoError(f"water level must be a finite number of metres, got {water_level}")
        interface = Interface(float(water_level), normal, n_air, n_water)
    level = float(interface.level) if interface is not None else None
    z_range = options.z_range_m or (-0.05, (level if level is not None else 0.0) + 0.4)
    _check_inputs(left_image, right_image, rig, interface, z_range)

    rect_air = rectify(rig.left, rig.right, interface, "air")
    maps_air, rect_left_air, _, disp_air, range_air = _match(rect_air, rig, left_image, right_image, *z_range, options)
    timings["rectify+match air (s)"] = time.perf_counter() - t0
    t1 = time.perf_counter()

    sets = [("air", rect_air, maps_air, rect_left_air, disp_air)]
    rect_water = None
    if interface is not None and options.model != "none":
        rect_water = rectify(rig.left, rig.right, interface, "water")
        diff = _rectification_difference(rect_air, rect_water, rig)
        if diff > options.same_rectification_px:
            maps_water = [rectification_maps(rect_water, cam, s) for s, cam in enumerate((rig.left, rig.right))]
            _, rect_left_w, _, disp_w, _ = _match(rect_water, rig, left_image, right_image, z_range[0],
                                                             min(z_range[1], level), options)
            sets.append(("water", rect_water, maps_water, rect_left_w, disp_w))
        else:
            sets = [("both", rect_water, maps_air, rect_left_air, disp_air)]
    timings["rectify+match water (s)"] = time.perf_counter() - t1
    t2 = time.perf_counter()

    itf_for_math = interface if interface is not None else Interface(-1e6)
    points, colours, pixels, submerged, gaps = [], [], [], [], []
    parallax = np.zeros(0)
    for kind, rect, _maps, rect_left, disp in sets:
        rl, rr, v, u = _pairs_from_disparity(disp)
        model = options.model if interface is not None else "none"
        if model == "none":
            kind = "both" if kind in ("air", "both") else kind
        chosen, gap, sub, keep, px_l = _triangulate(rect, rig, itf_for_math, rl, rr, options.max_ray_gap_m, model, kind)
        idx = np.nonzero(keep)[0]
        colour = rect_left[v[idx], u[idx]]
        points.append(chosen[idx])
        colours.append(colour if colour.ndim == 2 else np.repeat(colour[:, None], 3, axis=1))
        pixels.append(px_l[idx])
        submerged.append(sub[idx])
        gaps.append(gap[idx])
        if rect_water is not None and kind in ("water", "both") and model == "exact":
            parallax = _vertical_parallax(rect_water, rig, interface, points[-1][submerged[-1]])
    timings["triangulate (s)"] = time.perf_counter() - t2

    survey = Survey(
        points=np.concatenate(points) if points else np.zeros((0, 3)),
        colors=np.concatenate(colours).astype(np.uint8) if colours else np.zeros((0, 3), np.uint8),
        pixels=np.concatenate(pixels) if pixels else np.zeros((0, 2)),
        submerged=np.concatenate(submerged) if submerged else np.zeros(0, bool),
        rig_json=json.dumps(rig_to_dict(rig.with_interface(interface)), default=float),
        model=options.model,
        water_level=level if level is not None else float("nan"),
    )
    if len(survey) == 0:
        raise JaxStereoError("no matches survived: the images share no matchable texture in the expected depth range")
    summary = {
        "points": len(survey),
        "submerged_fraction": float(survey.submerged.mean()),
        "model": options.model,
        "water_level_m": survey.water_level,
        "rectifications": [s[0] for s in sets],
        "disparity_range_air_px": list(range_air),
        "vertical_parallax_px_mean": float(np.mean(np.abs(parallax))) if parallax.size else 0.0,
        "vertical_parallax_px_max": float(np.max(np.abs(parallax))) if parallax.size else 0.0,
        "median_ray_gap_mm": float(1e3 * np.median(np.concatenate(gaps))) if gaps else 0.0,
        "seconds": timings,
    }
    return survey, summary


def _rectification_difference(rect_a: Rectification, rect_b: Rectification, rig: Rig, step: int = 16) -> float:
    """Largest distance (pixels) between the real pixels two rectifications map a coarse grid to."""
    w, h = rect_a.size
    u, v = np.meshgrid(np.arange(0, w, step, dtype=np.float64), np.arange(0, h, step, dtype=np.float64))
    grid = jnp.asarray(np.stack([u.ravel(), v.ravel()], axis=-1))
    worst = 0.0
    for side, cam in enumerate((rig.left, rig.right)):
        a, ok_a = rectified_to_real_jit(rect_a, cam, side, grid)
        b, ok_b = rectified_to_real_jit(rect_b, cam, side, grid)
        ok = np.asarray(ok_a & ok_b)
        if ok.any():
            worst = max(worst, float(np.max(np.abs(np.asarray(a - b))[ok])))
    return worst


def _vertical_parallax(rect: Rectification, rig: Rig, interface: Interface, points: np.ndarray) -> np.ndarray:
    """Vertical parallax (pixels) between the water-rectified images of exact under-water points.

    Zero for a perfect first-order model; its size is what the approximation leaves to the matcher.
    """
    if points.shape[0] == 0:
        return np.zeros(0)
    sample = points[np.linspace(0, points.shape[0] - 1, PARALLAX_SAMPLES).astype(int)]
    return np.asarray(_parallax_jit(rect, rig.left, rig.right, interface, jnp.asarray(sample)))


@jax.jit
def _parallax_jit(rect, left, right, interface, points):
    rows = []
    for side, cam in enumerate((left, right)):
        px, _ = project_refracted(cam, interface, points)
        rows.append(real_to_rectified(rect, cam, side, px)[:, 1])
    return rows[0] - rows[1]
