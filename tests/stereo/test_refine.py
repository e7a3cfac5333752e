"""Bundle adjustment through refraction against exact synthetic correspondences."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest
from scipy.optimize import least_squares

import jaxstereo as js
from jaxstereo._calibration.rig import Rig
from jaxstereo._stereo.refine import find_correspondences, refine_problem, refine_rig
from jaxstereo._surface.grid import grid_median, save_dem
from jaxstereo._synthetic.flume_rig import RigSpec, flume_rig
from jaxstereo._synthetic.matches import surface_correspondences
from jaxstereo._synthetic.render import render_view
from jaxstereo._synthetic.scenes import Breakwater, Damage, Extent, SlopingBoard, build_scene

LEVEL = 0.158


@pytest.fixture(scope="module")
def flume():
    spec = Breakwater(seed=3)
    scene = build_scene(spec)
    left, right = flume_rig(RigSpec(image_size=(1728, 1152), water_level_m=LEVEL))
    return spec, scene, left, right


def _correspondences(scene, left, right, n, noise_px, seed=0):
    """Surface points seen by both cameras, projected exactly through the water, with pixel noise."""
    return surface_correspondences(scene.heightfield, left, right, js.Interface(LEVEL), n, noise_px, seed)


def test_level_from_floor_control_starting_5cm_off(flume):
    spec, scene, left, right = flume
    pl, pr, _ = _correspondences(scene, left, right, 1500, 0.1)
    floor = (-0.75, spec.toe_x_m - 2 * spec.dn50_m)  # the bare floor in front of the toe
    result = refine_rig(Rig(left, right), pl, pr, LEVEL + 0.05, refine=("water",), control="floor",
                        floor_region=floor)
    level, std = result.parameters["water level (m)"]
    assert abs(level - LEVEL) <= min(1e-3, 2 * std)
    # The floor alone, seen by two nadir cameras, fixes the level to 0.5-1 mm (one sigma) here: determined only
    # where its 95 % interval is within the tolerance asked for (1 mm by default).
    assert 3e-4 < std < 1e-3 and result.level_determined == (2 * std <= 1e-3)
    wider = refine_rig(Rig(left, right), pl, pr, LEVEL + 0.05, refine=("water",), control="floor",
                       floor_region=floor, level_tolerance_m=2e-3)
    assert wider.level_determined and wider.parameters["water level (m)"] == (level, std)
    assert result.rms_after_px <= 0.3 and result.rms_after_px < result.rms_before_px
    assert abs(float(result.rig.interface.level) - level) < 1e-12


def test_right_pose_comes_back_with_control_points(flume):
    spec, scene, left, right = flume
    pl, pr, _ = _correspondences(scene, left, right, 1500, 0.1)
    gl, gr, gxyz = _correspondences(scene, left, right, 12, 0.05, seed=9)
    perturb = jnp.array([np.deg2rad(0.2) / np.sqrt(3)] * 3 + [0.0, 0.002 / np.sqrt(2), 0.002 / np.sqrt(2)])
    moved = right.with_pose(right.pose.retract(perturb))
    result = refine_rig(Rig(left, moved), pl, pr, LEVEL + 0.05, refine=("water", "right-pose"), control="floor",
                        floor_region=(-0.75, spec.toe_x_m - 2 * spec.dn50_m), control_points=(gl, gr, gxyz))
    angle = np.rad2deg(np.linalg.norm(np.asarray(js.so3_log(np.asarray(result.rig.right.pose.R) @ np.asarray(right.pose.R).T))))
    assert angle <= 0.02
    assert np.linalg.norm(np.asarray(result.rig.right.center) - np.asarray(right.center)) <= 5e-4
    assert result.rms_after_px <= 0.3
    level, std = result.parameters["water level (m)"]
    assert abs(level - LEVEL) <= 3 * std + 1e-3


def _dry_dem(scene, shift_x=0.0):
    """A 5 mm DEM of the undamaged model (as a dry survey would give), from its exact heightfield."""
    hf = scene.heightfield
    X, Y = np.meshgrid(hf.x, hf.y)
    nodes = np.stack([X.ravel() + shift_x, Y.ravel(), np.asarray(hf.z).ravel()], axis=-1)
    return grid_median(nodes, 0.005)


def test_level_and_pose_from_a_dry_dem_of_the_parts_that_did_not_move(flume, monkeypatch):
    """The wet images show the model after a test (a hole at the SWL); the control is the dry DEM before it.

    The solves with the level held at the guess only place the start: here the first of them is made to report
    its step limit (as it did on the POV-Ray flume seen by its cameras turned 180 degrees), and the converged
    refinement after it still counts as converged and determined."""
    from jaxstereo._stereo import refine as module

    start = module._start_at_the_guessed_level

    def start_that_stops(*args):
        theta, outcomes = start(*args)
        return theta, ["stopped at its step limit"] + outcomes[1:]

    monkeypatch.setattr(module, "_start_at_the_guessed_level", start_that_stops)
    spec, scene, left, right = flume
    wet = build_scene(dataclasses.replace(spec, damage=Damage(half_length_dn50=3.0, half_width_dn50=4.0, swl_m=LEVEL)))
    pl, pr, _ = surface_correspondences(wet.heightfield, left, right, js.Interface(LEVEL), 1500, 0.1)
    perturb = jnp.array([np.deg2rad(0.2) / np.sqrt(3)] * 3 + [0.0, 0.002 / np.sqrt(2), 0.002 / np.sqrt(2)])
    moved = right.with_pose(right.pose.retract(perturb))
    result = refine_rig(Rig(left, moved), pl, pr, LEVEL + 0.05, refine=("water", "right-pose"), control=_dry_dem(scene))
    level, std = result.parameters["water level (m)"]
    angle = np.rad2deg(np.linalg.norm(np.asarray(js.so3_log(np.asarray(result.rig.right.pose.R) @ np.asarray(right.pose.R).T))))
    assert abs(level - LEVEL) <= 1e-3 and result.level_determined and std < 5e-4
    assert result.converged and result.outcomes == ("converged",) * 3
    assert result.rig.calibration["refine"]["start_solves"][0] == "stopped at its step limit"
    assert angle <= 0.02
    assert np.linalg.norm(np.asarray(result.rig.right.center) - np.asarray(right.center)) <= 5e-4
    assert result.rms_after_px <= 0.3
    # The damaged patch is not taken as control: fewer control terms than correspondences on the DEM.
    assert result.n_control < result.n_correspondences
    with pytest.raises(js.JaxStereoError, match="does not overlap the correspondences"):
        refine_rig(Rig(left, right), pl, pr, LEVEL, control=_dry_dem(scene, shift_x=5.0))


def test_each_correspondence_counts_once_wherever_it_sits_in_the_list(flume):
    """Correspondences are padded to a power of two with copies of the first; the copies weigh nothing. One
    bad correspondence (1.5 px off, inside the gate) moves the level as little first in the list as last (1500
    correspondences, padded with 548 copies of the bad one when it comes first)."""
    spec, scene, left, right = flume
    pl, pr, points = _correspondences(scene, left, right, 1500, 0.1, seed=4)
    bad = int(np.nonzero(np.asarray(points)[:, 2] < LEVEL - 0.05)[0][0])  # a submerged one: it pulls the level
    pr = pr.copy()
    pr[bad, 0] += 1.5
    levels = []
    for order in (np.r_[bad, np.delete(np.arange(len(pl)), bad)], np.r_[np.delete(np.arange(len(pl)), bad), bad]):
        result = refine_rig(Rig(left, right), pl[order], pr[order], LEVEL + 0.01, refine=("water",), control="floor",
                            floor_region=(-0.75, spec.toe_x_m - 2 * spec.dn50_m))
        levels.append(result.parameters["water level (m)"][0])
        assert result.n_correspondences == len(pl)
    assert abs(levels[0] - levels[1]) < 1e-6
    assert abs(levels[1] - LEVEL) < 1e-3


def test_level_not_determined_is_said(flume):
    spec, scene, left, right = flume
    pl, pr, _ = _correspondences(scene, left, right, 1500, 0.1)
    # Two nadir cameras and no control: a change of level barely moves the rays.
    result = refine_rig(Rig(left, right), pl, pr, LEVEL + 0.05, refine=("water",), control=None)
    assert not result.level_determined
    assert result.parameters["water level (m)"][1] > 2e-3
    # The floor alone cannot fix the level once the right camera may rotate: said too.
    result = refine_rig(Rig(left, right), pl, pr, LEVEL + 0.05, refine=("water", "right-pose"), control="floor",
                        floor_region=(-0.75, spec.toe_x_m - 2 * spec.dn50_m))
    assert not result.level_determined
    # A level under every correspondence refracts nothing: the solver stops there (zero step), undetermined.
    result = refine_rig(Rig(left, right), pl, pr, -0.3, refine=("water",), control=_dry_dem(scene))
    assert result.n_submerged == 0 and not result.level_determined


def test_same_minimum_as_scipy(flume, x64):  # differentiates the residual itself, as a user would in 64 bits
    _, scene, left, right = flume
    pl, pr, _ = _correspondences(scene, left, right, 400, 0.1)
    perturb = jnp.array([1e-3, -5e-4, 8e-4, 0.0, 1e-3, -1e-3])
    fn, theta0, args = refine_problem(Rig(left, right.with_pose(right.pose.retract(perturb))), pl, pr, LEVEL + 0.01)
    sol = optx.least_squares(fn, optx.LevenbergMarquardt(rtol=1e-12, atol=1e-12), theta0, args, max_steps=200,
                             throw=False)
    assert sol.result == optx.RESULTS.successful
    f = jax.jit(lambda t: fn(t, args))
    J = jax.jit(jax.jacfwd(lambda t: fn(t, args)))
    ref = least_squares(lambda t: np.asarray(f(jnp.asarray(t))), np.asarray(theta0),
                        jac=lambda t: np.asarray(J(jnp.asarray(t))), method="lm", xtol=1e-14, ftol=1e-14, gtol=1e-14)
    cost_optx = 0.5 * float(jnp.sum(f(sol.value) ** 2))
    assert abs(cost_optx - ref.cost) <= 1e-6 * ref.cost
    # Without control the minimum is flat along the level: only the well-determined rotations are compared.
    np.testing.assert_allclose(np.asarray(sol.value)[1:4], ref.x[1:4], atol=5e-3)


def test_sift_correspondences_agree_with_the_true_geometry():
    spec = SlopingBoard(extent=Extent(spacing=2e-3))
    left, right = flume_rig(RigSpec(image_size=(864, 576), water_level_m=0.18))
    water = js.Interface(0.18)
    scene = build_scene(spec)
    il, ir = (render_view(c, scene.heightfield, water).image for c in (left, right))
    pl, pr = find_correspondences(il, ir, 1000)
    assert len(pl) >= 300
    # Consistent with the refracted epipolar geometry: the exact triangulation re-projects onto them.
    fn, theta0, args = refine_problem(Rig(left, right, water), pl, pr, 0.18, refine=("water",))
    r = np.abs(np.asarray(fn(theta0, args)) * 0.3)
    assert np.median(r) < 0.3


def test_refine_bad_input(flume):
    _, scene, left, right = flume
    pl, pr, _ = _correspondences(scene, left, right, 100, 0.1)
    rig = Rig(left, right)
    with pytest.raises(js.JaxStereoError, match="at least 12 are needed"):
        refine_rig(rig, pl[:5], pr[:5], LEVEL)
    with pytest.raises(js.JaxStereoError, match="below the water plane"):
        refine_rig(rig, pl, pr, 5.0)
    with pytest.raises(js.JaxStereoError, match="cannot refine 'focus'"):
        refine_rig(rig, pl, pr, LEVEL, refine=("focus",))
    with pytest.raises(js.JaxStereoError, match="correspondences agree"):
        refine_rig(rig, pl, np.random.default_rng(0).uniform(0, 1000, pr.shape), LEVEL)
    with pytest.raises(js.JaxStereoError, match=r"no correspondence lies in the floor region x -5.000 to -4.000 m "
                       r"\(at the guessed level they span x -?\d"):  # out of view: refused before any solve
        refine_rig(rig, pl, pr, LEVEL, control="floor", floor_region=(-5.0, -4.0))


def test_refine_command(tmp_path, capsys):
    from jaxstereo._app.cli import main
    from jaxstereo._app.images import write_image
    from jaxstereo._calibration.rig import load_rig, save_rig

    spec = Breakwater(seed=3, extent=Extent(spacing=1.5e-3))
    scene = build_scene(spec)
    left, right = flume_rig(RigSpec(image_size=(864, 576), water_level_m=LEVEL))
    water = js.Interface(LEVEL)
    for name, cam in (("l.png", left), ("r.png", right)):
        write_image(tmp_path / name, render_view(cam, scene.heightfield, water).image)
    save_rig(Rig(left, right), tmp_path / "rig.json")
    args = ["refine", str(tmp_path / "l.png"), str(tmp_path / "r.png"), "--rig", str(tmp_path / "rig.json"),
            "--water-level-guess", str(LEVEL + 0.05), "-o", str(tmp_path / "wet.json")]
    assert main(args + ["--control", "floor", "--floor-x", "-0.75", str(spec.toe_x_m - 2 * spec.dn50_m)]) == 0
    out = capsys.readouterr().out
    assert "water level (m)" in out and "NOT DETERMINED" not in out
    assert abs(float(load_rig(tmp_path / "wet.json").interface.level) - LEVEL) < 2e-3
    save_dem(_dry_dem(scene), tmp_path / "dry.npz")
    # At 864x576 (1 px is about 3 mm here) the dry DEM fixes the level only to about a millimetre: the command
    # either writes a level within two of its standard deviations or refuses it, in one line, writing nothing.
    (tmp_path / "wet.json").unlink(missing_ok=True)
    code = main(args + ["--control", str(tmp_path / "dry.npz")])
    out, err = capsys.readouterr()
    if code == 0:
        level, std = (float(v) for v in out.split("water level (m)")[1].split()[0:3:2])
        assert abs(level - LEVEL) <= 2 * std and std <= 1e-3
    else:
        assert code == 2 and "water level not determined" in err and not (tmp_path / "wet.json").exists()
    save_dem(_dry_dem(scene, shift_x=5.0), tmp_path / "elsewhere.npz")
    assert main(args + ["--control", str(tmp_path / "elsewhere.npz")]) == 2
    assert "does not overlap the correspondences" in capsys.readouterr().err
    (tmp_path / "wet.json").unlink(missing_ok=True)
    assert main(args) == 2  # no control: refused, in one line, and no rig written
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "water level not determined" in err and "--keep-guess" in err, err
    assert not (tmp_path / "wet.json").exists()
    assert main(args + ["--keep-guess"]) == 0  # or, asked for, the guess is kept and said so
    assert "WATER LEVEL NOT DETERMINED" in capsys.readouterr().out
    kept = load_rig(tmp_path / "wet.json")
    assert float(kept.interface.level) == LEVEL + 0.05 and kept.calibration["refine"]["level_kept_from_guess"]
    (tmp_path / "bad.csv").write_text("u,v\n1,2\n")
    assert main(args + ["--control", str(tmp_path / "bad.csv")]) == 2
    assert "must have 7 columns" in capsys.readouterr().err
    # Broken input: each a one-line error, exit 2, no rig written.
    (tmp_path / "empty.png").write_bytes(b"")
    write_image(tmp_path / "small.png", np.zeros((100, 150, 3), np.uint8))
    cases = [
        (["refine", str(tmp_path / "empty.png"), *args[2:]], "is empty (0 bytes)"),
        (["refine", str(tmp_path / "l.png"), str(tmp_path / "small.png"), *args[3:]], "small.png' is 150x100"),
        ([*args[:6], "5.0", *args[7:]], "below the water plane"),
        ([*args, "--refine", "water,focus"], "cannot refine 'focus'"),
    ]
    for argv, text in cases:
        (tmp_path / "wet.json").unlink(missing_ok=True)
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and text in err, err
        assert not (tmp_path / "wet.json").exists()


def _as_calibrated(cam, eps):
    """The camera as a calibration with a relative focal-length error `eps` gives it: the focal length scaled,
    and with it every distance along the view, the centre's height above the floor board included."""
    c = np.asarray(cam.center)
    return js.Camera(float(cam.fx) * (1 + eps), float(cam.fy) * (1 + eps), float(cam.cx), float(cam.cy),
                     np.asarray(cam.dist), js.Pose.from_center(np.asarray(cam.pose.R), [c[0], c[1], c[2] * (1 + eps)]),
                     cam.image_size)


