"""Uncertainty propagation: the JAX Jacobians against finite differences of an independent numpy reference,
the disparity's standard deviation against the scatter it predicts, and a survey's error bars end to end."""

import jax.numpy as jnp
import numpy as np
import pytest

from jaxstereo import Interface, Rig, reconstruct
from jaxstereo._stereo import matching
from jaxstereo._stereo.matching import refine_disparity
from jaxstereo._stereo.reconstruct import _triangulate_chunk, _triangulate_model
from jaxstereo._stereo.rectify import rectified_to_real, rectify
from jaxstereo._stereo.uncertainty import SHARED_PARAMETERS, _shared_jacobians, covariance_matrices, perturbed_rig
from jaxstereo._synthetic.flume_rig import flume_rig, realistic_rig_spec

LEVEL = 0.18


@pytest.fixture(scope="module")
def wet_pair():
    """A realistic rig (turned cameras, a 35 mm lens's distortion) and matches of emerged and submerged points."""
    with_x64 = __import__("jax").enable_x64(True)
    with with_x64:
        left, right = flume_rig(realistic_rig_spec(water_level_m=LEVEL, image_size=(1200, 800)))
        interface = Interface(LEVEL)
        rect = rectify(left, right, interface, "water")
        rng = np.random.default_rng(3)
        rl = np.stack([rng.uniform(100, 1100, 40), rng.uniform(100, 700, 40)], -1)
        # disparities for points from 10 cm below to 15 cm above the water (emerged and submerged alike)
        d = rng.uniform(0.0, 1.0, 40)
        lo, hi = _disparity_span(rect, left, right, interface, rl)
        rr = np.stack([rl[:, 0] - (lo + d * (hi - lo)), rl[:, 1]], -1)
    return left, right, interface, rect, rl, rr


def _disparity_span(rect, left, right, interface, rl):
    from jaxstereo._stereo.epipolar import disparity_bounds

    return disparity_bounds(rect, left, right, interface, LEVEL - 0.10, LEVEL + 0.15)


def test_disparity_derivative_matches_finite_differences_of_the_triangulation(x64, wet_pair):
    """The shared Jacobians' last column, d(point)/d(disparity) for the point's own class, against central
    differences of the exact model's triangulation (`_triangulate_model`) itself."""
    left, right, interface, rect, rl, rr = wet_pair
    _, _, submerged, ok, _ = _triangulate_chunk(rect, left, right, interface, "exact", jnp.asarray(rl), jnp.asarray(rr))
    submerged = np.asarray(submerged)
    assert np.all(ok) and 0 < np.sum(submerged) < len(rl)  # both kinds of point are checked
    J = np.asarray(_shared_jacobians(rect, left, right, interface, jnp.asarray(rl), jnp.asarray(rr)))
    jac = np.where(submerged[:, None], J[1, :, :, 14], J[0, :, :, 14])
    h = 1e-4
    step = np.array([[h, 0.0]])
    plus = np.asarray(_triangulate_model(rect, left, right, interface, "exact", jnp.asarray(rl), jnp.asarray(rr - step))[0])
    minus = np.asarray(_triangulate_model(rect, left, right, interface, "exact", jnp.asarray(rl), jnp.asarray(rr + step))[0])
    fd = (plus - minus) / (2 * h)
    np.testing.assert_allclose(jac, fd, rtol=1e-5, atol=1e-9)
    assert np.all(np.abs(jac[:, 2]) > 1e-4)  # millimetres per pixel: a real derivative


def _reference_points(theta, rig: Rig, interface: Interface, raw_l, raw_r, submerged):
    """numpy reference: the same raw pixels seen by the rig moved by `theta` (`perturbed_rig`), backprojected,
    refracted by Snell's law at the moved water level and triangulated by the rays' midpoint."""
    moved = perturbed_rig(rig, theta)
    rays = []
    for cam, raw in ((moved.left, raw_l), (moved.right, raw_r)):
        o, d = (np.asarray(a) for a in cam.backproject(raw))
        if submerged:
            s = (interface.level + theta[13] - o[:, 2]) / d[:, 2]
            o = o + s[:, None] * d
            cos_i = -d[:, 2:3]  # rays point down, the normal up
            mu = float(interface.n_air) / float(interface.n_water)
            cos_t = np.sqrt(1 - mu**2 * (1 - cos_i**2))
            d = mu * d + (mu * cos_i - cos_t) * np.array([0.0, 0.0, 1.0])
            d = d / np.linalg.norm(d, axis=1, keepdims=True)
        rays.append((o, d))
    (o1, d1), (o2, d2) = rays
    w0 = o1 - o2
    a, b, c = (d1 * d1).sum(1), (d1 * d2).sum(1), (d2 * d2).sum(1)
    dd, e = (d1 * w0).sum(1), (d2 * w0).sum(1)
    den = a * c - b * b
    s, t = (b * e - c * dd) / den, (a * e - b * dd) / den
    return 0.5 * (o1 + s[:, None] * d1 + o2 + t[:, None] * d2)


