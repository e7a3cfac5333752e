"""Gridding speed: median per cell (jaxstereo's default) versus Delaunay linear interpolation (the paper's).

Run: python benchmarks/bench_grid.py [--points 4000000] [--spacing 0.005] [--delaunay-points 1000000]
Both run in this process on a synthetic cloud over a 1.5 m x 1 m flume patch.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from jaxstereo._surface.grid import grid_delaunay, grid_median


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=4_000_000)
    parser.add_argument("--spacing", type=float, default=0.005)
    parser.add_argument("--delaunay-points", type=int, default=1_000_000)
    args = parser.parse_args(argv)
    rng = np.random.default_rng(0)
    xy = rng.uniform([-0.75, -0.5], [0.75, 0.5], (args.points, 2))
    z = 0.2 * np.sin(4 * xy[:, 0]) + 0.05 * np.cos(7 * xy[:, 1]) + rng.normal(0, 0.001, args.points)
    points = np.column_stack([xy, z])

    grid_median(points[:1000], args.spacing)
    start = time.perf_counter()
    dem = grid_median(points, args.spacing)
    t_median = time.perf_counter() - start

    n_d = min(args.delaunay_points, args.points)
    start = time.perf_counter()
    grid_delaunay(points[:n_d], args.spacing, dem.x, dem.y)
    t_delaunay = time.perf_counter() - start

    rate_d = n_d / t_delaunay
    print(f"{args.points} points, spacing {args.spacing} m, grid {dem.z.shape[1]} x {dem.z.shape[0]}")
    print("| method | points | seconds | points/s | ratio to Delaunay (per point) |")
    print("|---|---:|---:|---:|---:|")
    print(f"| Delaunay + linear (baseline, the paper's) | {n_d} | {t_delaunay:.2f} | {rate_d / 1e6:.2f} M | 1.00x |")
    print(f"| median per cell (jaxstereo) | {args.points} | {t_median:.2f} | {args.points / t_median / 1e6:.2f} M "
          f"| {args.points / t_median / rate_d:.1f}x |")


if __name__ == "__main__":
    main()
