"""Stereo rectification of a wet pair, in air (real cameras) or through the water (virtual cameras).

Both rectified cameras share one rotation and one intrinsic matrix, and sit at the real camera
centres ("air") or at the first-order virtual centres ("water"). In "water" mode the real image is
first warped into the virtual camera through the interface plane (the paper's step), so that
epipolar lines of under-water points become (nearly) straight rows.
"""

from __future__ import annotations

import cv2
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._geometry.camera import Camera
from .._geometry.errors import JaxStereoError
from .._geometry.first_order import _virtual_camera
from .._geometry.interface import Interface, check_camera_above
from .._geometry.module import Module, field
from .._geometry.refraction import intersect_plane
from .._geometry.vectors import apply3, inverse3, unit3
from .table_cache import cached_tables


class Rectification(Module):
    """A rectified stereo geometry (a PyTree: passes through `jax.jit`).

    **Fields:** `K` (3, 3) shared rectified intrinsics, pixels; `R` (3, 3) world -> rectified camera
    rotation (both cameras); `centers` (2, 3) rectified camera centres (left, right), world metres;
    `interface` (for "water", else None); `mode` ("air" or "water", static); `size` (width, height) pixels of the
    rectified images, static: the real images' size, or their height and width where the baseline runs down them.
    """

    K: Float[Array, "3 3"]
    R: Float[Array, "3 3"]
    centers: Float[Array, "2 3"]
    interface: Interface | None
    mode: str = field(static=True)
    size: tuple[int, int] = field(static=True)

    @property
    def baseline_m(self) -> float:
        c = np.asarray(self.centers)
        return float(np.linalg.norm(c[1] - c[0]))

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
        check_camera_above(left.center, interface, "left camera")
        check_camera_above(right.center, interface, "right camera")
    return rectify_checked(left, right, interface, mode)


def rectify_checked(left: Camera, right: Camera, interface: Interface | None, mode: str) -> Rectification:
    """`rectify` for callers that validated the mode, the interface and the cameras' heights once already."""
    itf = interface if mode == "water" else None
    arrays = cached_tables("rectification", (left, right, itf, mode),
                           lambda: _rectification_arrays(left, right, interface, mode))
    size = (int(arrays["size"][0]), int(arrays["size"][1]))
    # device_put, not jnp.asarray: the same arrays, without an eager operation to trace and load in a fresh process
    return Rectification(*(jax.device_put(arrays[key]) for key in ("K", "R", "centers")), itf, mode, size)


def _rectification_arrays(left: Camera, right: Camera, interface: Interface | None, mode: str) -> dict:
    """The rectification's `K` (3, 3), `R` (3, 3), `centers` (2, 3), float64 numpy, and `size` (2,) (width,
    height) pixels of the rectified images.

    The rectified rows run along the baseline. Where the baseline runs up or down the left image (cameras side by
    side across the images' short side, or turned a quarter about their axes), the rectified images are the real
    ones' height wide and their width high, so that they hold the same view turned; otherwise they are the real
    images' size."""
    cams = (_virtual_camera(left, interface), _virtual_camera(right, interface)) if mode == "water" else (left, right)
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
    along_image = np.asarray(left.pose.R) @ x  # the baseline in the left camera's frame
    if abs(along_image[1]) > abs(along_image[0]):
        w, h = h, w
    # Principal point: the mean view direction of the two cameras lands in the image centre.
    K = np.array([[f, 0.0, (w - 1) / 2.0], [0.0, f, (h - 1) / 2.0], [0.0, 0.0, 1.0]])
    shift = []
    for cam in (left, right):
        d = R @ np.asarray(cam.pose.R)[2]
        shift.append(f * d[:2] / d[2])
    K[:2, 2] -= np.mean(shift, axis=0)
    return {"K": K, "R": R, "centers": np.stack([c0, c1]), "size": np.array([w, h], dtype=np.int64)}


