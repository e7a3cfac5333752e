"""Stereo rectification of a wet pair, in air (real cameras) or through the water (virtual cameras).

Both rectified cameras share one rotation and one intrinsic matrix, and sit at the real camera
centres ("air") or at the first-order virtual centres ("water"). In "water" mode the real image is
first warped into the virtual camera through the interface plane (the paper's step), so that
epipolar lines of under-water points become (nearly) straight rows.
"""

from __future__ import annotations

import dataclasses

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from ._camera import Camera
from ._errors import JaxStereoError
from ._first_order import virtual_camera
from ._interface import Interface
from ._refraction import intersect_plane


@dataclasses.dataclass(frozen=True)
class Rectification:
    """A rectified stereo geometry.

    **Fields:** `mode` ("air" or "water"); `K` (3, 3) shared rectified intrinsics, pixels; `R` (3, 3)
    world -> rectified camera rotation (both cameras); `centers` ((3,), (3,)) rectified camera centres,
    world metres; `size` (width, height); `interface` (for "water").
    """

    mode: str
    K: np.ndarray
    R: np.ndarray
    centers: tuple[np.ndarray, np.ndarray]
    size: tuple[int, int]
    interface: Interface | None

    @property
    def baseline_m(self) -> float:
        return float(np.linalg.norm(self.centers[1] - self.centers[0]))

    @property
    def focal_px(self) -> float:
        return float(self.K[0, 0])


def rectify(left: Camera, right: Camera, interface: Interface | None, mode: str) -> Rectification:
    """Rectified geometry of a pair: shared rotation with X along the baseline, Z along the mean view.

    **Arguments:** the two cameras, the interface (required for mode "water"), `mode` "air" or "water".
    """
    if mode not in ("air", "water"):
        raise JaxStereoError(f"rectification mode must be 'air' or 'water', got {mode!r}")
    if mode == "water":
        if interface is None:
            raise JaxStereoError("water rectification needs the interface (water level)")
        cams = (virtual_camera(left, interface), virtual_camera(right, interface))
    else:
        cams = (left, right)
    c0, c1 = (np.asarray(c.center, dtype=np.float64) for c in cams)
    x = c1 - c0
    if np.linalg.norm(x) == 0:
        raise JaxStereoError("the two cameras share one centre: no stereo baseline")
    x /= np.linalg.norm(x)
    z = np.asarray(left.pose.R)[2] + np.asarray(right.pose.R)[2]
    z = z - (z @ x) * x
    z /= np.linalg.norm(z)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    f = float(np.mean([float(cams[0].fx), float(cams[0].fy), float(cams[1].fx), float(cams[1].fy)]))
    w, h = left.image_size
    # Principal point: the mean view direction of the two cameras lands in the image centre.
    K = np.array([[f, 0.0, (w - 1) / 2.0], [0.0, f, (h - 1) / 2.0], [0.0, 0.0, 1.0]])
    shift = []
    for cam in (left, right):
        d = R @ np.asarray(cam.pose.R)[2]
        shift.append(f * d[:2] / d[2])
    K[:2, 2] -= np.mean(shift, axis=0)
    return Rectification(mode, K, R, (c0, c1), (w, h), interface)


def rectified_to_real(rect: Rectification, camera: Camera, side: int, pixels):
    """Map rectified pixels (..., 2) of one side (0 left, 1 right) to that camera's real pixels (..., 2).

    Air: a pure rotation about the camera centre. Water: the virtual ray is intersected with the
    interface plane and that point projected by the real camera (with its distortion).
    """
    K_inv = jnp.asarray(np.linalg.inv(rect.K))
    hom = jnp.concatenate([pixels, jnp.ones_like(pixels[..., :1])], axis=-1)
    d = (hom @ K_inv.T) @ jnp.asarray(rect.R)
    center = jnp.asarray(rect.centers[side])
    if rect.mode == "air":
        return camera.project(center + d), jnp.ones(pixels.shape[:-1], bool)
    itf = rect.interface
    hit, s = intersect_plane(jnp.broadcast_to(center, d.shape), d, itf.normal, itf.level)
    return camera.project(hit), (s > 0) & jnp.isfinite(s)


def real_to_rectified(rect: Rectification, camera: Camera, side: int, pixels):
    """Inverse of `rectified_to_real`: real pixels (..., 2) -> rectified pixels (..., 2)."""
    origin, d = camera.backproject(pixels)
    if rect.mode == "water":
        itf = rect.interface
        hit, _ = intersect_plane(origin, d, itf.normal, itf.level)
        d = hit - jnp.asarray(rect.centers[side])
    p = d @ jnp.asarray(rect.R).T
    p = p @ jnp.asarray(rect.K).T
    return p[..., :2] / p[..., 2:3]




def rectification_maps(rect: Rectification, camera: Camera, side: int) -> tuple[np.ndarray, np.ndarray]:
    """`cv2.remap` maps (float32 (h, w) each) from the rectified image of `side` to the real image."""
    w, h = rect.size
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pixels = jnp.asarray(np.stack([u, v], axis=-1))
    fn = jax.jit(lambda cam, p: rectified_to_real(rect, cam, side, p))
    real, ok = fn(camera, pixels)
    real = np.asarray(real, dtype=np.float32)
    real[~np.asarray(ok)] = -1.0
    return real[..., 0], real[..., 1]


def remap(image: np.ndarray, maps: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Warp a real image into the rectified frame (bilinear; black outside)."""
    return cv2.remap(image, maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
