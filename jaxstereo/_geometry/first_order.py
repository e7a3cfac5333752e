"""The paper's first-order refraction model (Ferreira et al. 2005): a virtual pinhole camera.

Keeping the first-order term of Snell's law, `tan(theta_water) ~ tan(theta_air) / n` with
`n = n_water / n_air`, every refracted ray of a camera at height `H` above the interface passes
through one virtual centre on the interface normal through the camera, at height `n * H`. The
virtual camera keeps the real camera's orientation and principal point, has its focal length scaled
by `n` (so a nadir camera's virtual image equals its undistorted real image) and no distortion. Real
and virtual images are related by the homography induced by the interface plane; after warping,
any ordinary (in-air) stereo algorithm applies to the submerged part of the scene.
"""

from __future__ import annotations

from typing import Union

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float

from .camera import Camera
from .errors import check_shape
from .interface import Interface, check_camera_above
from .pose import Pose
from .precision import float64
from .refraction import intersect_plane
from .types import Scalar
from .vectors import inverse3


@float64
def virtual_camera(camera: Camera, interface: Interface) -> Camera:
    """The first-order virtual camera of `camera` under `interface`.

    **Returns:** a distortion-free `Camera` with the same rotation and principal point, focal lengths
    multiplied by `n_water / n_air`, and its centre moved along the interface normal from height `H`
    to `n H` above the plane.
    """
    check_camera_above(camera.center, interface)
    return _virtual_camera(camera, interface)


def _virtual_camera(camera: Camera, interface: Interface) -> Camera:
    """`virtual_camera` for callers that checked the camera's height once at their own boundary."""
    n = interface.ratio
    height = interface.height_of(camera.center)
    center = camera.center + (n - 1.0) * height * interface.normal
    pose = Pose.from_center(camera.pose.R, center)
    return Camera(camera.fx * n, camera.fy * n, camera.cx, camera.cy, jnp.zeros(8, camera.fx.dtype), pose,
                  camera.image_size)


def _plane_basis(interface: Interface):
    nrm = interface.normal
    helper = jnp.where(jnp.abs(nrm[0]) < 0.9, jnp.array([1.0, 0.0, 0.0]), jnp.array([0.0, 1.0, 0.0]))
    e1 = jnp.cross(nrm, helper)
    e1 = e1 / jnp.linalg.norm(e1)
    e2 = jnp.cross(nrm, e1)
    origin = interface.level * nrm
    return origin, e1, e2


def _plane_to_image(camera: Camera, interface: Interface) -> Float[Array, "3 3"]:
    origin, e1, e2 = _plane_basis(interface)
    R, t = camera.pose.R, camera.pose.t
    M = jnp.stack([R @ e1, R @ e2, R @ origin + t], axis=1)
    return camera.K @ M


@float64
def first_order_homography(camera: Camera, interface: Interface) -> Float[Array, "3 3"]:
    """Homography (3, 3) from the real camera's undistorted pixels to its virtual camera's pixels.

    Both cameras see the interface plane; a real pixel maps to the virtual pixel of the same
    interface point. Apply it to undistorted pixels (`camera.undistort_pixels`) in homogeneous form.
    """
    check_camera_above(camera.center, interface)
    virtual = _virtual_camera(camera, interface)
    H = _plane_to_image(virtual, interface) @ inverse3(_plane_to_image(camera, interface))
    return H / H[2, 2]


@float64
def project_first_order(
    camera: Camera, interface: Interface, points_world: Float[ArrayLike, "*#batch 3"]
) -> tuple[Float[Array, "*#batch 2"], Bool[Array, "*#batch"]]:
    """First-order forward projection of world points (..., 3) to real-image pixels (..., 2).

    Under-water points are seen along the line to the virtual centre; that line's crossing of the
    interface is projected by the real camera (with its distortion). Points above the plane project
    as plain pinhole points. Returns `(pixels, valid)` as `project_refracted` does.
    """
    check_shape("points_world", points_world, (3,))
    check_camera_above(camera.center, interface)
    virtual = _virtual_camera(camera, interface)
    c_virtual = virtual.center
    d = points_world - c_virtual
    hit, _ = intersect_plane(jnp.broadcast_to(c_virtual, d.shape), d, interface.normal, interface.level)
    submerged = interface.height_of(points_world) < 0
    target = jnp.where(submerged[..., None], hit, points_world)
    return camera.project(target), camera.depth(target) > 0


@float64
def backproject_first_order(
    camera: Camera, interface: Interface, pixels: Float[ArrayLike, "*#batch 2"]
) -> tuple[Float[Array, "*#batch 3"], Float[Array, "*#batch 3"], Bool[Array, "*#batch"]]:
    """First-order back-projection: pixels (..., 2) -> rays in the water from the virtual centre.

    **Returns:** `(origins, directions, valid)` like `backproject_refracted`: origins on the interface
    (..., 3), unit directions (..., 3) along the virtual ray, `valid` (...,) false for rays that never
    reach the water.
    """
    check_shape("pixels", pixels, (2,))
    check_camera_above(camera.center, interface)
    virtual = _virtual_camera(camera, interface)
    origin, d = camera.backproject(pixels)
    hit, s = intersect_plane(origin, d, interface.normal, interface.level)
    direction = hit - virtual.center
    direction = direction / jnp.linalg.norm(direction, axis=-1, keepdims=True)
    return hit, direction, (s > 0) & jnp.isfinite(s)


@float64
def refraction_angle_exact(incidence: Union[Scalar, Float[ArrayLike, "*#batch"]], n_ratio: Scalar) -> Float[Array, "*#batch"]:
    """Exact refraction angle (radians) for incidence angles (radians): `asin(sin(theta) / n)`."""
    return jnp.arcsin(jnp.sin(incidence) / n_ratio)


@float64
def refraction_angle_first_order(incidence: Union[Scalar, Float[ArrayLike, "*#batch"]],
                                 n_ratio: Scalar) -> Float[Array, "*#batch"]:
    """First-order refraction angle (radians): `atan(tan(theta) / n)`, the virtual-camera model's."""
    return jnp.arctan(jnp.tan(incidence) / n_ratio)
