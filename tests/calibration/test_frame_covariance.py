"""The world frame's covariance against the spread of the frame itself, refitted (scipy, OpenCV's projection) to
corners with independent noise and a smooth error shared by each image's corners."""

import cv2
import numpy as np
from scipy.optimize import least_squares

import jaxstereo as js
from jaxstereo._calibration.calibration import _frame_residuals
from jaxstereo._calibration.pose_covariance import covariance_with_smooth_errors

NOISE_PX = 0.02
SMOOTH_PX = 0.01


def _rig():
    """Two nadir cameras 2 m over a 9x6 board of 40 mm squares on the floor, 0.2 m apart, turned slightly."""
    cameras = []
    for x, turn in ((-0.1, (0.004, -0.003, 0.01)), (0.1, (-0.002, 0.005, -0.007))):
        pose = js.Pose.look_at([0.16 + x, 0.1, 2.0], [0.16, 0.1, 0.0])
        R = cv2.Rodrigues(np.asarray(turn))[0] @ np.asarray(pose.R)
        cameras.append(js.Camera(2600.0, 2600.0, 863.5, 575.5, np.zeros(5),
                                 js.Pose.from_center(R, np.asarray(pose.center)), (1728, 1152)))
    corners = np.array([[0.04 * i, 0.04 * j, 0.0] for j in range(6) for i in range(9)])
    return cameras, corners


def _project(camera, points):
    rvec = cv2.Rodrigues(np.asarray(camera.pose.R))[0]
    return cv2.projectPoints(points, rvec, np.asarray(camera.pose.t), np.asarray(camera.K), None)[0].reshape(-1, 2)


def _refit(cameras, corners, seen):
    """The frame move (w, v) that best reprojects the corners onto `seen` (2n, 2): scipy on OpenCV's projection."""
    def residuals(p):
        moved = corners + np.cross(p[:3], corners) + p[3:]
        return (np.concatenate([_project(c, moved) for c in cameras]) - seen).ravel()

    return least_squares(residuals, np.zeros(6), x_scale=1e-3, xtol=1e-12, ftol=1e-12).x


def _smooth_errors(rng, pixels, smooth_px):
    """An offset and gradients in u and v over one image's corners, `smooth_px` RMS per axis on average."""
    centred = pixels - pixels.mean(axis=0)
    terms = np.column_stack([np.ones(len(pixels)), centred / np.sqrt(np.mean(centred**2, axis=0))])
    return terms @ rng.normal(0.0, smooth_px / np.sqrt(3.0), (3, 2))


def test_frame_covariance_covers_noise_and_smooth_corner_errors():
    """Over 300 sets of corners, the refitted frame's tilt and height spread as the covariance says (within the
    sampling error of 300 variances, 8 %), and the covariance with independent noise alone falls short (its tilt
    variances by more than 1.7 times)."""
    rng = np.random.default_rng(5)
    cameras, corners = _rig()
    exact = [_project(c, corners) for c in cameras]
    image = np.repeat([0, 1], len(corners))
    moves, predicted, noise_only = [], [], []
    for _ in range(300):
        seen = np.concatenate([p + rng.normal(0.0, NOISE_PX, p.shape) + _smooth_errors(rng, p, SMOOTH_PX)
                               for p in exact])
        moves.append(_refit(cameras, corners, seen))
    args = (*cameras, np.asarray(corners), np.asarray(corners))
    seen = np.concatenate(exact) + rng.normal(0.0, NOISE_PX, (2 * len(corners), 2))
    for smooth, out in ((SMOOTH_PX, predicted), (0.0, noise_only)):
        cov, noise = covariance_with_smooth_errors(_frame_residuals, 6, seen, image, smooth, *args, seen)
        out.append(cov)
        assert abs(noise / NOISE_PX - 1) < 0.15
    spread = np.var(np.asarray(moves), axis=0)
    for k in (0, 1, 5):  # the tilt about x and y, the height at the origin
        ratio = spread[k] / predicted[0][k, k]
        print(f"parameter {k}: spread / covariance {ratio:.2f}, with noise alone {spread[k] / noise_only[0][k, k]:.2f}")
        assert 0.75 < ratio < 1.33
    assert all(spread[k] / noise_only[0][k, k] > 1.7 for k in (0, 1))
