import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import random_refraction_case

import jaxstereo as js

# Kernel tests: they jit, differentiate and do float64 arithmetic on JAX arrays themselves.
pytestmark = pytest.mark.usefixtures("x64")


def _snell_angles(d_in, d_out, normal):
    cos_in = abs(d_in @ normal)
    cos_out = abs(d_out @ normal)
    return np.sqrt(1 - cos_in**2), np.sqrt(1 - cos_out**2)


def test_refract_directions_obeys_snell_law(rng):
    normal = np.array([0.0, 0.0, 1.0])
    for theta in np.deg2rad([0.0, 10.0, 30.0, 60.0, 89.0]):
        d = np.array([np.sin(theta), 0.0, -np.cos(theta)])
        out, ok = js.refract_directions(jnp.asarray(d), jnp.asarray(normal), 1.0, 1.333)
        out = np.asarray(out)
        sin_in, sin_out = _snell_angles(d, out, normal)
        assert ok
        assert abs(1.0 * sin_in - 1.333 * sin_out) < 1e-14
        assert abs(np.linalg.norm(out) - 1) < 1e-14
        # Stays in the plane of incidence and keeps going down.
        assert abs(out[1]) < 1e-15 and out[2] < 0


def test_total_internal_reflection_is_reported_not_nan():
    # From water into air beyond the critical angle (48.6 deg for 1.333).
    normal = jnp.array([0.0, 0.0, 1.0])
    theta = np.deg2rad(np.array([30.0, 48.0, 49.0, 70.0]))
    d = jnp.asarray(np.column_stack([np.sin(theta), np.zeros(4), np.cos(theta)]))
    out, ok = js.refract_directions(d, normal, 1.333, 1.0)
    np.testing.assert_array_equal(ok, [True, True, False, False])
    assert np.all(np.isfinite(out))
    # The reflected direction mirrors the incident one.
    np.testing.assert_allclose(out[2:], d[2:] * jnp.array([1.0, 1.0, -1.0]), atol=1e-15)


def test_round_trip_returns_the_point(rng):
    worst = 0.0
    for _ in range(40):
        camera, interface, points, _ = random_refraction_case(rng, max_incidence_deg=45.0, max_tilt_deg=5.0)
        pixels, valid = js.project_refracted(camera, interface, points)
        assert bool(jnp.all(valid))
        origins, directions, ok = js.backproject_refracted(camera, interface, pixels)
        assert bool(jnp.all(ok))
        level = points @ interface.normal
        back, _ = js.intersect_plane(origins, directions, interface.normal, level)
        worst = max(worst, float(jnp.max(jnp.abs(back - points))))
    assert worst < 1e-9, worst


def test_refraction_point_matches_forward_traced_hit(rng):
    camera, interface, points, hit = random_refraction_case(rng, max_incidence_deg=45.0)
    found = js.refraction_points(camera.center, points, interface)
    np.testing.assert_allclose(found, hit, atol=1e-9, rtol=0)


def test_fermat_optical_path_is_stationary(rng):
    for _ in range(10):
        camera, interface, points, _ = random_refraction_case(rng, max_incidence_deg=45.0, max_tilt_deg=5.0)
        surface = js.refraction_points(camera.center, points, interface)
        grad = jax.vmap(jax.grad(js.optical_path_length, argnums=1), in_axes=(None, 0, 0, None))(
            camera.center, surface, points, interface
        )
        normal = interface.normal
        tangential = grad - (grad @ normal)[:, None] * normal
        assert float(jnp.max(jnp.abs(tangential))) < 1e-9
        # And it is a minimum: any in-plane move lengthens the optical path.
        e = jnp.cross(normal, jnp.array([1.0, 0.0, 0.0]))
        e = e / jnp.linalg.norm(e)
        base = js.optical_path_length(camera.center, surface, points, interface)
        moved = js.optical_path_length(camera.center, surface + 1e-4 * e, points, interface)
        assert bool(jnp.all(moved > base))


def test_points_in_air_project_as_pinhole(rng):
    camera, interface, points, _ = random_refraction_case(rng)
    above = points + (interface.level - points @ interface.normal + 0.1)[:, None] * interface.normal
    pixels, valid = js.project_refracted(camera, interface, above)
    np.testing.assert_allclose(pixels, camera.project(above), atol=1e-12)
    assert bool(jnp.all(valid))


def test_newton_converges_to_grazing_incidence(rng):
    # Incidence up to 85 degrees and extreme depth ratios still reach round-off.
    camera, interface, points, hit = random_refraction_case(rng, max_incidence_deg=85.0, n=2000)
    found = js.refraction_points(camera.center, points, interface)
    reference = js.refraction_points(camera.center, points, interface, iterations=60)
    np.testing.assert_allclose(found, reference, atol=1e-12, rtol=0)
    np.testing.assert_allclose(found, hit, atol=1e-8, rtol=0)


def test_an_unconverged_solve_is_flagged_invalid(rng):
    # Too few Newton steps at grazing incidence: `valid` says so, and whatever it keeps is right.
    camera, interface, points, hit = random_refraction_case(rng, max_incidence_deg=85.0, n=2000)
    _, valid = js.project_refracted(camera, interface, points, iterations=0)
    found = js.refraction_points(camera.center, points, interface, iterations=0)
    error = np.linalg.norm(np.asarray(found - hit), axis=-1)
    valid = np.asarray(valid)
    assert 0 < valid.sum() < valid.size
    assert error[valid].max() < 1e-8
    assert np.median(error[~valid]) > 1e-8
    _, valid_default = js.project_refracted(camera, interface, points)
    assert bool(jnp.all(valid_default))


