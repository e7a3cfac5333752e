"""Bundle adjustment through refraction: optimistix (jit) versus scipy.optimize.least_squares, same residuals.

Run: python benchmarks/bench_solvers.py [--correspondences 2000] [--solver lm|dogleg|...] [--control surface|floor]
Both solve the same problem (water level and right-camera pose, points eliminated, Cauchy loss) from the
same start; optimistix's compile time is printed apart from its solve time. `--control surface` (default)
puts every correspondence on a known surface (as a dry DEM does: a well-posed problem); `floor` only those
on the bare floor, with which the level trades against the pose (a nearly flat valley).
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from scipy.optimize import least_squares

import jaxstereo as js
from jaxstereo._calibration.rig import Rig
from jaxstereo._stereo.refine import refine_problem
from jaxstereo._synthetic.flume_rig import RigSpec, flume_rig
from jaxstereo._synthetic.scenes import Breakwater, build_scene

SOLVERS = {
    "lm": optx.LevenbergMarquardt(rtol=1e-8, atol=1e-8),
    "lm-tight": optx.LevenbergMarquardt(rtol=1e-10, atol=1e-10),
    "gauss-newton": optx.GaussNewton(rtol=1e-8, atol=1e-8),
    "dogleg": optx.Dogleg(rtol=1e-8, atol=1e-8),
}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--correspondences", type=int, default=2000)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--solver", choices=sorted(SOLVERS), default="lm")
    parser.add_argument("--control", choices=["surface", "floor"], default="surface")
    args = parser.parse_args(argv)
    with jax.enable_x64(True):
        scene = build_scene(Breakwater(seed=3))
        left, right = flume_rig(RigSpec(image_size=(1728, 1152), water_level_m=0.158))
        rng = np.random.default_rng(0)
        xy = rng.uniform([-0.6, -0.35], [0.6, 0.35], (args.correspondences, 2))
        z, _ = scene.heightfield.height_at(jnp.asarray(xy))
        X = jnp.asarray(np.column_stack([xy, np.asarray(z)]))
        water = js.Interface(0.158)
        pl = np.asarray(js.project_refracted(left, water, X)[0]) + rng.normal(0, 0.1, (len(xy), 2))
        pr = np.asarray(js.project_refracted(right, water, X)[0]) + rng.normal(0, 0.1, (len(xy), 2))
        moved = right.with_pose(right.pose.retract(jnp.array([2e-3, -1e-3, 1.5e-3, 0.0, 1e-3, -1e-3])))
        if args.control == "floor":  # correspondences on the bare floor (z = 0)
            fn, theta0, pargs = refine_problem(Rig(left, moved), pl, pr, 0.168, floor_mask=np.asarray(X[:, 2]) < 1e-9)
        else:  # every correspondence on a known surface, 2 mm standard deviation
            fn, theta0, pargs = refine_problem(Rig(left, moved), pl, pr, 0.168, floor_mask=np.ones(len(pl), bool),
                                               control_z=np.asarray(X[:, 2]), floor_sigma_m=0.002)
        solver = SOLVERS[args.solver]
        @jax.jit
        def solve(t, a):
            sol = optx.least_squares(fn, solver, t, a, max_steps=100, throw=False)
            return sol.value, sol.stats["num_steps"]

        start = time.perf_counter()
        jax.block_until_ready(solve(theta0, pargs))
        compile_s = time.perf_counter() - start
        times = []
        for _ in range(args.repeat):
            start = time.perf_counter()
            value, steps = jax.block_until_ready(solve(theta0, pargs))
            times.append(time.perf_counter() - start)
        t_optx = min(times)
        cost_optx = 0.5 * float(jnp.sum(fn(value, pargs) ** 2))

        f = jax.jit(lambda t: fn(t, pargs))
        J = jax.jit(jax.jacfwd(lambda t: fn(t, pargs)))
        f(theta0).block_until_ready()
        J(theta0).block_until_ready()
        start = time.perf_counter()
        ref = least_squares(lambda t: np.asarray(f(jnp.asarray(t))), np.asarray(theta0),
                            jac=lambda t: np.asarray(J(jnp.asarray(t))), method="lm", xtol=1e-10, ftol=1e-10)
        t_scipy = time.perf_counter() - start

    print(f"{args.correspondences} correspondences, {theta0.size} parameters, control {args.control}; optimistix "
          f"compile {compile_s:.2f} s, {int(steps)} steps; scipy {ref.nfev} residual and {ref.njev} Jacobian evaluations")
    print("| solver | seconds (after compilation) | final cost | ratio to scipy |")
    print("|---|---:|---:|---:|")
    print(f"| scipy least_squares (LM, jitted residuals and Jacobian; baseline) | {t_scipy:.3f} | {ref.cost:.6f} | 1.00x |")
    speed = f"{t_scipy / t_optx:.1f}x faster" if t_optx <= t_scipy else f"{t_optx / t_scipy:.1f}x slower"
    print(f"| optimistix {args.solver} (jit) | {t_optx:.3f} | {cost_optx:.6f} | {speed} |")
    print(f"relative cost difference {abs(cost_optx - ref.cost) / ref.cost:.2e}")


if __name__ == "__main__":
    main()
