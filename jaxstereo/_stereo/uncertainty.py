"""Each survey point's covariance, propagated by JAX derivatives through the exact refracted triangulation.

Two kinds of error, kept apart because they behave differently downstream:

- **matching**, independent from match to match (beyond the matching window): the disparity's standard
  deviation from the matching itself (`refine_disparity`) times the derivative of the point with respect
  to its disparity (see below: tabulated with the shared Jacobian, to within 1 % of the exact derivative);
- **shared** by every point of a survey: the calibration (the world frame's 6 parameters, the right
  camera's pose relative to the left 6, the focal length 1) and the water level (1), with the covariance
  the calibration and `refine` recorded in the rig. Their effect on a point is the (3, 14) Jacobian of the
  triangulation with respect to them, computed exactly (forward-mode JAX derivatives) on a table over
  (u, v, disparity) for emerged and for submerged points, and interpolated to each match (it is smooth in
  all three). The table holds the derivative with respect to the disparity too. Both come from the exact
  model (in air, or refracted exactly): for a first-order survey they are the exact model's, which differs
  from its own by the approximation's small relative error;
- the **sub-pixel estimators' disagreement** (`refine_disparity`): a systematic offset of unknown sign,
  correlated over the window, carried by the same derivative as the matching's.

`grid_survey` keeps them apart as DEM layers and `damage_sigma` samples them through the damage.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from .._calibration.rig import Rig
from .._geometry.camera import Camera
from .._geometry.interface import Interface
from .._geometry.pose import so3_exp
from .._geometry.refraction import intersect_plane, refract_directions
from .._geometry.triangulate import triangulate_rays
from .rectify import Rectification, rectified_rays
from .table_cache import cached_tables

SHARED_PARAMETERS = ("frame rotation x (rad)", "frame rotation y (rad)", "frame rotation z (rad)",
                     "frame shift x (m)", "frame shift y (m)", "frame shift z (m)",
                     "right rotation x (rad)", "right rotation y (rad)", "right rotation z (rad)",
                     "right shift x (m)", "right shift y (m)", "right shift z (m)",
                     "focal length (relative)", "water level (m)")
TABLE_STEP_PX = 96  # table spacing in u and v (pixels)
TABLE_STEP_DISPARITY_PX = 8  # and in disparity
INTERPOLATION_CHUNK = 1 << 17  # matches per compiled interpolation call
TABLE_CHANNELS = 10  # the shared covariance's 6 terms, its water level part, the point's derivative (3)
# Matches closer than this share most of their sub-pixel fit's patch: their errors correlate. The large patch's
# width (`ReconstructOptions.subpixel_window`). Measured on the POV-Ray flume's board, the height errors' correlation
# along rows and columns falls to zero at 32 px with a 31 px patch and at about 45 px with 47; on curved rubble,
# where the 9 px patch fits, it is 0.08 at 8 px already, so there the damage's error bars are generous.
MATCH_CORRELATION_PX = 47


@dataclasses.dataclass(frozen=True)
class SharedErrors:
    """The errors shared by every point of a survey.

    **Fields:** `cov` (14, 14) covariance of the parameters named in `SHARED_PARAMETERS` (radians, metres,
    relative focal length; block diagonal: frame, right pose, focal, level); `recorded` which of the rig's
    records were found ("world frame", "right pose", "focal length", "water level") and which were not.
    """

    cov: np.ndarray
    recorded: dict

    @property
    def std(self) -> dict:
        return {name: float(np.sqrt(self.cov[k, k])) for k, name in enumerate(SHARED_PARAMETERS)}


def shared_errors(rig: Rig, level_std_m: float) -> SharedErrors:
    """The shared errors of surveys made with `rig`: the world frame's and the right pose's covariance and the
    focal length's relative std from its calibration record, and the water level's std `level_std_m` (metres;
    0 for a level known exactly, or a dry survey). A record the rig lacks counts as zero and is named so."""
    record = rig.calibration if isinstance(rig.calibration, dict) else {}
    frame = record.get("world_frame") if isinstance(record.get("world_frame"), dict) else {}
    cov = np.zeros((14, 14))
    recorded = {}
    for key, block, name in (("frame_cov", slice(0, 6), "world frame"), ("right_pose_cov", slice(6, 12), "right pose")):
        value = np.asarray(frame.get(key, np.zeros((0, 0))), dtype=np.float64)
        recorded[name] = value.shape == (6, 6) and bool(np.all(np.isfinite(value)))
        if recorded[name]:
            cov[block, block] = value
    focal = record.get("focal_std_rel")
    recorded["focal length"] = focal is not None and bool(np.isfinite(focal))
    cov[12, 12] = float(focal) ** 2 if recorded["focal length"] else 0.0
    recorded["water level"] = bool(np.isfinite(level_std_m))
    cov[13, 13] = float(level_std_m) ** 2 if recorded["water level"] else 0.0
    return SharedErrors(cov, recorded)


def _perturbed_rays(theta, rect: Rectification, left: Camera, right: Camera, rl, rr):
    """The real rays of rectified matches under a small error `theta` (14,) of the shared parameters:
    `((c_l, d_l), (c_r, d_r))` world centres and unit directions (n, 3)."""
    (cl, dl, _), (cr, dr, _) = (rectified_rays(rect, cam, side, px) for side, cam, px in ((0, left, rl), (1, right, rr)))
    eps = theta[12]
    rays = []
    for cam, c, d in ((left, cl, dl), (right, cr, dr)):
        # A focal length off by eps: the rays' angles shrink, and the camera, fitted to the origin board with
        # that focal length, sits eps further from it (the world origin).
        dc = d @ cam.pose.R.T
        dc = jnp.concatenate([dc[..., :2] / (1.0 + eps), dc[..., 2:]], axis=-1)
        rays.append([c * (1.0 + eps), dc @ cam.pose.R])
    rays[1][1] = rays[1][1] @ so3_exp(theta[6:9])  # the right pose's rotation (`Pose.retract`: R exp(w))
    rays[1][0] = rays[1][0] + theta[9:12]
    frame = so3_exp(theta[0:3])  # the world frame's move: X -> exp(w) X + v
    out = []
    for c, d in rays:
        d = d @ frame.T
        out.append((c @ frame.T + theta[3:6], d / jnp.linalg.norm(d, axis=-1, keepdims=True)))
    return out


def _triangulate_as(submerged: bool, interface: Interface | None, theta, rays):
    """Points (n, 3) from two rays each: in air, or both refracted at the interface raised by `theta[13]`."""
    (cl, dl), (cr, dr) = rays
    if not submerged or interface is None:
        return triangulate_rays(cl, dl, cr, dr)[0]
    refracted = []
    for c, d in ((cl, dl), (cr, dr)):
        hit, _ = intersect_plane(c, d, interface.normal, interface.level + theta[13])
        bent, _ = refract_directions(d, interface.normal, interface.n_air, interface.n_water)
        refracted.append((hit, bent))
    return triangulate_rays(refracted[0][0], refracted[0][1], refracted[1][0], refracted[1][1])[0]


def _shared_jacobians(rect, left, right, interface, rl, rr):
    """(2, n, 3, 15): the points' Jacobians with respect to the shared parameters (the first 14 columns,
    `SHARED_PARAMETERS`) and to the disparity (the last: metres per pixel), emerged and submerged."""
    def points(theta, submerged):
        shifted = rr - theta[14] * jnp.asarray([1.0, 0.0])  # a larger disparity moves the right pixel left
        return _triangulate_as(submerged, interface, theta, _perturbed_rays(theta, rect, left, right, rl, shifted))

    zero = jnp.zeros(15)
    return jnp.stack([jax.jacfwd(points)(zero, s) for s in (False, True)])


_shared_jacobians_jit = jax.jit(_shared_jacobians)


def shared_covariance_table(rect: Rectification, rig: Rig, interface: Interface | None, shared: SharedErrors,
                            image_size: tuple[int, int], search: tuple[int, int]) -> dict:
    """The shared errors' covariance of a point (3, 3) and the point's derivative with respect to its disparity
    (3,), for emerged and submerged points (in air; refracted exactly), on a table over the left rectified pixel
    (u, v) and the disparity (every `TABLE_STEP_PX` and `TABLE_STEP_DISPARITY_PX`), over the rectified images'
    `image_size` (w, h) pixels (`rect.size`) and the disparity `search` (first, count) pixels.

    **Returns:** `{"table": (2, nv, nu, nd, 10) [xx, yy, zz, xy, xz, yz, zz from the water level alone] m^2 and
    [dx, dy, dz] / dd metres per pixel, "origin": (v0, u0, d0), "step": (sv, su, sd)}` for `point_covariances`.
    """
    V, U, D = np.meshgrid(*_table_axes(image_size, search), indexing="ij")
    n = V.size
    padded = 1 << max(10, int(np.ceil(np.log2(n))))  # a few compiled sizes, not one per search range
    rl = np.stack([U.ravel(), V.ravel()], axis=-1)
    rr = np.stack([U.ravel() - D.ravel(), V.ravel()], axis=-1)

    def table() -> dict:
        padded_l, padded_r = (jnp.asarray(np.pad(a, ((0, padded - n), (0, 0)), mode="edge")) for a in (rl, rr))
        J = np.asarray(_shared_jacobians_jit(rect, rig.left, rig.right, interface, padded_l, padded_r))[:, :n]
        shared_part = J[..., :14]
        cov = np.einsum("cnik,kl,cnjl->cnij", shared_part, shared.cov, shared_part)
        level_zz = J[..., 2, 13] ** 2 * shared.cov[13, 13]
        ten = np.stack([cov[..., 0, 0], cov[..., 1, 1], cov[..., 2, 2], cov[..., 0, 1], cov[..., 0, 2],
                        cov[..., 1, 2], level_zz, J[..., 0, 14], J[..., 1, 14], J[..., 2, 14]], axis=-1)
        return {"table": np.nan_to_num(ten, nan=0.0, posinf=0.0, neginf=0.0)}

    inputs = (rect, rig.left, rig.right, interface, np.asarray(shared.cov, np.float64), tuple(image_size),
              tuple(int(k) for k in search))
    ten = cached_tables("shared covariance", inputs, table)["table"]
    return {"table": ten.reshape((2,) + V.shape + (TABLE_CHANNELS,)), "origin": (0.0, 0.0, float(search[0])),
            "step": (float(TABLE_STEP_PX), float(TABLE_STEP_PX), float(TABLE_STEP_DISPARITY_PX))}


def _table_axes(image_size: tuple[int, int], search: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The covariance table's nodes: rows, columns (pixels, every `TABLE_STEP_PX`) and disparities (pixels, every
    `TABLE_STEP_DISPARITY_PX` over the `search` range `(first, count)`), float64."""
    w, h = image_size
    us = np.arange(0, w - 1 + TABLE_STEP_PX, TABLE_STEP_PX, dtype=np.float64)
    vs = np.arange(0, h - 1 + TABLE_STEP_PX, TABLE_STEP_PX, dtype=np.float64)
    ds = np.arange(search[0], search[0] + search[1] + TABLE_STEP_DISPARITY_PX, TABLE_STEP_DISPARITY_PX,
                   dtype=np.float64)
    return vs, us, ds