def test_level_uncertainty_covers_its_error_over_20_trials(flume):
    """Realistic rigs (each camera turned by up to 0.7 deg, lens distortion), 0.1-0.3 px of noise, a calibration
    whose focal length is off by a draw of its stated 0.03 %, the level guessed up to 2 cm off: the true level
    (measured from the calibrated cameras, as the flume scorecard does) lies within 2 standard deviations in at
    least 90 % of the trials, and within half a standard deviation in at most 70 % (not over-cautious either)."""
    from jaxstereo._synthetic.flume_rig import realistic_rig_spec

    spec, scene, _, _ = flume
    rng = np.random.default_rng(0)
    rel, z = 3e-4, []
    for k in range(20):
        turned = tuple(tuple(rng.uniform(-0.7, 0.7, 3)) for _ in range(2))
        left, right = flume_rig(realistic_rig_spec(water_level_m=LEVEL, misalignment_deg=turned))
        pl, pr, _ = surface_correspondences(scene.heightfield, left, right, js.Interface(LEVEL), 2000,
                                            rng.uniform(0.1, 0.3), k)
        eps = rng.normal(0, rel)
        rig = Rig(_as_calibrated(left, eps), _as_calibrated(right, eps), None, {"focal_std_rel": rel})
        result = refine_rig(rig, pl, pr, LEVEL + rng.uniform(-0.02, 0.02), refine=("water",), control="floor",
                            floor_region=(-0.75, spec.toe_x_m - 2 * spec.dn50_m))
        level, std = result.parameters["water level (m)"]
        z.append(abs(level - (LEVEL + eps * float(left.center[2]))) / std)
    z = np.asarray(z)
    assert np.mean(z <= 2) >= 0.9, z  # measured: 95 %
    assert np.mean(z <= 0.5) <= 0.7, z  # measured: 40 %


