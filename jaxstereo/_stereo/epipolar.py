"""Exact epipolar geometry of a wet pair in a rectified frame.

A rectification (in air, or through the water with the first-order virtual cameras) makes epipolar
lines straight rows only approximately: under water the exact epipolar "line" is a curve, and on a
tilted rig the virtual cameras do not make emerged points' lines exact rows either. These functions
give, for a rectified match, where its exact point projects in the right rectified image, so that a
match can be moved onto its exact epipolar curve, and the disparities a height range can produce.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._geometry.camera import Camera
from .._geometry.interface import Interface
from .._geometry.refraction import intersect_plane, refract_directions, refraction_points
from .._geometry.triangulate import closest_points, triangulate_rays
from .._geometry.vectors import apply3
from .rectify import Rectification, rectified_rays
from .table_cache import cached_tables


def _rectified_pixel(rect: Rectification, side: int, surface: Float[ArrayLike, "*b 3"], camera: Camera) -> Float[Array, "*b 2"]:
    """Rectified pixel of a real ray that reaches the interface at `surface` (water) or points at it (air)."""
    origin = rect.centers[side] if rect.mode == "water" else camera.center
    p = apply3(rect.K @ rect.R, surface - origin)
    return p[..., :2] / p[..., 2:3]


def project_exact_rectified(
    rect: Rectification, camera: Camera, side: int, interface: Interface | None, points: Float[ArrayLike, "*b 3"]
) -> Float[Array, "*b 2"]:
    """Exact rectified pixel (..., 2) of world points (..., 3) seen by `camera` (side 0 left, 1 right).

    Points above the water (or with no interface) are seen along straight rays; points below it through
    their exact refraction point. Valid for "air" and "water" rectifications alike.
    """
    center = camera.center
    if interface is None:  # a dry scene: straight rays, air rectification
        return _rectified_pixel(rect, side, points, camera)
    below = interface.height_of(points) < 0
    bent = refraction_points(center, points, interface)
    if rect.mode == "air":
        target = jnp.where(below[..., None], bent, points)
        return _rectified_pixel(rect, side, target, camera)
    straight, _ = intersect_plane(jnp.broadcast_to(center, points.shape), points - center, interface.normal,
                                  interface.level)
    return _rectified_pixel(rect, side, jnp.where(below[..., None], bent, straight), camera)


def _rays(rect: Rectification, camera: Camera, side: int, interface: Interface | None, pixels):
    """The real rays of rectified `pixels` (n, 2) of one side: `(air, water, reach)`, with `air` and `water` each
    `(origin, direction)` ((n, 3) each, world metres, unit directions): the ray in air, and refracted at the
    interface (None without one); `reach` (n,) false where the ray never reaches the water or is totally reflected
    (None without an interface)."""
    origin, direction, _ = rectified_rays(rect, camera, side, pixels)
    if interface is None:
        return (origin, direction), None, None
    hit, s = intersect_plane(origin, direction, interface.normal, interface.level)
    bent, ok = refract_directions(direction, interface.normal, interface.n_air, interface.n_water)
    return (origin, direction), (hit, bent), ok & (s > 0) & jnp.isfinite(s)


def triangulate_exact(rect: Rectification, left: Camera, right: Camera, interface: Interface | None, rl, rr):
    """Exact triangulation of rectified matches: in air, or refracted where the in-air point is under water.

    **Returns:** `(points, gap, submerged, ok)`: world points (n, 3), the distance between the two rays
    (n,) metres, whether each point is under water (n,), and `ok` (n,) false for total internal
    reflection or rays that never reach the water.
    """
    (air_l, water_l, reach_l), (air_r, water_r, reach_r) = (_rays(rect, cam, side, interface, px)
                                                            for side, cam, px in ((0, left, rl), (1, right, rr)))
    p_air, gap_air = triangulate_rays(*air_l, *air_r)
    if interface is None:
        return p_air, gap_air, jnp.zeros(gap_air.shape, bool), jnp.ones(gap_air.shape, bool)
    p_water, gap_water = triangulate_rays(*water_l, *water_r)
    submerged = interface.height_of(p_air) < 0
    points = jnp.where(submerged[..., None], p_water, p_air)
    gap = jnp.where(submerged, gap_water, gap_air)
    return points, gap, submerged, ~submerged | (reach_l & reach_r)


@jax.jit
def exact_row_offset(rect: Rectification, left: Camera, right: Camera, interface: Interface | None, rl, rr):
    """Where a rectified match's exact point lands in the right rectified image.

    The left pixel is the reference: the match's exact point lies on its ray (refracted where the match is under
    water, as `triangulate_exact` decides), at the point of that ray nearest the right pixel's ray, and is
    projected exactly into the right rectified image. (The midpoint of the two rays, projected, lands halfway
    between the rectified row and the exact curve: the offsets came out half the true ones, against the exact
    projection of points into both cameras.)

    **Arguments:** rectified left pixels `rl` (n, 2) and their matches `rr` (n, 2) on the same row.

    **Returns:** `(offset,)`: the exact right pixel's row minus the left row (n,) pixels; zero for an exact
    rectification.
    """
    air_l, water_l, _ = _rays(rect, left, 0, interface, rl)
    for _ in range(2):  # the second pass from the right pixel on the curve: the nearest point is then the exact one
        air_r, water_r, _ = _rays(rect, right, 1, interface, rr)
        points, on_right, _ = closest_points(*air_l, *air_r)
        if interface is not None:  # under water as `triangulate_exact` decides: by the in-air rays' midpoint
            submerged = interface.height_of(0.5 * (points + on_right)) < 0
            points = jnp.where(submerged[..., None], closest_points(*water_l, *water_r)[0], points)
        row = project_exact_rectified(rect, right, 1, interface, points)[:, 1]
        rr = jnp.stack([rr[:, 0], row], axis=-1)
    return (row - rl[:, 1],)


def disparity_bounds(rect: Rectification, left: Camera, right: Camera, interface: Interface | None,
                     z_lo: float, z_hi: float) -> tuple[float, float]:
    """Smallest and largest disparity (pixels) of points at heights z_lo..z_hi seen across the left image.

    Exact: left rays are refracted where they reach heights below the water, and the points are projected
    exactly into the right rectified image.
    """
    w, h = rect.size

    def samples() -> dict:
        u, v = np.meshgrid(np.linspace(0, w - 1, 24), np.linspace(0, h - 1, 16))
        pixels = jnp.asarray(np.stack([u.ravel(), v.ravel()], axis=-1))
        d, ok = _disparity_samples(rect, left, right, interface, pixels, jnp.asarray([z_lo, z_hi]))
        d = np.asarray(d)[np.asarray(ok)]
        return {"disparities": d[np.isfinite(d)]}

    d = cached_tables("disparity bounds", (rect, left, right, interface, float(z_lo), float(z_hi)),
                      samples)["disparities"]
    if d.size == 0:
        return None
    return float(d.min()), float(d.max())


@jax.jit
def _disparity_samples(rect, left, right, interface, pixels, heights):
    """Disparities (2, n) of the left rectified `pixels`' points at each of the two `heights`, and validity."""
    origin, direction, _ = rectified_rays(rect, left, 0, pixels)
    normal = interface.normal if interface is not None else jnp.asarray([0.0, 0.0, 1.0])
    found, valid = [], []
    for k in range(2):
        z = heights[k]
        point, s = intersect_plane(origin, direction, normal, z)
        ok = (s > 0) & jnp.isfinite(s)
        if interface is not None:
            hit, s0 = intersect_plane(origin, direction, normal, interface.level)
            bent, ok_w = refract_directions(direction, normal, interface.n_air, interface.n_water)
            under, s1 = intersect_plane(hit, bent, normal, z)
            below = z < interface.level
            point = jnp.where(below, under, point)
            ok = jnp.where(below, (s0 > 0) & (s1 > 0) & ok_w & jnp.isfinite(s1), ok)
        right_px = project_exact_rectified(rect, right, 1, interface, point)
        found.append(pixels[:, 0] - right_px[:, 0])
        valid.append(ok)
    return jnp.stack(found), jnp.stack(valid)