def load_point_covariances(image_size: tuple[int, int], search: tuple[int, int]) -> None:
    """Trace `point_covariances`' compiled part for the table of the rectified `image_size` (w, h) and `search`
    (first, count) pixels, and load it (JAX's persistent cache) or compile it, on zeros: what a fresh process
    would otherwise do in its first call (a tenth of a second). Thread-safe; the values are not used."""
    shape = (2, *(len(axis) for axis in _table_axes(image_size, search)), TABLE_CHANNELS)
    zeros = np.zeros(INTERPOLATION_CHUNK, np.float32)
    # numpy in, as the real calls pass it (jnp.asarray would trace and load an eager copy per shape)
    jax.block_until_ready(_chunk_errors(np.zeros(shape, np.float32), np.zeros((3, INTERPOLATION_CHUNK), np.float32),
                                        zeros.astype(np.int32), zeros, zeros))


def point_covariances(table: dict, v: np.ndarray, u: np.ndarray, disparity: np.ndarray, refracted: np.ndarray,
                      sigma_d: np.ndarray, disagreement: np.ndarray,
                      on_rows: Callable[[dict, int, int], None] | None = None) -> dict:
    """Each point's covariance: shared (interpolated from `table`), matching (`sigma_d^2 j j^T`) and the sub-pixel
    estimators' disagreement (`delta^2 j j^T`, see `refine_disparity`), with `j` the point's derivative with
    respect to its disparity (interpolated from `table` too).

    **Arguments:** the matches' left rectified rows `v`, columns `u`, disparities (k,) pixels; `refracted` (k,)
    bool: the table's submerged (refracted) sub-table, else the emerged (in-air) one; the disparities' std
    `sigma_d` (k,) pixels; `disagreement` (k,) pixels.

    `on_rows(fields, start, stop)`, when given, is called each time rows `start:stop` of the returned `fields` are
    known, in order (the command line writes them to the survey's file meanwhile); they do not change after.

    **Returns:** the `Survey` fields `cov` (k, 6) float32 [xx, yy, zz, xy, xz, yz] m^2, `sigma_z_match` and
    `sigma_z_level` (k,) float32 metres (the matching's and the water level's parts of the vertical std), and
    `dz_subpixel` (k,) float32 metres, the signed vertical offset the estimators' disagreement gives.
    """
    f32 = np.float32  # covariances need no more
    origin, step = table["origin"], table["step"]
    coords = np.stack([(np.asarray(v, f32) - f32(origin[0])) / f32(step[0]),
                       (np.asarray(u, f32) - f32(origin[1])) / f32(step[1]),
                       (np.asarray(disparity, f32) - f32(origin[2])) / f32(step[2])])
    per_point = (refracted.astype(np.int32), np.asarray(sigma_d, f32), np.nan_to_num(disagreement).astype(f32))
    values = jax.device_put(table["table"].astype(f32))  # on the device once; device_put loads no eager copy
    k = len(v)
    out = {"cov": np.empty((k, 6), f32), **{name: np.empty(k, f32) for name in _PER_POINT_ERRORS}}
    for start in range(0, k, INTERPOLATION_CHUNK):  # fixed-size chunks: compiled once, whatever the count
        part = slice(start, start + INTERPOLATION_CHUNK)
        count = coords[:, part].shape[1]
        pad = INTERPOLATION_CHUNK - count
        chunk = [np.pad(coords[:, part], ((0, 0), (0, pad)))]  # numpy in, as `reconstruct._chunked`
        chunk += [np.pad(a[part], (0, pad)) for a in per_point]
        for name, result in zip(("cov", *_PER_POINT_ERRORS), _chunk_errors(values, *chunk)):
            out[name][part] = np.asarray(result)[:count]
        if on_rows is not None:
            on_rows(out, start, start + count)
    return out


