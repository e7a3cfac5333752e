"""How well a stereo calibration fixes the right camera's pose relative to the left: its covariance.

`jaxstereo refine` may free the right camera's pose, and on rough scenes a tiny move of it (a few
thousandths of a degree) trades against millimetres of water level. The calibration already knows the
pose to about that precision; this covariance, recorded in the rig, lets `refine` hold the pose to it
(a robust prior: a real move of the camera still comes through). The world frame's covariance from the
origin board (`calibration._frame_covariance`) uses `covariance_with_smooth_errors` from here.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from .._geometry.camera import Camera
from .._geometry.pose import Pose, so3_exp
from .._geometry.precision import float64


@float64
def right_pose_covariance(K_left, dist_left, K_right, dist_right, R, T, image_size, objects, pixels_left,
                          pixels_right, board_rvecs, board_tvecs) -> np.ndarray:
    """Covariance (6, 6) of the right camera's pose in the left camera's frame, as `Pose.retract` moves it
    (rotation vector acting on the left frame's axes, radians; centre shift in the left frame, metres).

    Least squares over the right pose and every board pose together, from the corners of each pair in both
    images (`objects[k]` (n, 3) board metres, `pixels_left[k]`, `pixels_right[k]` (n, 2)), intrinsics held;
    the pixel noise is estimated from the residuals. The board poses' own uncertainty is marginalised out.

    **Arguments:** OpenCV's intrinsics and distortion of both cameras; `R` (3, 3), `T` (3,) with
    `x_right = R x_left + T`; `image_size` (w, h); `board_rvecs`, `board_tvecs` the boards' poses in the left
    camera frame (Rodrigues vectors, metres).
    """
    left = Camera(K_left[0, 0], K_left[1, 1], K_left[0, 2], K_left[1, 2], np.ravel(dist_left)[:8],
                  Pose(np.eye(3), np.zeros(3)), image_size)
    right0 = Camera(K_right[0, 0], K_right[1, 1], K_right[0, 2], K_right[1, 2], np.ravel(dist_right)[:8],
                    Pose(np.asarray(R, float), np.ravel(T).astype(float)), image_size)
    # Every pair's corners in one array, each with its board's index: one compiled residual for the whole set,
    # whatever the number of boards and of corners on each.
    counts = [len(o) for o in objects]
    board = jnp.asarray(np.repeat(np.arange(len(counts)), counts))
    corners = jnp.asarray(np.concatenate(objects).astype(float))
    R0 = jnp.stack([Pose.from_rvec(np.ravel(rv), np.ravel(tv)).R for rv, tv in zip(board_rvecs, board_tvecs)])
    t0 = jnp.asarray(np.stack([np.ravel(tv) for tv in board_tvecs]).astype(float))
    seen = jnp.asarray(np.concatenate([np.concatenate(pixels_left), np.concatenate(pixels_right)]).astype(float))

    cov, _ = covariance_from_residuals(_pose_residuals, 6 + 6 * len(counts), left, right0, R0, t0, board, corners,
                                       seen)
    return cov[:6, :6]


def _pose_residuals(p, left, right0, R0, t0, board, corners, seen):
    """Reprojection residuals (pixels) of every board corner in both images, the right pose moved by `p[:6]` and
    board k's by `p[6 + 6k : 12 + 6k]` (rotation in its own frame, shift)."""
    right = right0.with_pose(right0.pose.retract(p[:6]))
    q = p[6:].reshape(-1, 6)
    R = R0 @ jax.vmap(so3_exp)(q[:, :3])
    points = jnp.einsum("nij,nj->ni", R[board], corners) + (t0 + q[:, 3:])[board]
    return (jnp.concatenate([left.project(points), right.project(points)]) - seen).ravel()


def covariance_from_residuals(residuals, n_params: int, *args) -> tuple[np.ndarray, float]:
    """Gauss-Newton covariance (n_params, n_params) of small parameters about zero, `residuals(p, *args)` in
    pixels, with the pixel noise estimated from the residuals at zero (n - n_params degrees of freedom).

    `residuals` and its Jacobian are compiled once per function and shapes of `args` (pass the data as `args`
    and keep `residuals` a module-level function: a closure would compile anew at every call; run eagerly,
    every operation would compile on its own for each new shape).

    **Returns:** `(cov, noise_px)`; `cov` is all inf when the parameters are not determined.
    """
    J, noise = _jacobian_and_noise(residuals, n_params, args)
    try:
        cov = noise**2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return np.full((n_params, n_params), np.inf), noise
    return (cov if np.all(np.isfinite(cov)) else np.full((n_params, n_params), np.inf)), noise


def _jacobian_and_noise(residuals, n_params: int, args) -> tuple[np.ndarray, float]:
    """The Jacobian (m, n_params) of `residuals(p, *args)` at `p = 0` and the pixel noise its residuals there
    give (m - n_params degrees of freedom)."""
    value, jacobian = _compiled(residuals)
    p0 = jnp.zeros(n_params)
    r0 = np.asarray(value(p0, *args))
    noise = float(np.sqrt(float(r0 @ r0) / max(r0.size - n_params, 1)))
    return np.asarray(jacobian(p0, *args)), noise


@float64
def covariance_with_smooth_errors(residuals, n_params: int, pixels: np.ndarray, image: np.ndarray,
                                  smooth_px: float, *args) -> tuple[np.ndarray, float]:
    """`covariance_from_residuals` for corners whose errors are not all independent: each image's corners also
    share a smooth error, an offset and a gradient across the corners in u and in v, of `smooth_px` RMS over
    them per axis (pixels). Such an error barely shows in the residuals (the parameters take most of it up) but
    moves the parameters: on one board, a gradient of a hundredth of a pixel across it tilts the board's plane
    as much as the independent noise of all its corners does.

    **Arguments:** `residuals(p, *args)` of layout (n, 2) raveled, as `covariance_from_residuals`; `pixels`
    (n, 2) the corners (pixels); `image` (n,) which image each corner was seen in (any integer labels).
    **Returns:** `(cov, noise_px)`; `cov` all inf when the parameters are not determined.
    """
    J, noise = _jacobian_and_noise(residuals, n_params, args)
    try:
        inverse = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return np.full((n_params, n_params), np.inf), noise
    # The smooth errors' basis: per image and axis, an offset and the corners' centred, scaled u and v
    # (each of unit RMS over the image's corners), each of variance smooth_px^2 / 3.
    pixels = np.asarray(pixels, dtype=np.float64)
    labels = np.unique(image)
    basis = np.zeros((2 * len(pixels), 6 * len(labels)))
    for k, label in enumerate(labels):
        rows = np.flatnonzero(image == label)
        centred = pixels[rows] - pixels[rows].mean(axis=0)
        spread = np.maximum(np.sqrt(np.mean(centred**2, axis=0)), 1e-9)
        terms = np.column_stack([np.ones(len(rows)), centred / spread])
        for axis in range(2):
            basis[2 * rows + axis, 6 * k + 3 * axis: 6 * k + 3 * axis + 3] = terms
    gain = inverse @ J.T @ basis  # parameters per unit coefficient of the smooth errors
    cov = noise**2 * inverse + (smooth_px**2 / 3.0) * gain @ gain.T
    return (cov if np.all(np.isfinite(cov)) else np.full((n_params, n_params), np.inf)), noise


@functools.cache
def _compiled(residuals):
    """`residuals` and its Jacobian with respect to its first argument, compiled."""
    return jax.jit(residuals), jax.jit(jax.jacfwd(residuals))
