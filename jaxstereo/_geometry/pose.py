"""Rigid camera poses: the world -> camera transform `x_cam = R x_world + t`, as in OpenCV."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .errors import JaxStereoError, is_concrete
from .module import Module
from .precision import as_float64, float64
from .types import Coefficients, Matrix3, Vector3
from .vectors import apply3


def _skew(v: Float[ArrayLike, "3"]) -> Float[Array, "3 3"]:
    x, y, z = v[0], v[1], v[2]
    zero = jnp.zeros_like(x)
    return jnp.stack(
        [jnp.stack([zero, -z, y]), jnp.stack([z, zero, -x]), jnp.stack([-y, x, zero])]
    )


@float64
def so3_exp(rvec: Float[ArrayLike, "3"]) -> Float[Array, "3 3"]:
    """Rotation matrix of a rotation vector (axis times angle in radians, OpenCV's `rvec`).

    Differentiable everywhere, including at `rvec = 0` (Taylor series near zero).
    """
    rvec = jnp.asarray(rvec)
    theta2 = jnp.sum(rvec**2)
    small = theta2 < 1e-12
    safe2 = jnp.where(small, 1.0, theta2)
    theta = jnp.sqrt(safe2)
    a = jnp.where(small, 1.0 - theta2 / 6.0, jnp.sin(theta) / theta)
    b = jnp.where(small, 0.5 - theta2 / 24.0, (1.0 - jnp.cos(theta)) / safe2)
    k = _skew(rvec)
    return jnp.eye(3, dtype=k.dtype) + a * k + b * (k @ k)


@float64
def so3_log(R: Float[ArrayLike, "3 3"]) -> Float[Array, "3"]:
    """Rotation vector (radians) of a rotation matrix; the inverse of `so3_exp` for angles below pi.

    Differentiable everywhere below pi, the identity included (its Jacobian there is the identity's).
    """
    R = jnp.asarray(R)
    cos = (jnp.trace(R) - 1.0) / 2.0
    w = jnp.stack([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])  # 2 sin(theta) * axis
    w2 = jnp.sum(w * w)
    # Near zero, theta / (2 sin theta) = 1/2 + theta^2/12 with theta^2 ~ |w|^2 / 4: a polynomial in w, so
    # the gradient never meets arccos'(1) or the norm's derivative at 0.
    small = (w2 < 1e-12) & (cos > 0.0)
    safe_w2 = jnp.where(w2 < 1e-12, 1.0, w2)
    sin = jnp.sqrt(safe_w2) / 2.0
    theta = jnp.where(w2 < 1e-12, jnp.where(cos > 0.0, 0.0, jnp.pi), jnp.arctan2(sin, cos))
    factor = jnp.where(small, 0.5 + w2 / 48.0, theta / (2.0 * sin))
    # Near pi, sin(theta) -> 0: recover the axis from the symmetric part instead.
    near_pi = (cos < 0.0) & (theta > jnp.pi - 1e-4)
    B = (R + R.T) / 2.0 - jnp.clip(cos, -1.0, 1.0) * jnp.eye(3, dtype=R.dtype)
    B = jnp.where(near_pi, B, jnp.eye(3, dtype=R.dtype))  # finite gradients where this branch is unused
    col = jnp.argmax(jnp.diag(B))
    axis = B[:, col] / jnp.maximum(jnp.linalg.norm(B[:, col]), 1e-300)
    axis = axis * jnp.where(jnp.dot(axis, w) < 0, -1.0, 1.0)
    return jnp.where(near_pi, axis * theta, factor * w)


class Pose(Module):
    """A rigid transform from the world frame to a camera frame: `x_cam = R @ x_world + t`.

    **Fields:**

    - `R`: rotation matrix, shape (3, 3), world -> camera.
    - `t`: translation, shape (3,), metres, the world origin in camera coordinates.
    """

    R: Float[Array, "3 3"]
    t: Float[Array, "3"]

    def __init__(self, R: Matrix3 | Coefficients, t: Vector3 | Coefficients):
        # Any float array or nested sequence here: `__check_init__` names a wrong shape.
        self.R = as_float64(R)
        self.t = as_float64(t)

    def __check_init__(self):
        if np.shape(self.R) != (3, 3):
            raise JaxStereoError(f"pose R must have shape (3, 3), got {np.shape(self.R)}")
        if np.shape(self.t) != (3,):
            raise JaxStereoError(f"pose t must have shape (3,), got {np.shape(self.t)}")
        if is_concrete(self.R):
            R = np.asarray(self.R, dtype=np.float64)
            if not np.all(np.isfinite(R)) or not np.all(np.isfinite(np.asarray(self.t))):
                raise JaxStereoError("pose R and t must be finite")
            if np.abs(R @ R.T - np.eye(3)).max() > 1e-5 or np.linalg.det(R) < 0:
                raise JaxStereoError("pose R is not a rotation matrix (R R^T != I or det R < 0)")

    @classmethod
    @float64
    def from_rvec(cls, rvec: Vector3, t: Vector3) -> "Pose":
        """Pose from OpenCV's rotation vector `rvec` (3,) radians and translation `t` (3,) metres."""
        return cls(so3_exp(jnp.asarray(rvec)), jnp.asarray(t))

    @classmethod
    @float64
    def from_center(cls, R: Matrix3, center: Vector3) -> "Pose":
        """Pose from the world -> camera rotation `R` (3, 3) and the camera centre (3,) in world metres."""
        R = jnp.asarray(R)
        return cls(R, -R @ jnp.asarray(center))

    @classmethod
    @float64
    def look_at(cls, center: Vector3, target: Vector3, up: Vector3 = (0.0, 0.0, 1.0)) -> "Pose":
        """Pose of a camera at `center` looking at `target` (world metres), image 'up' towards `up`.

        Camera axes follow OpenCV: x right, y down, z forward. When the view direction is parallel to
        `up` (a nadir camera), image x is aligned with world X.
        """
        center = np.asarray(center, dtype=np.float64)
        z = np.asarray(target, dtype=np.float64) - center
        norm = np.linalg.norm(z)
        if norm == 0:
            raise JaxStereoError("look_at: target equals the camera centre")
        z = z / norm
        up = np.asarray(up, dtype=np.float64)
        x = np.cross(z, up)
        if np.linalg.norm(x) < 1e-9:
            x = np.array([1.0, 0.0, 0.0]) - z * z[0]
        x = x / np.linalg.norm(x)
        y = np.cross(z, x)
        R = np.stack([x, y, z])
        return cls.from_center(R, center)

    @property
    @float64
    def rvec(self) -> Float[Array, "3"]:
        """OpenCV rotation vector (3,), radians."""
        return so3_log(self.R)

    @property
    @float64
    def center(self) -> Float[Array, "3"]:
        """Camera centre in world coordinates (3,), metres."""
        return -self.R.T @ self.t

    @float64
    def apply(self, points_world: Float[ArrayLike, "*#batch 3"]) -> Float[Array, "*#batch 3"]:
        """World points (..., 3) to camera coordinates (..., 3)."""
        return apply3(self.R, jnp.asarray(points_world)) + self.t

    @float64
    def inverse_apply(self, points_cam: Float[ArrayLike, "*#batch 3"]) -> Float[Array, "*#batch 3"]:
        """Camera-frame points (..., 3) to world coordinates (..., 3)."""
        return apply3(self.R.T, points_cam - self.t)

    @float64
    def compose(self, other: "Pose") -> "Pose":
        """The pose `self o other`: first `other`, then `self` (x -> R_s (R_o x + t_o) + t_s)."""
        return Pose(self.R @ other.R, self.R @ other.t + self.t)

    @float64
    def inverse(self) -> "Pose":
        """The inverse transform (camera -> world as a `Pose`)."""
        return Pose(self.R.T, -self.R.T @ self.t)

    @float64
    def retract(self, delta: Float[ArrayLike, "6"]) -> "Pose":
        """Small update for optimisation: `delta = (rotation vector (3,) rad, centre shift (3,) m)`.

        The rotation acts in the world frame (`R_new = R @ exp(delta[:3])`); the camera centre moves by
        `delta[3:]` in world metres. `retract(zeros)` is the identity.
        """
        R = self.R @ so3_exp(delta[:3])
        center = self.center + delta[3:]
        return Pose(R, -R @ center)
