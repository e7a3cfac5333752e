import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from scipy.spatial.transform import Rotation

import jaxstereo as js

# Kernel tests: they jit, differentiate and do float64 arithmetic on JAX arrays themselves.
pytestmark = pytest.mark.usefixtures("x64")

def _rotvec(R):
    u, _, vt = np.linalg.svd(R)  # nearest rotation, as scipy wants one
    return Rotation.from_matrix(u @ vt).as_rotvec()


vec3 = st.lists(st.floats(-3.0, 3.0, allow_nan=False), min_size=3, max_size=3)


@settings(max_examples=60, deadline=None)
@given(vec3)
def test_so3_exp_matches_opencv_rodrigues(rvec):
    expected, _ = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64))
    np.testing.assert_allclose(js.so3_exp(jnp.asarray(rvec)), expected, atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(vec3)
def test_so3_log_inverts_exp(rvec):
    rvec = np.asarray(rvec)
    if np.linalg.norm(rvec) >= np.pi - 1e-3:
        rvec = rvec / np.linalg.norm(rvec) * (np.pi - 1e-2)
    np.testing.assert_allclose(js.so3_log(js.so3_exp(jnp.asarray(rvec))), rvec, atol=1e-9)


def test_so3_log_near_pi_matches_opencv():
    rvec = np.array([0.3, -0.5, 0.8])
    rvec = rvec / np.linalg.norm(rvec) * (np.pi - 1e-7)
    R, _ = cv2.Rodrigues(rvec)
    back = np.asarray(js.so3_log(jnp.asarray(R)))
    R_back, _ = cv2.Rodrigues(back)
    np.testing.assert_allclose(R_back, R, atol=1e-6)


@pytest.mark.parametrize("rvec", [np.zeros(3), np.array([1e-9, -2e-9, 0.5e-9]), np.array([0.3, -0.2, 0.1])])
def test_so3_log_jacobian_is_finite_and_matches_finite_differences(rvec):
    # log(exp(r)) = r: its Jacobian is the identity, at the identity rotation too (arccos'(1) is infinite).
    J = jax.jacfwd(lambda r: js.so3_log(js.so3_exp(r)))(jnp.asarray(rvec))
    np.testing.assert_allclose(J, np.eye(3), atol=1e-7)
    # With respect to R itself, against central differences of an independent reference (scipy's rotvec;
    # cv2.Rodrigues rounds angles below 1e-5 rad to zero).
    R0 = np.asarray(js.so3_exp(jnp.asarray(rvec)))
    G = np.asarray(jax.jacrev(js.so3_log)(jnp.asarray(R0)))
    assert np.all(np.isfinite(G))
    E = np.zeros((3, 3)); E[1, 0], E[0, 1] = 1.0, -1.0  # a tangent direction (skew), keeps R a rotation to 1st order
    h = 1e-6
    numeric = (_rotvec(R0 + h * E @ R0) - _rotvec(R0 - h * E @ R0)) / (2 * h)
    np.testing.assert_allclose(np.einsum("kij,ij->k", G, E @ R0), numeric, atol=1e-6)


def test_so3_exp_gradient_at_zero_is_finite_and_right():
    # d/drvec of R @ v at rvec = 0 is -skew(v).
    v = jnp.array([0.2, -0.7, 1.1])
    J = jax.jacfwd(lambda r: js.so3_exp(r) @ v)(jnp.zeros(3))
    expected = -np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    np.testing.assert_allclose(J, expected, atol=1e-12)


def test_pose_center_inverse_and_retract(rng):
    pose = js.Pose.from_rvec(rng.normal(size=3), rng.normal(size=3))
    X = jnp.asarray(rng.normal(size=(10, 3)))
    np.testing.assert_allclose(pose.inverse_apply(pose.apply(X)), X, atol=1e-12)
    np.testing.assert_allclose(pose.apply(pose.center[None])[0], 0.0, atol=1e-12)
    np.testing.assert_allclose(pose.compose(pose.inverse()).R, np.eye(3), atol=1e-12)
    moved = pose.retract(jnp.array([0.0, 0.0, 0.0, 0.1, -0.2, 0.3]))
    np.testing.assert_allclose(moved.center - pose.center, [0.1, -0.2, 0.3], atol=1e-12)
    np.testing.assert_allclose(moved.R, pose.R, atol=1e-12)


def test_look_at_points_the_optical_axis_at_the_target():
    pose = js.Pose.look_at([0.5, -0.2, 2.0], [0.1, 0.3, 0.0])
    target_cam = pose.apply(jnp.array([0.1, 0.3, 0.0]))
    np.testing.assert_allclose(target_cam[:2], 0.0, atol=1e-12)
    assert target_cam[2] > 0
    nadir = js.Pose.look_at([0.0, 0.0, 2.0], [0.0, 0.0, 0.0])
    # Nadir: image x along world X, image y along world -Y (right-handed, camera z down).
    np.testing.assert_allclose(nadir.R, np.diag([1.0, -1.0, -1.0]), atol=1e-12)


def test_bad_pose_input_names_the_parameter():
    with pytest.raises(js.JaxStereoError, match="rotation matrix"):
        js.Pose(jnp.eye(3) * 2.0, jnp.zeros(3))
    with pytest.raises(js.JaxStereoError, match="pose t"):
        js.Pose(jnp.eye(3), jnp.zeros(2))