def rectified_to_real(rect: Rectification, camera: Camera, side: int, pixels):
    """Map rectified pixels (..., 2) of one side (0 left, 1 right) to that camera's real pixels (..., 2).

    Air: a pure rotation about the camera centre. Water: the virtual ray is intersected with the
    interface plane and that point projected by the real camera (with its distortion).
    """
    K_inv = inverse3(rect.K)
    hom = jnp.concatenate([pixels, jnp.ones_like(pixels[..., :1])], axis=-1)
    d = (hom @ K_inv.T) @ rect.R
    center = rect.centers[side]
    if rect.mode == "air":
        return camera.project(center + d), jnp.ones(pixels.shape[:-1], bool)
    itf = rect.interface
    hit, s = intersect_plane(jnp.broadcast_to(center, d.shape), d, itf.normal, itf.level)
    return camera.project(hit), (s > 0) & jnp.isfinite(s)


def rectified_rays(rect: Rectification, camera: Camera, side: int, pixels):
    """Real-camera rays of rectified pixels (..., 2), without any distortion round trip.

    **Returns:** `(origin, direction, surface)`: the real camera centre broadcast (..., 3), unit
    directions of the real rays in the world (..., 3), and for "water" the points where the rays
    cross the interface (..., 3) (for "air": the same as `origin`).
    """
    K_inv = inverse3(rect.K)
    hom = jnp.concatenate([pixels, jnp.ones_like(pixels[..., :1])], axis=-1)
    d = unit3(apply3(rect.R.T @ K_inv, hom))
    origin = jnp.broadcast_to(camera.center, d.shape)
    if rect.mode == "air":
        return origin, d, origin
    itf = rect.interface
    hit, _ = intersect_plane(jnp.broadcast_to(rect.centers[side], d.shape), d, itf.normal, itf.level)
    return origin, unit3(hit - origin), hit


def real_to_rectified(rect: Rectification, camera: Camera, side: int, pixels):
    """Inverse of `rectified_to_real`: real pixels (..., 2) -> rectified pixels (..., 2)."""
    origin, d = camera.backproject(pixels)
    if rect.mode == "water":
        itf = rect.interface
        hit, _ = intersect_plane(origin, d, itf.normal, itf.level)
        d = hit - rect.centers[side]
    p = d @ rect.R.T
    p = p @ rect.K.T
    return p[..., :2] / p[..., 2:3]




def rectification_maps(rect: Rectification, camera: Camera, side: int) -> tuple[np.ndarray, np.ndarray]:
    """`cv2.remap` maps (float32 (h, w) each) from the rectified image of `side` to the real image."""
    w, h = rect.size
    if rect.mode == "air":
        # A rotation about the camera centre: OpenCV's optimised map (R: camera frame -> rectified frame).
        K = np.asarray(camera.K, dtype=np.float64)
        R = np.asarray(rect.R) @ np.asarray(camera.pose.R).T
        dist = np.asarray(camera.dist, dtype=np.float64)
        return cv2.initUndistortRectifyMap(K, dist, R, np.asarray(rect.K), (w, h), cv2.CV_32FC1)
    # Through the water the map is smooth (a plane homography composed with the lens): computed exactly on a
    # grid every MAP_STEP pixels and interpolated bilinearly (error below 1e-3 px, see the tests).
    us, vs = _coarse_axis(w), _coarse_axis(h)

    def coarse() -> dict:
        u, v = np.meshgrid(us, vs)
        real, ok = rectified_to_real_jit(rect, camera, side, jnp.asarray(np.stack([u, v], axis=-1)))
        return {"real": np.asarray(real), "ok": np.asarray(ok)}

    grid = cached_tables("rectification map grid", (rect, camera, side), coarse)
    real, ok = grid["real"], grid["ok"]
    # float32 where full-size, as the maps are (1e-4 px; cv2.remap reads them to 1/32 px): on the development
    # flume's 1728x1152 pair, both cameras' maps 0.05 s on 2 cores (dense interpolation matrices) -> 0.03 s on one
    maps = [_upsampled(np.asarray(real[..., k], dtype=np.float64), h, w, np.float32) for k in range(2)]
    outside = ~_all_weighed_ok(np.asarray(ok, dtype=bool), h, w)
    for m in maps:
        m[outside] = -1.0
    return maps[0], maps[1]


