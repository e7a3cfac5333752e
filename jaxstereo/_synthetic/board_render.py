"""Synthetic calibration photographs: a board at known poses in air, rendered through the camera model."""

from __future__ import annotations

import jax
import numpy as np

from .._calibration.boards import BoardSpec
from .._geometry.camera import Camera
from .._geometry.errors import JaxStereoError
from .._geometry.pose import Pose, so3_exp
from .._geometry.precision import float64

_backproject = jax.jit(lambda camera, pixels: camera.backproject(pixels))


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
    normal_w = R_bw[:, 2]
    origin_plane = t_bw
    out = np.empty((h, w))
    rows_per_chunk = max(1, 200_000 // (w * supersample * supersample))
    ox, oy = np.meshgrid(offsets, offsets)
    sub = np.stack([ox.ravel(), oy.ravel()], axis=-1)
    for r0 in range(0, h, rows_per_chunk):
        r1 = min(h, r0 + rows_per_chunk)
        u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(r0, r1, dtype=np.float64))
        pix = np.stack([u.ravel(), v.ravel()], axis=-1)[:, None, :] + sub[None]
        pix = pix.reshape(-1, 2)
        if pix.shape[0] < rows_per_chunk * w * supersample**2:  # keep one compiled shape
            pix = np.concatenate([pix, np.zeros((rows_per_chunk * w * supersample**2 - pix.shape[0], 2))])
        o, d = (np.asarray(a) for a in _backproject(camera, pix))
        n = (r1 - r0) * w * supersample**2
        o, d = o[:n], d[:n]
        denom = d @ normal_w
        s = ((origin_plane - o) @ normal_w) / np.where(denom == 0, np.nan, denom)
        p = o + s[:, None] * d
        xb = (p - t_bw) @ R_bw  # board frame
        value = board.reflectance(xb[:, :2], texture)
        value = np.where(np.isfinite(value) & (s > 0), value, background)
        out[r0:r1] = value.reshape(r1 - r0, w, supersample**2).mean(axis=-1)
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