def test_shared_jacobians_match_finite_differences_of_a_numpy_reference(x64, wet_pair):
    left, right, interface, rect, rl, rr = wet_pair
    raw_l = np.asarray(rectified_to_real(rect, left, 0, jnp.asarray(rl))[0])
    raw_r = np.asarray(rectified_to_real(rect, right, 1, jnp.asarray(rr))[0])
    J = np.asarray(_shared_jacobians(rect, left, right, interface, jnp.asarray(rl), jnp.asarray(rr)))
    rig = Rig(left, right)
    steps = [1e-6] * 3 + [1e-6] * 3 + [1e-7] * 3 + [1e-7] * 3 + [1e-6, 1e-6]
    for cls in (0, 1):
        for k, name in enumerate(SHARED_PARAMETERS):
            delta = np.zeros(14)
            delta[k] = steps[k]
            fd = (_reference_points(delta, rig, interface, raw_l, raw_r, cls)
                  - _reference_points(-delta, rig, interface, raw_l, raw_r, cls)) / (2 * steps[k])
            scale = np.abs(fd).max()
            if cls == 0 and name == "water level (m)":
                assert np.all(J[cls, :, :, k] == 0)  # the level does not move emerged points
                continue
            # The focal length's reference scales the distorted pixels (as the calibration does); the table
            # scales the undistorted ray: equal up to the lens's distortion, a few percent at the corners.
            tol = 0.05 if name.startswith("focal") else 2e-3
            np.testing.assert_allclose(J[cls, :, :, k], fd, atol=tol * scale, err_msg=f"{name}, class {cls}")
    h = 1e-3  # pixels of disparity: a larger one moves the right pixel left
    moved = [np.asarray(rectified_to_real(rect, right, 1, jnp.asarray(rr + sign * np.array([[h, 0.0]])))[0])
             for sign in (-1, 1)]
    for cls in (0, 1):
        fd = (_reference_points(np.zeros(14), rig, interface, raw_l, moved[0], cls)
              - _reference_points(np.zeros(14), rig, interface, raw_l, moved[1], cls)) / (2 * h)
        np.testing.assert_allclose(J[cls, :, :, 14], fd, atol=2e-3 * np.abs(fd).max(),
                                   err_msg=f"disparity, class {cls}")


def test_covariance_matrices_unpacks_the_six_terms():
    cov = covariance_matrices(np.array([[1.0, 2.0, 3.0, 0.1, 0.2, 0.3]]))[0]
    np.testing.assert_array_equal(cov, [[1.0, 0.1, 0.2], [0.1, 2.0, 0.3], [0.2, 0.3, 3.0]])


def test_disparity_sigma_predicts_the_scatter_under_independent_noise(monkeypatch):
    """With independent pixel noise (the least-squares formula's assumption) and the calibration factors set to
    one, the predicted std of the large patch's fit matches the disparities' measured scatter. With the small patch
    (9 px) beside it, 0.3-0.4 % of the pixels switch to a small fit that lies 0.2-0.5 px off (noise, not relief,
    on this flat texture), and the scatter grows past the prediction by up to a quarter."""
    monkeypatch.setattr(matching, "MATCH_NOISE_SCALE", 1.0)
    rng = np.random.default_rng(0)
    h, w, shift = 480, 800, 12
    texture = cv2_blur(rng.uniform(0, 255, (h, w + shift)), 1.5)
    right_clean = texture[:, shift:]
    left_clean = texture[:, :w]
    # x_right = x_left - d: left pixel u sees the texture at u, right pixel u - d sees texture at u - d + shift
    rows = []
    for noise in (2.0, 6.0):
        left = np.clip(left_clean + rng.normal(0, noise, left_clean.shape), 0, 255).astype(np.uint8)
        right = np.clip(right_clean + rng.normal(0, noise, right_clean.shape), 0, 255).astype(np.uint8)
        start = np.full((h, w), float(shift), np.float32)  # SGBM's whole pixel: one linearisation
        inner = np.s_[40:-40, 60:-60]
        for small_window in (None, 9):
            d, sigma, *_ = refine_disparity(left, right, start, window=31, small_window=small_window)
            err = d[inner] - shift
            rows.append((np.std(err), np.median(sigma[inner])))
    large_only, with_small = rows[0::2], rows[1::2]
    for measured, predicted in large_only:
        assert 0.85 <= predicted / measured <= 1.3, rows  # 0.99 and 1.03 measured
    for measured, predicted in with_small:
        assert 0.75 <= predicted / measured <= 1.3, rows  # 0.80 and 0.87 measured
    assert large_only[1][0] > 2 * large_only[0][0]  # more noise, more scatter, and the prediction follows it


