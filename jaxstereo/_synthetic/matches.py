"""Exact synthetic correspondences: surface points of a scene projected through the water into both cameras."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .._geometry.camera import Camera
from .._geometry.interface import Interface
from .._geometry.precision import float64
from .._geometry.refraction import project_refracted
from .heightfield import Heightfield


@float64
def surface_correspondences(heightfield: Heightfield, left: Camera, right: Camera, interface: Interface, n: int,
                            noise_px: float, seed: int = 0, xy_min=(-0.7, -0.4), xy_max=(0.7, 0.4),
                            oversample: int = 3, margin_px: float = 5.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Up to `n` random surface points seen inside both images, with Gaussian pixel noise.

    Points are drawn uniformly in the rectangle `xy_min`..`xy_max` (world metres, `oversample * n` draws),
    lifted onto the heightfield, projected exactly (through the water where submerged) and kept when both
    projections lie `margin_px` inside the images. Occlusion is ignored: this tests geometry, not matching.

    **Returns:** `(left_pixels (k, 2), right_pixels (k, 2), points (k, 3))`, k <= n.
    """
    rng = np.random.default_rng(seed)
    xy = rng.uniform(xy_min, xy_max, (oversample * n, 2))
    z, _ = heightfield.height_at(jnp.asarray(xy))
    X = jnp.asarray(np.column_stack([xy, np.asarray(z)]))
    pl = np.asarray(project_refracted(left, interface, X)[0])
    pr = np.asarray(project_refracted(right, interface, X)[0])
    w, h = left.image_size
    upper = np.array([w - 1 - margin_px, h - 1 - margin_px])
    ok = np.all((pl > margin_px) & (pl < upper) & (pr > margin_px) & (pr < upper), axis=1)
    pl, pr, X = pl[ok][:n], pr[ok][:n], np.asarray(X)[ok][:n]
    return pl + rng.normal(0, noise_px, pl.shape), pr + rng.normal(0, noise_px, pr.shape), X
