"""The geometry's PyTree base (`_geometry/module.py`): fields as leaves and static data, the checks, immutability,
and a survey's imports without equinox."""

import dataclasses
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxstereo as js
from jaxstereo._geometry.module import replaced


def _camera():
    K = np.array([[1500.0, 0.0, 863.5], [0.0, 1500.0, 575.5], [0.0, 0.0, 1.0]])
    return js.Camera.from_opencv(K, [-0.1, 0.05], [0.01, 3.1, -0.02], [0.1, -0.2, 1.9], (1728, 1152))


def test_a_camera_is_a_pytree_of_its_arrays_with_its_size_static():
    camera = _camera()
    leaves, tree = jax.tree_util.tree_flatten(camera)
    assert len(leaves) == 7  # fx fy cx cy dist R t
    rebuilt = jax.tree_util.tree_unflatten(tree, leaves)
    assert rebuilt == camera and rebuilt is not camera and rebuilt.image_size == (1728, 1152)
    paths = [jax.tree_util.keystr(path) for path, _ in jax.tree_util.tree_flatten_with_path(camera)[0]]
    assert paths[0] == ".fx" and paths[-1] == ".pose.t"
    # Another image size is another tree structure: a compiled function is not reused for it.
    other = js.Camera(camera.fx, camera.fy, camera.cx, camera.cy, camera.dist, camera.pose, (864, 576))
    assert jax.tree_util.tree_structure(other) != tree


def test_a_camera_passes_through_jit_and_grad_with_the_analytic_derivative():
    camera = _camera()
    point = jnp.array([0.05, -0.1, 0.2])

    def u_of_fx(fx):
        return js.Camera(fx, camera.fy, camera.cx, camera.cy, camera.dist, camera.pose, camera.image_size).project(
            point)[0]

    with jax.enable_x64(True):
        jitted = jax.jit(lambda cam, p: cam.project(p))(camera, point)
        gradient = float(jax.grad(u_of_fx)(camera.fx))
    np.testing.assert_allclose(np.asarray(jitted), np.asarray(camera.project(point)), rtol=0, atol=1e-9)
    # u = fx * x'' + cx: du/dfx is the distorted normalised coordinate x'' = (u - cx) / fx
    u = float(camera.project(point)[0])
    assert gradient == pytest.approx((u - float(camera.cx)) / float(camera.fx), rel=1e-12)


def test_fields_are_frozen_and_converted_and_checked_once_made():
    camera = _camera()
    with pytest.raises(dataclasses.FrozenInstanceError):
        camera.fx = 1.0
    pose = js.Pose(np.eye(3, dtype=np.float32), [0, 0, 1])  # the converter: float64 arrays
    assert pose.R.dtype == np.float64 and pose.t.dtype == np.float64
    with pytest.raises(js.JaxStereoError, match="not a rotation"):
        js.Pose(2.0 * np.eye(3), np.zeros(3))
    with pytest.raises(js.JaxStereoError, match="unit vector"):
        js.Interface(0.1, normal=(0.0, 0.0, 2.0))


def test_a_copy_with_new_values_and_equality_by_value():
    interface = js.Interface(0.2)
    higher = interface.with_level(0.25)
    assert float(higher.level) == 0.25 and float(interface.level) == 0.2
    assert higher != interface and js.Interface(0.25) == higher
    moved = replaced(_camera(), image_size=(10, 10))
    assert moved.image_size == (10, 10) and moved.fx == _camera().fx
    with pytest.raises(TypeError, match="no field"):
        replaced(interface, height=1.0)
    with pytest.raises(TypeError):
        hash(interface)


def test_a_survey_imports_no_equinox():
    code = ("import sys\nimport jaxstereo._stereo.reconstruct, jaxstereo._calibration.rig\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] == 'equinox'))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "[]"
