"""6. water-level: bundle-adjustment accuracy for the water level versus image noise, number of
correspondences, camera tilt and control; optimistix against scipy on the same residuals."""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from scipy.optimize import least_squares

import jaxstereo as js
from jaxstereo._stereo.refine import LEVEL_TOLERANCE_M, refine_problem
from jaxstereo._synthetic.matches import surface_correspondences

from ._common import Output

LEVEL = 0.158


def _case(scene, n, noise, tilt_deg, control, seed=0):
    left, right = js.flume_rig(js.RigSpec(image_size=(1728, 1152), water_level_m=LEVEL, tilt_deg=tilt_deg,
                                          center_xy_m=(0.0, -2.158 * np.tan(np.deg2rad(tilt_deg)))))
    pl, pr, X = surface_correspondences(scene.heightfield, left, right, js.Interface(LEVEL), n, noise, seed,
                                        xy_min=(-0.7, -0.45), xy_max=(0.7, 0.45), oversample=4)
    floor = (X[:, 2] < 1e-9) if control == "floor" else None
    fn, theta0, args = refine_problem(js.Rig(left, right), pl, pr, LEVEL + 0.05, refine=("water",), floor_mask=floor)
    solver = optx.LevenbergMarquardt(rtol=1e-8, atol=1e-8)
    solve = jax.jit(lambda t, a: optx.least_squares(fn, solver, t, a, max_steps=200, throw=False).value)
    solve(theta0, args).block_until_ready()
    start = time.perf_counter()
    theta = solve(theta0, args).block_until_ready()
    t_optx = time.perf_counter() - start
    f = jax.jit(lambda t: fn(t, args))
    J = jax.jit(jax.jacfwd(lambda t: fn(t, args)))
    f(theta0).block_until_ready()
    J(theta0).block_until_ready()
    start = time.perf_counter()
    least_squares(lambda t: np.asarray(f(jnp.asarray(t))), np.asarray(theta0),
                  jac=lambda t: np.asarray(J(jnp.asarray(t))), method="lm")
    t_scipy = time.perf_counter() - start
    Jm = np.asarray(J(theta))
    r = np.asarray(f(theta))
    std = np.sqrt(np.linalg.inv(Jm.T @ Jm)[0, 0] * (r @ r) / max(1, r.size - 1)) * 1e-2
    level = LEVEL + 0.05 + float(theta[0]) * 1e-2
    return level - LEVEL, std, t_optx, t_scipy, int(np.sum(floor)) if floor is not None else 0


def _dem_case(dry, wet, n, noise, seed=0):
    """Level and right-camera pose together, a dry DEM of the undamaged model as control; the wet images
    show the damaged model; the right camera is moved by 0.2 deg and 2 mm, the level guess is 5 cm off."""
    left, right = js.flume_rig(js.RigSpec(image_size=(1728, 1152), water_level_m=LEVEL))
    pl, pr, _ = surface_correspondences(wet.heightfield, left, right, js.Interface(LEVEL), n, noise, seed)
    hf = dry.heightfield
    X, Y = np.meshgrid(hf.x, hf.y)
    dem = js.grid_median(np.stack([X.ravel(), Y.ravel(), np.asarray(hf.z).ravel()], axis=-1), 0.005)
    perturb = jnp.array([np.deg2rad(0.2) / np.sqrt(3)] * 3 + [0.0, 0.002 / np.sqrt(2), 0.002 / np.sqrt(2)])
    moved = right.with_pose(right.pose.retract(perturb))
    result = js.refine_rig(js.Rig(left, moved), pl, pr, LEVEL + 0.05, refine=("water", "right-pose"), control=dem)
    level, std = result.parameters["water level (m)"]
    angle = np.rad2deg(np.linalg.norm(np.asarray(js.so3_log(result.rig.right.pose.R @ right.pose.R.T))))
    return level - LEVEL, std, angle, result.n_control, result.level_determined


def run(out: Output, full: bool = False) -> None:
    scene = js.build_scene(js.Breakwater(seed=3))
    cases = [(n, noise, 0.0, "floor") for n in ((500, 2000) if not full else (250, 1000, 4000))
             for noise in (0.05, 0.2, 0.5)]
    cases += [(2000, 0.2, 10.0, "floor"), (2000, 0.2, 0.0, "none")]
    rows = []
    for n, noise, tilt, control in cases:
        out.log(f"{n} correspondences, noise {noise} px, tilt {tilt} deg, control {control}")
        err, std, t_optx, t_scipy, n_floor = _case(scene, n, noise, tilt, control)
        rows.append([n, noise, tilt, f"{control} ({n_floor})" if control == "floor" else control,
                     f"{1e3 * err:+.2f}", f"{1e3 * std:.2f}", "yes" if 2 * std <= LEVEL_TOLERANCE_M else "NO", "-",
                     f"{1e3 * t_optx:.0f}", f"{1e3 * t_scipy:.0f}"])
    with jax.enable_x64(True):
        wet = js.build_scene(js.Breakwater(seed=3, damage=js.Damage(half_length_dn50=3.0, half_width_dn50=4.0,
                                                                        swl_m=LEVEL)))
        for noise in (0.05, 0.2, 0.5):
            out.log(f"2000 correspondences, noise {noise} px, level and right pose, dry DEM as control")
            err, std, angle, n_control, determined = _dem_case(scene, wet, 2000, noise)
            rows.append([2000, noise, 0.0, f"dry DEM, right pose free ({n_control})", f"{1e3 * err:+.2f}",
                         f"{1e3 * std:.2f}", "yes" if determined else "NO", f"{angle:.4f}", "-", "-"])
    out.table(["correspondences", "noise (px)", "tilt (deg)", "control (control terms)", "level error (mm)",
               "std (mm)", "determined", "right pose error (deg)", "optimistix (ms)", "scipy (ms)"], rows,
              "Water level by bundle adjustment through refraction, starting 5 cm off (level only, poses fixed; "
              "last rows: level and right-camera pose, the pose moved by 0.2 deg and 2 mm)",
              "Exact correspondences on the synthetic breakwater with Gaussian pixel noise. Without control the level "
              "is not determined (two nadir cameras: a level change barely moves the rays); the floor fixes it. A "
              "level counts as determined when its 95 % interval (two standard deviations) is within 1 mm, the rule of "
              "`jaxstereo refine` (whose std adds a jackknife and the world frame's share; the floor rows' is the "
              "Gauss-Newton one alone). The "
              "error grows with the noise faster than the standard deviation says: eliminating the points (each "
              "triangulated from noisy pixels) biases their depth, and the floor control turns that bias into a level "
              "bias (about -1 mm at 0.5 px, +2 mm on the 10-degree rig). Refining the points too should remove it (not tried yet). "
              "In the last rows the wet images show the model after a test (a hole at the still water level) and the "
              "control is a 5 mm DEM of the model before it (a dry survey): correspondences that agree with it within 3 "
              "sigma are control terms at their own heights, which fixes the level and the pose together (the floor "
              "alone cannot once the pose is free). Sigma is the larger of 2 mm and the points' own scatter about the "
              "DEM (their depth noise: 3.3 mm at 0.2 px, 7.6 mm at 0.5 px); with sigma held at 2 mm the selection cut "
              "the noise and the level came back 2.4 mm off at 0.2 px and diverged at 0.5 px.")
