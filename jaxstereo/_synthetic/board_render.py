"""Synthetic calibration photographs: a board at known poses in air, rendered through the camera model."""

from __future__ import annotations

import jax
import numpy as np

from .._calibration.boards import BoardSpec
from .._geometry.camera import Camera, undistort_normalized
from .._geometry.errors import JaxStereoError
from .._geometry.pose import Pose, so3_exp
from .._geometry.precision import float64

_undistorted = jax.jit(lambda camera, pixels: undistort_normalized(camera.pixels_to_normalized(pixels), camera.dist))


@float64
def render_board(
    camera: Camera, board: BoardSpec, board_to_world: Pose, supersample: int = 3, noise_dn: float = 1.0,
    seed: int = 0, background: float = 0.3,
) -> np.ndarray:
    """Render the board seen by `camera` (no water) as an 8-bit grey image (h, w).

    **Arguments:**

    - `camera`: the camera (its distortion is rendered too).
    - `board`: the board spec.
    - `board_to_world`: pose mapping board-frame points to world points (`x_w = R x_b + t`).
    - `supersample`: rays per pixel side (anti-aliasing; corners need it for sub-pixel accuracy).
    - `noise_dn`: sensor noise, 8-bit digital numbers; `seed` its random seed.
    - `background`: reflectance behind the board.
    """
    w, h = camera.image_size
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    texture = board.texture() if board.kind == "charuco" else None
    R_bw = np.asarray(board_to_world.R)
    t_bw = np.asarray(board_to_world.t)
    # Undistorted normalised coordinates at every pixel centre and one pixel beyond the image (h + 2, w + 2, 2):
    # a sub-pixel ray's are interpolated from them (exact without distortion, and the distortion is smooth).
    u, v = np.meshgrid(np.arange(-1.0, w + 1.0), np.arange(-1.0, h + 1.0))
    grid = np.asarray(_undistorted(camera, np.stack([u.ravel(), v.ravel()], axis=-1))).reshape(h + 2, w + 2, 2)
    gx, gy = np.ascontiguousarray(grid[..., 0]), np.ascontiguousarray(grid[..., 1])
    # In the board frame a ray is q + s * e, with e = (x, y, 1) @ M for undistorted normalised (x, y).
    M = np.asarray(camera.pose.R) @ R_bw
    q = (np.asarray(camera.center) - t_bw) @ R_bw
    out = np.zeros((h, w))
    rows_per_chunk = max(1, 200_000 // w)
    for r0 in range(0, h, rows_per_chunk):
        m = min(h, r0 + rows_per_chunk) - r0
        for oy in offsets:
            i, fy = r0 + 1 + int(np.floor(oy)), oy - np.floor(oy)
            for ox in offsets:
                j, fx = 1 + int(np.floor(ox)), ox - np.floor(ox)
                x, y = (((1 - fx) * g[i:i + m, j:j + w] + fx * g[i:i + m, j + 1:j + 1 + w]) * (1 - fy)
                        + ((1 - fx) * g[i + 1:i + 1 + m, j:j + w] + fx * g[i + 1:i + 1 + m, j + 1:j + 1 + w]) * fy
                        for g in (gx, gy))
                with np.errstate(divide="ignore", invalid="ignore"):
                    s = -q[2] / (x * M[0, 2] + y * M[1, 2] + M[2, 2])
                    xb = np.stack([q[0] + s * (x * M[0, 0] + y * M[1, 0] + M[2, 0]),
                                   q[1] + s * (x * M[0, 1] + y * M[1, 1] + M[2, 1])], axis=-1)
                value = board.reflectance(xb, texture)
                out[r0:r0 + m] += np.where(np.isfinite(value) & (s > 0), value, background)
    out /= supersample**2
    srgb = out ** (1 / 2.2) * 255.0
    if noise_dn > 0:
        srgb = srgb + np.random.default_rng(seed).normal(0.0, noise_dn, srgb.shape)
    return np.clip(np.round(srgb), 0, 255).astype(np.uint8)


def board_poses(
    cameras: tuple[Camera, ...], board: BoardSpec, n: int, seed: int = 0, distance_m: tuple[float, float] = (1.2, 2.1),
    max_tilt_deg: float = 35.0, margin_px: float = 15.0,
) -> list[Pose]:
    """Random board poses (board -> world) in front of all `cameras`, the whole board inside every image.

    Boards face the cameras, tilted up to `max_tilt_deg` about a random axis, at distances from the
    first camera in `distance_m` along directions within its field of view.
    """
    rng = np.random.default_rng(seed)
    corners = board.corners
    centre_b = corners.mean(axis=0)
    cam0 = cameras[0]
    R0 = np.asarray(cam0.pose.R)
    w, h = cam0.image_size
    poses = []
    tries = 0
    while len(poses) < n:
        tries += 1
        if tries > 200 * n:
            raise JaxStereoError(f"could not place {n} views of {board} inside every image; use a smaller board")
        # A viewing direction in camera 0 and a distance along it.
        px = rng.uniform([0.2 * w, 0.2 * h], [0.8 * w, 0.8 * h])
        ray_c = np.array([(px[0] - float(cam0.cx)) / float(cam0.fx), (px[1] - float(cam0.cy)) / float(cam0.fy), 1.0])
        target = np.asarray(cam0.center) + rng.uniform(*distance_m) * (R0.T @ ray_c) / np.linalg.norm(ray_c)
        # Board facing camera 0: board z axis towards the camera, then a random tilt and in-plane spin.
        axis = rng.normal(size=3)
        axis -= axis @ (R0.T @ [0, 0, 1.0]) * (R0.T @ [0, 0, 1.0])
        axis /= np.linalg.norm(axis)
        tilt = np.asarray(so3_exp(np.deg2rad(rng.uniform(10.0, max_tilt_deg)) * axis))
        spin = np.asarray(so3_exp(np.array([0.0, 0.0, np.deg2rad(rng.uniform(-25, 25))])))
        face = R0.T  # board axes along camera 0's: printed side (board -z) towards it, not mirrored
        R_bw = tilt @ face @ spin
        t_bw = target - R_bw @ centre_b
        pose = Pose(R_bw, t_bw)
        x0, x1, y0, y1 = board.outline
        outline = np.array([[x0, y0, 0.0], [x1, y0, 0.0], [x0, y1, 0.0], [x1, y1, 0.0]])
        world = np.concatenate([corners, outline]) @ R_bw.T + t_bw
        ok = True
        for cam in cameras:
            pc = np.asarray(cam.pose.apply(world))
            if np.any(pc[:, 2] <= 0):
                ok = False
                break
            proj = np.asarray(cam.project(world))
            cw, ch = cam.image_size
            if np.any(proj < margin_px) or np.any(proj[:, 0] > cw - 1 - margin_px) or np.any(
                proj[:, 1] > ch - 1 - margin_px
            ):
                ok = False
                break
            # The board's printed side (its -z side) must face this camera.
            if (np.asarray(cam.center) - target) @ R_bw[:, 2] >= 0:
                ok = False
                break
        if ok:
            poses.append(pose)
    return poses