def cv2_blur(image, sigma):
    import cv2

    return cv2.GaussianBlur(image, (0, 0), sigma)


def test_survey_carries_error_bars_that_grow_under_water(x64):
    """A flat textured floor half under water, on a realistic rig: every point has a covariance; the vertical
    std from matching is larger under water (refraction stretches depth) and covers the true errors."""
    from jaxstereo import Heightfield, render_view
    from jaxstereo._synthetic.flume_rig import jpeg

    left, right = flume_rig(realistic_rig_spec(water_level_m=0.1, image_size=(800, 540)))
    spacing = 0.002
    ny, nx = 700, 900
    x = -0.9 + spacing * np.arange(nx)
    X = np.broadcast_to(x, (ny, nx))
    z = np.where(X < 0, 0.05, 0.15)  # two flat levels: one under the water, one above it
    rng = np.random.default_rng(1)
    albedo = cv2_blur(rng.uniform(0.15, 0.85, (ny, nx, 3)), 0.7)
    field = Heightfield(z, albedo, -0.9, -0.7, spacing)
    images = [jpeg(render_view(cam, field, Interface(0.1)).image) for cam in (left, right)]
    survey, summary = reconstruct(images[0], images[1], Rig(left, right), 0.1)
    assert survey.cov.shape == (len(survey), 6) and np.all(survey.cov[:, 2] > 0)
    under, over = survey.submerged, ~survey.submerged
    assert np.median(survey.sigma_z_match[under]) > np.median(survey.sigma_z_match[over])
    truth = np.where(survey.points[:, 0] < 0, 0.05, 0.15)
    inside = np.abs(survey.points[:, 0]) > 0.03  # away from the step
    err = survey.points[inside, 2] - truth[inside]
    assert np.mean(np.abs(err) <= 2 * survey.sigma_z[inside]) >= 0.85
    assert summary["median_sigma_z_match_submerged_mm"] > summary["median_sigma_z_match_emerged_mm"]


def test_shared_covariance_table_interpolates_the_exact_jacobians(x64, wet_pair):
    """The table every 96 px and 8 px of disparity, interpolated, against the shared covariance from the exact
    Jacobians at the matches themselves: vertical variances within 2 % (1.1 % measured), horizontal within 6 %
    (5.0 %), i.e. standard deviations within 1 % and 3 %; the point's derivative with respect to its disparity
    within 1 %."""
    from jaxstereo._stereo.uncertainty import SharedErrors, point_covariances, shared_covariance_table

    left, right, interface, rect, rl, rr = wet_pair
    std = np.array([5e-4, 5e-4, 2e-4, 1e-4, 1e-4, 1e-4, 1e-5, 1e-5, 1e-5, 1e-5, 1e-5, 1e-5, 3e-4, 5e-4])
    shared = SharedErrors(np.diag(std**2), {})
    d = rl[:, 0] - rr[:, 0]
    search = (int(np.floor(d.min())) - 8, int(np.ceil(d.max() - d.min())) + 16)
    table = shared_covariance_table(rect, Rig(left, right), interface, shared, left.image_size, search)
    J = np.asarray(_shared_jacobians(rect, left, right, interface, jnp.asarray(rl), jnp.asarray(rr)))
    n = len(rl)
    for cls in (0, 1):
        exact = np.einsum("nik,kl,njl->nij", J[cls, ..., :14], shared.cov, J[cls, ..., :14])
        out = point_covariances(table, rl[:, 1], rl[:, 0], d, np.full(n, bool(cls)), np.zeros(n), np.zeros(n))
        np.testing.assert_allclose(out["cov"][:, 2], exact[:, 2, 2], rtol=0.02)
        np.testing.assert_allclose(out["cov"][:, 0], exact[:, 0, 0], rtol=0.06)
        # The point's derivative with respect to its disparity, from the same table: the matching's part of the
        # vertical std for a disparity std of one pixel, and the whole covariance it adds
        matched = point_covariances(table, rl[:, 1], rl[:, 0], d, np.full(n, bool(cls)), np.ones(n), np.zeros(n))
        np.testing.assert_allclose(matched["sigma_z_match"], np.abs(J[cls, :, 2, 14]), rtol=0.01)
        added = np.einsum("ni,nj->nij", J[cls, :, :, 14], J[cls, :, :, 14])
        np.testing.assert_allclose(matched["cov"][:, 2] - out["cov"][:, 2], added[:, 2, 2], rtol=0.02)