_PAIRS = ((0, 1, 2, 0, 0, 1), (0, 1, 2, 1, 2, 2))  # the covariance's [xx, yy, zz, xy, xz, yz]
_PER_POINT_ERRORS = ("sigma_z_match", "sigma_z_level", "dz_subpixel")


@jax.jit
def _interpolate_table(table, coords_t, cls):
    """`_trilinear` with coordinates (3, C) in and values (TABLE_CHANNELS, C) out."""
    return _trilinear(table, coords_t.T, cls).T


@jax.jit
def _combine_errors(channels, sigma_d, disagreement):
    """`point_covariances` on a chunk of C matches, float32, from the table's `channels` interpolated to them
    (TABLE_CHANNELS, C) and their disparities' std and disagreement (C,): `(cov (C, 6), sigma_z_match,
    sigma_z_level, dz_subpixel)`. (A compiled function of its own: fused with the interpolation, XLA's CPU
    code was ten times slower than the two apart.)"""
    j = channels[7:10]  # d(point)/d(disparity)
    match, method = j * sigma_d, j * disagreement
    cov = jnp.stack([channels[c] + match[p] * match[q] + method[p] * method[q]
                     for c, (p, q) in enumerate(zip(*_PAIRS))], axis=-1)
    return cov, jnp.abs(match[2]), jnp.sqrt(jnp.maximum(channels[6], 0.0)), method[2]