def waterline_disparity(rect: Rectification) -> np.ndarray | None:
    """The disparity (h, w) float32 px, at each left rectified pixel, of the water plane's own points in a "water"
    rectification (None in "air"): a match with a larger disparity lies above the water, a smaller one below.

    A point on the plane is where both real rays cross it, so its rectified pixels are its projections through the
    rectified virtual cameras: a plane seen by two cameras that share `K` and `R`, whose disparity is
    `f B / depth`, affine in the pixel. (A point above the plane: its two rays cross the plane past it, beyond each
    other, and its disparity is larger.)"""
    if rect.mode != "water" or rect.interface is None:
        return None
    w, h = rect.size
    K, R, centers = (np.asarray(a, dtype=np.float64) for a in (rect.K, rect.R, rect.centers))
    normal = np.asarray(rect.interface.normal, dtype=np.float64)
    height = float(rect.interface.level) - normal @ centers[0]  # < 0: the camera is above the water
    baseline = float((R @ (centers[1] - centers[0]))[0])  # along the rectified rows
    # Along a left rectified pixel's ray r = R^T K^-1 (u, v, 1), the plane lies at depth height / (n . r).
    a = R @ normal
    a = np.linalg.solve(K.T, a)  # n . r = a . (u, v, 1)
    u = np.arange(w, dtype=np.float64)[None, :]
    v = np.arange(h, dtype=np.float64)[:, None]
    return (K[0, 0] * baseline * (a[0] * u + a[1] * v + a[2]) / height).astype(np.float32)


MAP_STEP = 8


def _coarse_axis(n: int) -> np.ndarray:
    return np.arange(0, n - 1 + MAP_STEP, MAP_STEP, dtype=np.float64)


def _upsampled(values: np.ndarray, h: int, w: int, dtype=np.float64) -> np.ndarray:
    """`values` (nv, nu) on the coarse grid (every `MAP_STEP` pixels from 0, `_coarse_axis`), interpolated
    bilinearly to every pixel: (h, w) of `dtype` (the rows in float64, the full-size columns in `dtype`). Each
    coarse cell's `MAP_STEP` rows, then columns, are its first value plus the step to the next times their
    fraction, by broadcasting: no interpolation matrices, mostly zeros, and no gathers."""
    fraction = np.arange(MAP_STEP, dtype=np.float64) / MAP_STEP
    values = _with_last_repeated(values)
    along = values[:-1, None, :] + (values[1:] - values[:-1])[:, None, :] * fraction[None, :, None]
    along = along.reshape(-1, values.shape[1])[:h]  # (h, nu + 1)
    first, step = along[:, :-1, None].astype(dtype), (along[:, 1:] - along[:, :-1])[:, :, None].astype(dtype)
    full = first + step * fraction.astype(dtype)
    return np.ascontiguousarray(full.reshape(h, -1)[:, :w])  # a copy only where w is no multiple of the step


def _all_weighed_ok(ok: np.ndarray, h: int, w: int) -> np.ndarray:
    """Where (h, w) bool every coarse knot that `_upsampled` weighs in (weight > 0) is `ok` (nv, nu) bool: a pixel
    on a knot's row or column weighs in that knot alone along it."""
    on_knot = np.arange(MAP_STEP) == 0
    ok = _with_last_repeated(ok)
    along = ok[:-1, None, :] & (ok[1:, None, :] | on_knot[None, :, None])
    along = along.reshape(-1, ok.shape[1])[:h]
    return (along[:, :-1, None] & (along[:, 1:, None] | on_knot)).reshape(h, -1)[:, :w]


def _with_last_repeated(values: np.ndarray) -> np.ndarray:
    """`values` (nv, nu) with its last row and column repeated (nv + 1, nu + 1): the last knot, at or past the
    image's last pixel, may lie on it, and then it starts a cell of its own (weighed in alone)."""
    return np.pad(values, ((0, 1), (0, 1)), mode="edge")


def remap(image: np.ndarray, maps: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Warp a real image into the rectified frame (bilinear; black outside)."""
    return cv2.remap(image, maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


rectified_to_real_jit = jax.jit(rectified_to_real, static_argnums=2)
