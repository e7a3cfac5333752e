import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxstereo as js

# Kernel tests: they jit, differentiate and do float64 arithmetic on JAX arrays themselves.
pytestmark = pytest.mark.usefixtures("x64")


def _random_opencv_camera(rng, n_dist):
    K = np.array([[rng.uniform(400, 4000), 0, rng.uniform(300, 1300)], [0, 0, rng.uniform(200, 900)], [0, 0, 1.0]])
    K[1, 1] = K[0, 0] * rng.uniform(0.95, 1.05)
    dist = np.concatenate([
        [rng.uniform(-0.3, 0.3), rng.uniform(-0.1, 0.1), rng.uniform(-3e-3, 3e-3), rng.uniform(-3e-3, 3e-3),
         rng.uniform(-0.05, 0.05)],
        rng.uniform(-0.05, 0.05, n_dist - 5),
    ])
    rvec = rng.normal(scale=0.5, size=3)
    tvec = rng.normal(scale=0.5, size=3)
    return K, dist, rvec, tvec


@pytest.mark.parametrize("n_dist", [5, 8])
def test_project_matches_cv2_projectPoints(rng, n_dist):
    for _ in range(20):
        K, dist, rvec, tvec = _random_opencv_camera(rng, n_dist)
        camera = js.Camera.from_opencv(K, dist, rvec, tvec, (1280, 960))
        # Points in front of the camera within a ~45 degree cone.
        pc = np.column_stack([rng.uniform(-0.6, 0.6, 500), rng.uniform(-0.6, 0.6, 500), np.ones(500)])
        pc *= rng.uniform(0.5, 5.0, (500, 1))
        pose = camera.pose
        X = np.asarray(pose.inverse_apply(jnp.asarray(pc)))
        expected, _ = cv2.projectPoints(X, rvec, tvec, K, dist)
        got = camera.project(jnp.asarray(X))
        np.testing.assert_allclose(got, expected[:, 0, :], atol=1e-6, rtol=0)


@pytest.mark.parametrize("n_dist", [5, 8])
def test_backproject_inverts_project(rng, n_dist):
    for _ in range(20):
        K, dist, rvec, tvec = _random_opencv_camera(rng, n_dist)
        camera = js.Camera.from_opencv(K, dist, rvec, tvec, (1280, 960))
        xy = rng.uniform(-0.6, 0.6, (500, 2))
        pc = np.column_stack([xy, np.ones(500)]) * rng.uniform(0.5, 5.0, (500, 1))
        X = camera.pose.inverse_apply(jnp.asarray(pc))
        pixels = camera.project(X)
        origin, direction = camera.backproject(pixels)
        to_point = X - origin
        to_point = to_point / jnp.linalg.norm(to_point, axis=-1, keepdims=True)
        np.testing.assert_allclose(direction, to_point, atol=1e-9, rtol=0)
        # And pixel -> ray -> pixel.
        again = camera.project(origin + 2.0 * direction)
        np.testing.assert_allclose(again, pixels, atol=1e-9, rtol=0)


def test_undistort_matches_opencv(rng):
    K, dist, rvec, tvec = _random_opencv_camera(rng, 5)
    camera = js.Camera.from_opencv(K, dist, rvec, tvec, (1280, 960))
    pixels = rng.uniform([0, 0], [1280, 960], (300, 2))
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)
    if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4; OpenCV 5 folded it into undistortPoints
        ref = cv2.undistortPointsIter(pixels[:, None, :], K, dist, None, K, criteria)[:, 0, :]
    else:
        ref = cv2.undistortPoints(pixels[:, None, :], K, dist, None, None, K, criteria)[:, 0, :]
    got = camera.undistort_pixels(jnp.asarray(pixels))
    np.testing.assert_allclose(got, ref, atol=1e-6, rtol=0)
    np.testing.assert_allclose(camera.distort_pixels(got), pixels, atol=1e-9, rtol=0)


def test_project_is_jittable_and_vmappable(rng):
    K, dist, rvec, tvec = _random_opencv_camera(rng, 5)
    camera = js.Camera.from_opencv(K, dist, rvec, tvec, (1280, 960))
    X = camera.pose.inverse_apply(jnp.asarray(rng.uniform([-1, -1, 2], [1, 1, 3], (50, 3))))
    direct = camera.project(X)
    jitted = jax.jit(lambda c, x: c.project(x))(camera, X)
    mapped = jax.vmap(camera.project)(X[:, None, :])[:, 0, :]
    np.testing.assert_allclose(jitted, direct, atol=1e-10)
    np.testing.assert_allclose(mapped, direct, atol=1e-10)


def test_bad_camera_input_names_the_parameter():
    pose = js.Pose.from_rvec(np.zeros(3), np.zeros(3))
    with pytest.raises(js.JaxStereoError, match="fx"):
        js.Camera(-10.0, 10.0, 5.0, 5.0, np.zeros(5), pose, (10, 10))
    with pytest.raises(js.JaxStereoError, match="dist has 14"):
        js.Camera(10.0, 10.0, 5.0, 5.0, np.zeros(14), pose, (10, 10))
    with pytest.raises(js.JaxStereoError, match="image_size"):
        js.Camera(10.0, 10.0, 5.0, 5.0, np.zeros(5), pose, (0, 10))
    with pytest.raises(js.JaxStereoError, match="dist contains NaN"):
        js.Camera(10.0, 10.0, 5.0, 5.0, [np.nan, 0, 0, 0, 0], pose, (10, 10))