def _chunk_errors(table, coords_t, cls, sigma_d, disagreement):
    """`_combine_errors` of `_interpolate_table` at coordinates (3, C) of sub-tables `cls` (C,)."""
    return _combine_errors(_interpolate_table(table, coords_t, cls), sigma_d, disagreement)


def _trilinear(table, coords, cls):
    """Trilinear interpolation of `table` (2, n0, n1, n2, c) at fractional indices `coords` (k, 3) of the
    sub-table `cls` (k,) (clamped at the edges): (k, c). All channels share one set of corners and weights."""
    shape = jnp.asarray(table.shape[1:4])
    x = jnp.clip(coords, 0.0, shape - 1.0)
    i0 = jnp.minimum(jnp.floor(x).astype(jnp.int32), jnp.maximum(shape - 2, 0))
    t = x - i0
    n1, n2 = table.shape[2], table.shape[3]
    flat = table.reshape(-1, table.shape[-1])
    base = ((cls * table.shape[1] + i0[:, 0]) * n1 + i0[:, 1]) * n2 + i0[:, 2]
    out = jnp.zeros((coords.shape[0], table.shape[-1]), table.dtype)
    for corner in range(8):
        bits = [(corner >> axis) & 1 for axis in range(3)]
        weight = jnp.ones(coords.shape[0], table.dtype)
        for axis, bit in enumerate(bits):
            weight = weight * (t[:, axis] if bit else 1.0 - t[:, axis])
        out = out + weight[:, None] * jnp.take(flat, base + (bits[0] * n1 + bits[1]) * n2 + bits[2], axis=0)
    return out


