"""The OpenCV pinhole camera with OpenCV distortion, as a PyTree."""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .errors import JaxStereoError, check_shape, is_concrete
from .module import Module, field, replaced
from .pose import Pose
from .precision import as_float64, float64
from .types import Coefficients, Matrix3, Scalar
from .vectors import apply3, unit3

N_DIST = 8
UNDISTORT_ITERATIONS = 12


def _pad_dist(dist) -> Float[Array, "8"]:
    """The distortion coefficients padded with zeros to `N_DIST` (8,). Concrete values are padded in numpy:
    each jnp operation a fresh process runs first is traced and loaded (a fifth of a second for these two)."""
    xp = np if is_concrete(dist) else jnp
    dist = xp.ravel(xp.asarray(dist))
    if dist.shape[0] > N_DIST:
        raise JaxStereoError(
            f"dist has {dist.shape[0]} coefficients; jaxstereo supports OpenCV's first 8 "
            "(k1, k2, p1, p2, k3, k4, k5, k6), not the thin-prism or tilt terms"
        )
    return as_float64(xp.pad(dist, (0, N_DIST - dist.shape[0])))


@float64
def distort_normalized(xy: Float[ArrayLike, "*#batch 2"], dist: Float[ArrayLike, "8"]) -> Float[Array, "*#batch 2"]:
    """Apply OpenCV distortion to normalised image coordinates (x/z, y/z), shape (..., 2)."""
    k1, k2, p1, p2, k3, k4, k5, k6 = (dist[i] for i in range(N_DIST))
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    r4 = r2 * r2
    r6 = r4 * r2
    radial = (1.0 + k1 * r2 + k2 * r4 + k3 * r6) / (1.0 + k4 * r2 + k5 * r4 + k6 * r6)
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return jnp.stack([xd, yd], axis=-1)


def _distortion_and_jacobian(x, y, dist):
    """Distorted coordinates and the 2x2 Jacobian of OpenCV's distortion at (x, y) (closed form)."""
    k1, k2, p1, p2, k3, k4, k5, k6 = (dist[i] for i in range(N_DIST))
    r2 = x * x + y * y
    num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
    dnum = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
    dden = k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2)
    radial = num / den
    dradial = (dnum * den - num * dden) / (den * den)  # d radial / d r2
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    cross = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
    a = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
    d = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
    return xd, yd, a, cross, cross, d


@float64
def undistort_normalized(
    xy_distorted: Float[ArrayLike, "*#batch 2"], dist: Float[ArrayLike, "8"], iterations: int = UNDISTORT_ITERATIONS
) -> Float[Array, "*#batch 2"]:
    """Invert `distort_normalized` by a fixed number of Newton steps (differentiable, jit-friendly).

    **Arguments:**

    - `xy_distorted`: distorted normalised coordinates, shape (..., 2).
    - `dist`: the 8 OpenCV coefficients.
    - `iterations`: Newton steps; 12 reach float64 round-off inside the image of ordinary lenses.

    **Returns:** undistorted normalised coordinates, shape (..., 2).
    """
    tx, ty = xy_distorted[..., 0], xy_distorted[..., 1]

    def step(_, p):
        x, y = p
        xd, yd, a, b, c, d = _distortion_and_jacobian(x, y, dist)
        rx, ry = xd - tx, yd - ty
        det = a * d - b * c
        return x - (d * rx - b * ry) / det, y - (-c * rx + a * ry) / det

    x, y = jax.lax.fori_loop(0, iterations, step, (tx, ty))
    return jnp.stack([x, y], axis=-1)