def test_floor_level_std_is_the_floor_height_error_of_a_tilted_frame_over_n_minus_1(flume):
    """A frame known to +/- 1 mrad about y and 0.2 mm in height: the floor 0.6 m from the origin is known to
    hypot(0.6 mm, 0.2 mm); with the floor as control the level takes that over n - 1."""
    from jaxstereo._stereo.refine import floor_level_std

    _, _, left, right = flume
    cov = np.diag([1e-12, 1e-6, 1e-12, 1e-12, 1e-12, 0.2e-3**2])
    rig = Rig(left, right, None, {"world_frame": {"frame_cov": cov.tolist()}})
    water = js.Interface(LEVEL)
    floor_xy = np.column_stack([np.full(50, -0.6), np.linspace(-0.1, 0.1, 50)])
    expected = np.hypot(0.6e-3, 0.2e-3) / (1.333 - 1.0)
    assert floor_level_std(rig, water, floor_xy) == pytest.approx(expected, rel=1e-3)
    assert floor_level_std(Rig(left, right), water, floor_xy) == 0.0  # no record: no term
    assert floor_level_std(rig, water, np.zeros((0, 2))) == 0.0


def test_a_calibrated_pose_prior_holds_the_pose_yet_lets_a_real_move_through(flume):
    """With the calibration's right-pose covariance in the rig (0.0003 deg, 0.01 mm, as on the POV-Ray flume)
    the pose stays within a few of its standard deviations when it did not move, and a camera bumped by
    0.2 deg and 2 mm still comes back: the prior is robust (Cauchy), not a constraint."""
    spec, scene, left, right = flume
    cov = np.diag([np.deg2rad(3e-4) ** 2] * 3 + [1e-5**2] * 3)
    provenance = {"world_frame": {"right_pose_cov": cov.tolist()}}
    wet = build_scene(dataclasses.replace(spec, damage=Damage(half_length_dn50=3.0, half_width_dn50=4.0, swl_m=LEVEL)))
    pl, pr, _ = surface_correspondences(wet.heightfield, left, right, js.Interface(LEVEL), 1500, 0.1)
    held = refine_rig(Rig(left, right, None, provenance), pl, pr, LEVEL + 0.05, refine=("water", "right-pose"),
                      control=_dry_dem(scene))
    angle = np.rad2deg(np.linalg.norm(np.asarray(js.so3_log(np.asarray(held.rig.right.pose.R) @ np.asarray(right.pose.R).T))))
    assert angle <= 5 * 3e-4 * np.sqrt(3)
    level, std = held.parameters["water level (m)"]
    assert abs(level - LEVEL) <= 2 * std and held.level_determined
    perturb = np.array([np.deg2rad(0.2) / np.sqrt(3)] * 3 + [0.0, 0.002 / np.sqrt(2), 0.002 / np.sqrt(2)])
    moved = right.with_pose(right.pose.retract(perturb))
    back = refine_rig(Rig(left, moved, None, provenance), pl, pr, LEVEL + 0.05, refine=("water", "right-pose"),
                      control=_dry_dem(scene))
    angle = np.rad2deg(np.linalg.norm(np.asarray(js.so3_log(np.asarray(back.rig.right.pose.R) @ np.asarray(right.pose.R).T))))
    assert angle <= 0.02
    assert np.linalg.norm(np.asarray(back.rig.right.center) - np.asarray(right.center)) <= 5e-4
