"""Triangulation of ray pairs: the least-squares point closest to two rays."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .precision import float64
from .vectors import dot3, norm3


@float64
def triangulate_rays(
    origin_a: Float[ArrayLike, "*#batch 3"],
    direction_a: Float[ArrayLike, "*#batch 3"],
    origin_b: Float[ArrayLike, "*#batch 3"],
    direction_b: Float[ArrayLike, "*#batch 3"],
) -> tuple[Float[Array, "*#batch 3"], Float[Array, "*#batch"]]:
    """Midpoint of the shortest segment between two rays (the least-squares point for two rays).

    **Arguments:** ray origins and unit directions, each (..., 3), world metres.

    **Returns:** `(points, gap)`: the midpoints (..., 3) and the length (...,) metres of the shortest
    segment between the two lines (zero for rays that meet). Parallel rays give `gap = inf`.
    """
    pa, pb, parallel = closest_points(origin_a, direction_a, origin_b, direction_b)
    gap = jnp.where(parallel, jnp.inf, norm3(pa - pb))
    return 0.5 * (pa + pb), gap


def closest_points(
    origin_a: Float[ArrayLike, "*#batch 3"],
    direction_a: Float[ArrayLike, "*#batch 3"],
    origin_b: Float[ArrayLike, "*#batch 3"],
    direction_b: Float[ArrayLike, "*#batch 3"],
) -> tuple[Float[Array, "*#batch 3"], Float[Array, "*#batch 3"], Array]:
    """The two ends of the shortest segment between two lines, given by origins and unit directions (..., 3).

    **Returns:** `(on_a, on_b, parallel)`: the point of line a nearest line b and the point of line b nearest
    line a (..., 3), world metres, and `parallel` (...,) bool, where the lines are parallel and the two points
    mean nothing."""
    w = origin_a - origin_b
    b = dot3(direction_a, direction_b)
    d = dot3(direction_a, w)
    e = dot3(direction_b, w)
    denom = 1.0 - b * b
    parallel = denom <= 1e-15
    safe = jnp.where(parallel, 1.0, denom)
    sa = (b * e - d) / safe
    sb = (e - b * d) / safe
    return origin_a + sa[..., None] * direction_a, origin_b + sb[..., None] * direction_b, parallel
