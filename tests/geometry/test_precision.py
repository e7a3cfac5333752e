"""The float64 policy seen from a user's session with JAX's default settings (64-bit types disabled)."""

import subprocess
import sys

import jax
import numpy as np
import pytest
from helpers import random_refraction_case

import jaxstereo as js


def _case():
    rng = np.random.default_rng(7)
    return random_refraction_case(rng, max_incidence_deg=40.0, n=200)


def test_the_suite_runs_with_jax_defaults():
    assert not jax.config.jax_enable_x64


def test_geometry_is_float64_by_construction():
    K = np.array([[1500.0, 0.0, 863.5], [0.0, 1500.0, 575.5], [0.0, 0.0, 1.0]])
    camera = js.Camera.from_opencv(K, [-0.1, 0.05], [3.1, 0.01, -0.02], [0.1, -0.2, 1.9], (1728, 1152))
    for value in (camera.fx, camera.cx, camera.dist, camera.pose.R, camera.pose.t):
        assert value.dtype == np.float64
    interface = js.Interface(0.2)
    assert interface.level.dtype == np.float64 and interface.normal.dtype == np.float64


def test_projection_without_x64_equals_projection_with_x64():
    camera, interface, points, _ = _case()
    points = np.asarray(points)
    pixels, valid = js.project_refracted(camera, interface, points)
    assert pixels.dtype == np.float64
    with jax.enable_x64(True):
        reference, _ = js.project_refracted(camera, interface, points)
    np.testing.assert_array_equal(np.asarray(pixels), np.asarray(reference))
    assert bool(np.all(np.asarray(valid)))
    # float32 inputs are promoted, not computed in float32.
    pixels32, _ = js.project_refracted(camera, interface, points.astype(np.float32))
    assert pixels32.dtype == np.float64
    exact32, _ = (lambda p: js.project_refracted(camera, interface, p))(points.astype(np.float32).astype(np.float64))
    np.testing.assert_array_equal(np.asarray(pixels32), np.asarray(exact32))


def test_tracing_in_float32_is_refused_with_a_clear_error():
    camera, interface, points, _ = _case()
    with pytest.raises(js.JaxStereoError, match="64-bit types disabled.*jax.enable_x64"):
        jax.jit(lambda p: js.project_refracted(camera, interface, p)[0])(np.asarray(points))
    with pytest.raises(js.JaxStereoError, match="so3_exp"):
        jax.grad(lambda r: js.so3_exp(r).sum())(np.zeros(3))
    # Inside 64-bit mode the same transformations run.
    with jax.enable_x64(True):
        g = jax.grad(lambda r: js.so3_exp(r)[0, 1])(np.zeros(3))
    np.testing.assert_allclose(np.asarray(g), [0.0, 0.0, -1.0], atol=1e-15)


def test_import_changes_no_global_state():
    # rcParams read raw: matplotlib resolves (and imports pyplot for) the "backend" entry on access.
    code = (
        "import sys, jax, matplotlib\n"
        "raw = lambda: {k: dict.__getitem__(matplotlib.rcParams, k) for k in matplotlib.rcParams}\n"
        "before = (jax.config.jax_enable_x64, raw())\n"
        "import jaxstereo, jaxstereo._app.cli\n"
        "after = (jax.config.jax_enable_x64, raw())\n"
        "assert before == after, [k for k in before[1] if before[1][k] != after[1].get(k)]\n"
        "assert 'matplotlib.pyplot' not in sys.modules, 'pyplot imported'\n"
        "print('ok')\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and proc.stdout.strip() == "ok", proc.stderr


def test_the_suite_checks_annotations():
    # conftest.py installs jaxtyping's import hook with beartype: a wrong shape is stopped at the call.
    from jaxtyping import TypeCheckError

    camera, interface, points, _ = _case()
    with pytest.raises(TypeCheckError, match="points_world"):
        js.project_refracted(camera, interface, np.asarray(points)[:, :2])


def test_without_the_checker_the_library_names_the_parameter(unchecked):
    camera, interface, points, _ = _case()
    with pytest.raises(js.JaxStereoError, match="points_world must have shape"):
        js.project_refracted(camera, interface, np.asarray(points)[:, :2])