def covariance_matrices(cov6: np.ndarray) -> np.ndarray:
    """(n, 3, 3) symmetric matrices from (n, 6) [xx, yy, zz, xy, xz, yz]."""
    xx, yy, zz, xy, xz, yz = np.moveaxis(np.asarray(cov6, dtype=np.float64), -1, 0)
    return np.stack([np.stack([xx, xy, xz], -1), np.stack([xy, yy, yz], -1), np.stack([xz, yz, zz], -1)], -2)


def perturbed_rig(rig: Rig, theta: np.ndarray) -> Rig:
    """The rig moved by an error `theta` (14,) of the shared parameters (`SHARED_PARAMETERS`; the water level's
    entry is not used): both focal lengths scaled by (1 + eps) and the cameras moved eps further from the world
    origin, the right camera's pose retracted (`Pose.retract`), and both cameras moved with the world frame
    (`X -> exp(w) X + v`). The same model `shared_covariance_table` differentiates; for simulating calibration
    errors drawn from a covariance."""
    from .._geometry.pose import Pose

    theta = np.asarray(theta, dtype=np.float64)
    eps = theta[12]
    frame = np.asarray(so3_exp(theta[0:3]))
    cameras = []
    for cam, delta in ((rig.left, np.zeros(6)), (rig.right, theta[6:12])):
        R = np.asarray(cam.pose.R) @ np.asarray(so3_exp(delta[:3]))
        center = np.asarray(cam.pose.center) * (1.0 + eps) + delta[3:]
        R, center = R @ frame.T, frame @ center + theta[3:6]
        moved = Camera(float(cam.fx) * (1 + eps), float(cam.fy) * (1 + eps), float(cam.cx), float(cam.cy), cam.dist,
                       Pose.from_center(R, center), cam.image_size)
        cameras.append(moved)
    return Rig(cameras[0], cameras[1], rig.interface, rig.calibration)


def calibration_record(cov: np.ndarray) -> dict:
    """A rig's calibration record (`world_frame.frame_cov`, `world_frame.right_pose_cov`, `focal_std_rel`) holding
    the shared parameters' covariance `cov` (14, 14): what `shared_errors` reads back."""
    cov = np.asarray(cov, dtype=np.float64)
    return {"world_frame": {"frame_cov": cov[:6, :6].tolist(), "right_pose_cov": cov[6:12, 6:12].tolist()},
            "focal_std_rel": float(np.sqrt(cov[12, 12]))}