class Camera(Module):
    """An OpenCV camera: pinhole intrinsics, OpenCV distortion and a world -> camera pose.

    Pixel centres sit at integer coordinates (OpenCV's convention); `u = fx * x'' + cx`.

    **Fields:**

    - `fx`, `fy`: focal lengths, pixels.
    - `cx`, `cy`: principal point, pixels.
    - `dist`: distortion (8,): k1, k2, p1, p2, k3, k4, k5, k6 (OpenCV order; shorter inputs are zero-padded).
    - `pose`: `Pose`, world -> camera.
    - `image_size`: (width, height) in pixels (static).
    """

    fx: Float[Array, ""]
    fy: Float[Array, ""]
    cx: Float[Array, ""]
    cy: Float[Array, ""]
    dist: Float[Array, "8"]
    pose: Pose
    image_size: tuple[int, int] = field(static=True)

    @float64
    def __init__(self, fx: Scalar, fy: Scalar, cx: Scalar, cy: Scalar, dist: Coefficients, pose: Pose,
                 image_size: Sequence[int]):
        self.fx = as_float64(fx)
        self.fy = as_float64(fy)
        self.cx = as_float64(cx)
        self.cy = as_float64(cy)
        self.dist = _pad_dist(as_float64(dist))
        self.pose = pose
        self.image_size = (int(image_size[0]), int(image_size[1]))

    def __check_init__(self):
        if not isinstance(self.pose, Pose):
            raise JaxStereoError(f"camera pose must be a jaxstereo.Pose, got {type(self.pose).__name__}")
        if self.image_size[0] <= 0 or self.image_size[1] <= 0:
            raise JaxStereoError(f"camera image_size must be positive (width, height), got {self.image_size}")
        if is_concrete(self.fx, self.fy, self.cx, self.cy, self.dist):
            for name in ("fx", "fy"):
                value = float(getattr(self, name))
                if not np.isfinite(value) or value <= 0:
                    raise JaxStereoError(f"camera {name} must be a positive focal length in pixels, got {value}")
            for name in ("cx", "cy"):
                if not np.isfinite(float(getattr(self, name))):
                    raise JaxStereoError(f"camera {name} must be finite")
            if not np.all(np.isfinite(np.asarray(self.dist))):
                raise JaxStereoError("camera dist contains NaN or infinite values")

    @classmethod
    @float64
    def from_opencv(cls, K: Matrix3, dist: Coefficients, rvec: Coefficients, tvec: Coefficients,
                    image_size: Sequence[int]) -> "Camera":
        """Camera from OpenCV's `K` (3, 3), `dist` (<= 8,), `rvec` (3,) and `tvec` (3,) (world -> camera)."""
        K = np.asarray(K, dtype=np.float64)
        check_shape("K", K[None], (3, 3))
        pose = Pose.from_rvec(jnp.ravel(jnp.asarray(rvec, dtype=jnp.float64)), jnp.ravel(jnp.asarray(tvec, dtype=jnp.float64)))
        return cls(K[0, 0], K[1, 1], K[0, 2], K[1, 2], np.ravel(np.asarray(dist, dtype=np.float64)), pose, image_size)

    @property
    @float64
    def K(self) -> Float[Array, "3 3"]:
        """The 3x3 intrinsic matrix, pixels."""
        zero = jnp.zeros_like(self.fx)
        one = jnp.ones_like(self.fx)
        return jnp.stack(
            [jnp.stack([self.fx, zero, self.cx]), jnp.stack([zero, self.fy, self.cy]), jnp.stack([zero, zero, one])]
        )

    @property
    @float64
    def center(self) -> Float[Array, "3"]:
        """Camera centre in world coordinates (3,), metres."""
        return self.pose.center

    @float64
    def project(self, points_world: Float[ArrayLike, "*#batch 3"]) -> Float[Array, "*#batch 2"]:
        """Project world points (..., 3) metres to pixels (..., 2) through pose, pinhole and distortion.

        Points behind the camera still get a (meaningless) pixel; check `depth(points) > 0` where it matters.
        """
        pc = self.pose.apply(points_world)
        xy = pc[..., :2] / pc[..., 2:3]
        return self.normalized_to_pixels(distort_normalized(xy, self.dist))

    @float64
    def depth(self, points_world: Float[ArrayLike, "*#batch 3"]) -> Float[Array, "*#batch"]:
        """Depth of world points along the optical axis (camera z), metres."""
        return self.pose.apply(points_world)[..., 2]

    @float64
    def normalized_to_pixels(self, xy: Float[ArrayLike, "*#batch 2"]) -> Float[Array, "*#batch 2"]:
        """Normalised (distorted) coordinates (..., 2) to pixels (..., 2)."""
        return jnp.stack([self.fx * xy[..., 0] + self.cx, self.fy * xy[..., 1] + self.cy], axis=-1)

    @float64
    def pixels_to_normalized(self, pixels: Float[ArrayLike, "*#batch 2"]) -> Float[Array, "*#batch 2"]:
        """Pixels (..., 2) to normalised (still distorted) coordinates (..., 2)."""
        return jnp.stack([(pixels[..., 0] - self.cx) / self.fx, (pixels[..., 1] - self.cy) / self.fy], axis=-1)

    @float64
    def undistort_pixels(self, pixels: Float[ArrayLike, "*#batch 2"]) -> Float[Array, "*#batch 2"]:
        """Remove lens distortion: pixels (..., 2) -> ideal pinhole pixels (..., 2) with the same K."""
        return self.normalized_to_pixels(undistort_normalized(self.pixels_to_normalized(pixels), self.dist))

    @float64
    def distort_pixels(self, pixels: Float[ArrayLike, "*#batch 2"]) -> Float[Array, "*#batch 2"]:
        """Add lens distortion: ideal pinhole pixels (..., 2) -> observed pixels (..., 2)."""
        return self.normalized_to_pixels(distort_normalized(self.pixels_to_normalized(pixels), self.dist))

    @float64
    def backproject(self, pixels: Float[ArrayLike, "*#batch 2"]) -> tuple[Float[Array, "*#batch 3"], Float[Array, "*#batch 3"]]:
        """Rays through pixels: returns `(origin, direction)`, world frame, each (..., 3); directions are unit.

        The origin is the camera centre, broadcast to the batch shape.
        """
        xy = undistort_normalized(self.pixels_to_normalized(pixels), self.dist)
        d_cam = jnp.concatenate([xy, jnp.ones_like(xy[..., :1])], axis=-1)
        d_world = unit3(apply3(self.pose.R.T, d_cam))
        origin = jnp.broadcast_to(self.center, d_world.shape)
        return origin, d_world

    @float64
    def with_pose(self, pose: Pose) -> "Camera":
        """The same camera at another pose."""
        return replaced(self, pose=pose)