def _central_difference(f, x, step):
    cols = []
    for i in range(x.size):
        e = np.zeros_like(x)
        e[i] = step
        cols.append((np.asarray(f(jnp.asarray(x + e))) - np.asarray(f(jnp.asarray(x - e)))) / (2 * step))
    return np.stack(cols, axis=-1)


def _check_gradient(f, x, step=1e-6, rtol=1e-5):
    x = np.asarray(x, dtype=np.float64)
    analytic = np.asarray(jax.jacfwd(f)(jnp.asarray(x))).reshape(-1, x.size)
    reverse = np.asarray(jax.jacrev(f)(jnp.asarray(x))).reshape(-1, x.size)
    numeric = _central_difference(f, x, step).reshape(-1, x.size)
    np.testing.assert_allclose(reverse, analytic, rtol=1e-10, atol=1e-10)
    for j in range(x.size):
        scale = np.linalg.norm(numeric[:, j])
        assert np.linalg.norm(analytic[:, j] - numeric[:, j]) <= rtol * max(scale, 1e-3), (j, analytic[:, j],
                                                                                          numeric[:, j])


def _gradient_case(rng):
    camera, interface, points, _ = random_refraction_case(rng, max_incidence_deg=40.0, max_tilt_deg=5.0, n=6)
    return camera, interface, points


def test_gradient_wrt_points(rng):
    camera, interface, points = _gradient_case(rng)
    _check_gradient(lambda x: js.project_refracted(camera, interface, x.reshape(-1, 3))[0], np.ravel(points))


def test_gradient_wrt_pose(rng):
    camera, interface, points = _gradient_case(rng)
    rvec0 = np.asarray(camera.pose.rvec)
    t0 = np.asarray(camera.pose.t)

    def f(p):
        cam = camera.with_pose(js.Pose.from_rvec(p[:3], p[3:]))
        return js.project_refracted(cam, interface, points)[0]

    _check_gradient(f, np.concatenate([rvec0, t0]))


def test_gradient_wrt_intrinsics_and_distortion(rng):
    camera, interface, points = _gradient_case(rng)

    def f(p):
        cam = js.Camera(p[0], p[1], p[2], p[3], p[4:9], camera.pose, camera.image_size)
        return js.project_refracted(cam, interface, points)[0]

    x = np.concatenate([[camera.fx, camera.fy, camera.cx, camera.cy], np.asarray(camera.dist[:5])])
    _check_gradient(f, x)


def test_gradient_wrt_interface_level_normal_and_index(rng):
    camera, interface, points = _gradient_case(rng)
    n = np.asarray(interface.normal)
    tilt_x, tilt_y = -np.arcsin(n[1]), np.arctan2(n[0], n[2])
    np.testing.assert_allclose(js.tilt_normal(tilt_x, tilt_y), n, atol=1e-12)

    def f(p):
        itf = js.Interface.from_tilt(p[0], p[1], p[2], n_water=p[3])
        return js.project_refracted(camera, itf, points)[0]

    _check_gradient(f, np.array([float(interface.level), tilt_x, tilt_y, float(interface.n_water)]))


def test_project_refracted_under_jit_and_vmap(rng):
    camera, interface, points, _ = random_refraction_case(rng)
    direct, _ = js.project_refracted(camera, interface, points)
    jitted, _ = jax.jit(js.project_refracted)(camera, interface, points)
    mapped, _ = jax.vmap(js.project_refracted, in_axes=(None, None, 0))(camera, interface, points[:, None, :])
    np.testing.assert_allclose(jitted, direct, atol=1e-10)
    np.testing.assert_allclose(mapped[:, 0], direct, atol=1e-10)


def test_rays_that_never_reach_the_water_are_invalid(rng):
    camera, interface, _, _ = random_refraction_case(rng)
    # A camera looking up at the sky.
    up = camera.with_pose(js.Pose.look_at(camera.center, camera.center + jnp.array([0.1, 0.0, 1.0])))
    _, _, valid = js.backproject_refracted(up, interface, jnp.array([[600.0, 450.0]]))
    assert not bool(valid[0])


def test_bad_input_names_the_parameter(rng, unchecked):
    camera, interface, points, _ = random_refraction_case(rng)
    with pytest.raises(js.JaxStereoError, match="normal must be a unit vector"):
        js.Interface(0.1, normal=(0.0, 0.0, 2.0))
    with pytest.raises(js.JaxStereoError, match="normal must be a unit vector"):
        js.Interface(0.1, normal=(0.0, 0.0, 0.0))
    with pytest.raises(js.JaxStereoError, match="n_water must be a positive"):
        js.Interface(0.1, n_water=-1.33)
    with pytest.raises(js.JaxStereoError, match="n_air must be a positive"):
        js.Interface(0.1, n_air=0.0)
    with pytest.raises(js.JaxStereoError, match="points_world must have shape"):
        js.project_refracted(camera, interface, points[:, :2])
    with pytest.raises(js.JaxStereoError, match="pixels must have shape"):
        js.backproject_refracted(camera, interface, jnp.zeros((4, 3)))
    high = interface.with_level(float(camera.center @ interface.normal) + 0.5)
    with pytest.raises(js.JaxStereoError, match="below the water plane"):
        js.project_refracted(camera, high, points)
    with pytest.raises(js.JaxStereoError, match="below the water plane"):
        js.backproject_refracted(camera, high, jnp.zeros((4, 2)))


def test_forward_projection_requires_denser_water(rng):
    camera, _, points, _ = random_refraction_case(rng)
    with pytest.raises(js.JaxStereoError, match="n_water .* must exceed n_air"):
        js.project_refracted(camera, js.Interface(-1.0, n_air=1.5, n_water=1.333), points)
