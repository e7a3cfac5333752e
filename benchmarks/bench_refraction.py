"""Exact forward-projection throughput: jaxstereo (JAX, jit, float64) versus the same algorithm in numpy.

Run: python benchmarks/bench_refraction.py [--points 2000000] [--repeat 5]
Prints a table with points per second and the ratio to the numpy baseline measured in the same run.
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxstereo as js
from jaxstereo._geometry.refraction import NEWTON_ITERATIONS


def numpy_project_refracted(K, R, tvec, center, normal, level, n_air, n_water, points, iterations=NEWTON_ITERATIONS):
    """The same algorithm as `jaxstereo.project_refracted` (pinhole part without distortion), in numpy."""
    dc = center @ normal - level
    dp = level - points @ normal
    foot_c = center - dc * normal
    foot_p = points + dp[:, None] * normal
    v = foot_p - foot_c
    r = np.sqrt(np.einsum("ij,ij->i", v, v))
    u = v / np.where(r > 0, r, 1.0)[:, None]
    k = n_air / n_water
    t = r / (dc + k * dp)
    for _ in range(iterations + 1):
        q = 1.0 / np.sqrt(1.0 + (1.0 - k * k) * t * t)
        g = dc * t + dp * k * t * q - r
        t = t - g / (dc + dp * k * q**3)
    s = dc * t
    hit = foot_c + s[:, None] * u
    pc = hit @ R.T + tvec
    xy = pc[:, :2] / pc[:, 2:3]
    return xy * np.array([K[0, 0], K[1, 1]]) + np.array([K[0, 2], K[1, 2]])


def _time(fn, repeat):
    best = np.inf
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - start)
    return best


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=2_000_000)
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args(argv)

    with jax.enable_x64(True):
        rng = np.random.default_rng(0)
        camera = js.Camera(3935.0, 3935.0, 1247.5, 831.5, np.zeros(5), js.Pose.look_at([0, 0, 2.2], [0.2, 0.1, 0]),
                           (2496, 1664))
        interface = js.Interface(0.2)
        points_np = rng.uniform([-0.6, -0.4, -0.1], [0.6, 0.4, 0.19], (args.points, 3))
        points = jnp.asarray(points_np)

        project = jax.jit(lambda c, i, x: js.project_refracted(c, i, x)[0])
        start = time.perf_counter()
        project(camera, interface, points).block_until_ready()
        compile_s = time.perf_counter() - start
        t_jax = _time(lambda: project(camera, interface, points).block_until_ready(), args.repeat)

        K = np.asarray(camera.K)
        R = np.asarray(camera.pose.R)
        t = np.asarray(camera.pose.t)
        c = np.asarray(camera.center)
        normal = np.asarray(interface.normal)
        sub = points_np[:, 2] < 0.2
        args_np = (K, R, t, c, normal, 0.2, 1.0, 1.333, points_np[sub])
        t_np = _time(lambda: numpy_project_refracted(*args_np), max(1, args.repeat // 2))
        # Same answer for the submerged points.
        diff = np.abs(numpy_project_refracted(*args_np) - np.asarray(project(camera, interface, points))[sub]).max()

    n = args.points
    n_sub = int(sub.sum())
    rows = [
        ("numpy (baseline)", n_sub, t_np, n_sub / t_np),
        ("jaxstereo jit float64", n, t_jax, n / t_jax),
    ]
    print(f"exact forward projection, {jax.devices()[0].platform}, {NEWTON_ITERATIONS} Newton steps + 1, "
          f"compile {compile_s:.2f} s, max |jax - numpy| = {diff:.2e} px")
    print("| implementation | points | best time (s) | points/s | ratio to numpy |")
    print("|---|---:|---:|---:|---:|")
    base = rows[0][3]
    for name, count, seconds, rate in rows:
        print(f"| {name} | {count} | {seconds:.3f} | {rate / 1e6:.2f} M | {rate / base:.1f}x |")


if __name__ == "__main__":
    main()
