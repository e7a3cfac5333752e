"""The flat air-water interface: the plane `normal . x = level` with refractive indices either side."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .errors import JaxStereoError, is_concrete
from .module import Module, replaced
from .precision import as_float64, float64
from .types import Scalar, Vector3
from .vectors import dot3

N_AIR = 1.000
N_WATER = 1.333


class Interface(Module):
    """A flat refracting interface between air (above) and water (below).

    The plane is `normal . x = level` in world coordinates; `normal` is a unit vector pointing into the
    air (up, `(0, 0, 1)` for a level water surface in the Z-up world frame).

    **Fields:**

    - `normal`: unit normal (3,), pointing from water into air.
    - `level`: plane offset, metres (the water level `h` when the normal is vertical).
    - `n_air`: refractive index above the plane (default 1.000).
    - `n_water`: refractive index below the plane (default 1.333, fresh water).
    """

    normal: Float[Array, "3"]
    level: Float[Array, ""]
    n_air: Float[Array, ""]
    n_water: Float[Array, ""]

    @float64
    def __init__(self, level: Scalar, normal: Vector3 = (0.0, 0.0, 1.0), n_air: Scalar = N_AIR, n_water: Scalar = N_WATER):
        self.normal = as_float64(normal)
        self.level = as_float64(level)
        self.n_air = as_float64(n_air)
        self.n_water = as_float64(n_water)

    def __check_init__(self):
        if np.shape(self.normal) != (3,):
            raise JaxStereoError(f"interface normal must have shape (3,), got {np.shape(self.normal)}")
        if np.shape(self.level) != ():
            raise JaxStereoError(f"interface level must be a scalar in metres, got shape {np.shape(self.level)}")
        if not is_concrete(self.normal, self.level, self.n_air, self.n_water):
            return
        normal = np.asarray(self.normal, dtype=np.float64)
        norm = float(np.linalg.norm(normal))
        if not np.isfinite(norm) or abs(norm - 1.0) > 1e-6:
            raise JaxStereoError(f"interface normal must be a unit vector, got {normal.tolist()} (norm {norm:.6g})")
        if not np.isfinite(float(self.level)):
            raise JaxStereoError(f"interface level must be finite, got {float(self.level)}")
        for name in ("n_air", "n_water"):
            value = float(getattr(self, name))
            if not np.isfinite(value) or value <= 0:
                raise JaxStereoError(f"interface {name} must be a positive refractive index, got {value}")

    @classmethod
    @float64
    def from_tilt(cls, level: Scalar, tilt_x: Scalar = 0.0, tilt_y: Scalar = 0.0, n_air: Scalar = N_AIR,
                  n_water: Scalar = N_WATER) -> "Interface":
        """Interface whose normal is (0, 0, 1) tilted by `tilt_x` about the world X axis, then `tilt_y` about Y.

        Angles in radians; this two-angle parameterisation is the one bundle adjustment refines.
        """
        normal = tilt_normal(jnp.asarray(tilt_x), jnp.asarray(tilt_y))
        return cls(level, normal, n_air, n_water)

    @property
    @float64
    def ratio(self) -> Float[Array, ""]:
        """Relative index `n_water / n_air`."""
        return self.n_water / self.n_air

    @float64
    def height_of(self, points_world: Float[ArrayLike, "*#batch 3"]) -> Float[Array, "*#batch"]:
        """Signed distance (metres) of points above the plane: positive in air, negative under water."""
        return dot3(jnp.asarray(points_world), self.normal) - self.level

    @float64
    def with_level(self, level: Scalar) -> "Interface":
        """The same interface at another level (metres)."""
        return replaced(self, level=jnp.asarray(level, dtype=self.level.dtype))


@float64
def tilt_normal(tilt_x: Float[ArrayLike, ""], tilt_y: Float[ArrayLike, ""]) -> Float[Array, "3"]:
    """Unit normal: (0, 0, 1) rotated by `tilt_x` rad about X, then by `tilt_y` rad about Y."""
    return jnp.stack(
        [jnp.sin(tilt_y) * jnp.cos(tilt_x), -jnp.sin(tilt_x), jnp.cos(tilt_y) * jnp.cos(tilt_x)]
    )


def check_camera_above(center, interface: Interface, name: str = "camera") -> None:
    """Raise `JaxStereoError` when a concrete camera centre (3,) is not strictly above the water plane."""
    if not is_concrete(center, interface):
        return
    height = float(np.asarray(center, dtype=np.float64) @ np.asarray(interface.normal, dtype=np.float64)) - float(
        interface.level
    )
    if height <= 0:
        raise JaxStereoError(
            f"{name} centre is {-height:.4g} m below the water plane (level {float(interface.level):.4g} m): "
            "cameras must be in air, above the water level"
        )


def check_water_denser(interface: Interface) -> None:
    """Raise `JaxStereoError` when a concrete interface has `n_water <= n_air` (forward projection needs it)."""
    if is_concrete(interface) and float(interface.n_water) <= float(interface.n_air):
        raise JaxStereoError(
            f"interface n_water ({float(interface.n_water):g}) must exceed n_air ({float(interface.n_air):g}) "
            "for forward projection through the surface"
        )
