"""End-to-end reconstruction time of one wet pair versus bare SGBM on the same rectified pair.

Run: python benchmarks/bench_reconstruct.py [--size 2496x1664] [--scene breakwater|board]
Renders the pair once (synthetic flume), then times load -> rectify -> match -> triangulate -> write
(warm, after a first compiling run) and OpenCV's StereoSGBM alone on the rectified images, in one run.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import jax

import jaxstereo as js
from jaxstereo._flume_rig import RigSpec, flume_rig
from jaxstereo._images import read_image, write_image
from jaxstereo._matching import disparity_search_range, sgbm_disparity
from jaxstereo._reconstruct import ReconstructOptions, _disparity_range, _grey, reconstruct
from jaxstereo._rectify import rectification_maps, rectify, remap
from jaxstereo._render import render_view
from jaxstereo._rig import Rig
from jaxstereo._scenes import Breakwater, SlopingBoard, build_scene
from jaxstereo._survey import save_survey


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="2496x1664")
    parser.add_argument("--scene", choices=["breakwater", "board"], default="breakwater")
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args(argv)
    w, h = (int(v) for v in args.size.lower().split("x"))
    level = 0.158 if args.scene == "breakwater" else 0.18
    spec = Breakwater(seed=0) if args.scene == "breakwater" else SlopingBoard()
    left, right = flume_rig(RigSpec(image_size=(w, h), water_level_m=level))
    rig = Rig(left, right)
    water = js.Interface(level)
    tmp = Path(tempfile.mkdtemp(prefix="jaxstereo-bench-"))
    scene = build_scene(spec)
    for name, cam in (("left.png", left), ("right.png", right)):
        write_image(tmp / name, render_view(cam, scene.heightfield, water).image)
    options = ReconstructOptions(z_range_m=(-0.05, 0.45))

    def pipeline():
        t0 = time.perf_counter()
        a, b = read_image(tmp / "left.png"), read_image(tmp / "right.png")
        t1 = time.perf_counter()
        survey, summary = reconstruct(a, b, rig, level, options)
        t2 = time.perf_counter()
        save_survey(survey, tmp / "survey.npz")
        t3 = time.perf_counter()
        return t3 - t0, {"load": t1 - t0, **summary["seconds"], "write": t3 - t2}, len(survey)

    start = time.perf_counter()
    pipeline()
    first = time.perf_counter() - start
    runs = [pipeline() for _ in range(args.repeat)]
    total, stages, n_points = min(runs, key=lambda r: r[0])

    with jax.enable_x64(True):
        rect = rectify(left, right, water, "air")
        maps = [rectification_maps(rect, cam, s) for s, cam in enumerate((left, right))]
        a, b = read_image(tmp / "left.png"), read_image(tmp / "right.png")
        ra, rb = _grey(remap(a, maps[0])), _grey(remap(b, maps[1]))
        lo, num = disparity_search_range(*_disparity_range(rect, -0.05, 0.45), options.match.margin_px)
    sgbm = []
    for _ in range(args.repeat):
        start = time.perf_counter()
        sgbm_disparity(ra, rb, lo, num, options.match)
        sgbm.append(time.perf_counter() - start)
    t_sgbm = min(sgbm)

    print(f"{args.scene} {w}x{h}, {n_points} points, disparity search {num} px; first run (compiling) {first:.1f} s")
    print("| step | seconds | ratio to bare SGBM |")
    print("|---|---:|---:|")
    print(f"| bare SGBM on the rectified pair (baseline) | {t_sgbm:.2f} | 1.00x |")
    print(f"| jaxstereo end to end (load, rectify, match, triangulate, write) | {total:.2f} | {total / t_sgbm:.2f}x |")
    for stage, seconds in stages.items():
        print(f"|   {stage} | {seconds:.2f} | {seconds / t_sgbm:.2f}x |")


if __name__ == "__main__":
    main()
