"""Synthetic-flume rendering time: a stereo pair of the breakwater model, wet and dry, after compilation.

Run: python benchmarks/bench_render.py [--size 1728x1152] [--out DIR]
Prints a table (seconds per pair with one, two and three of the heightfield's bounds skipping empty space, ratio
to one bound, rendered in the same run) and saves the images.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax

import jaxstereo as js
from jaxstereo._app.images import write_image
from jaxstereo._synthetic.flume_rig import RigSpec, flume_rig
from jaxstereo._synthetic.render import RenderOptions, render_view
from jaxstereo._synthetic.scenes import Breakwater, build_scene


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="1728x1152")
    parser.add_argument("--out", default="benchmarks/out")
    args = parser.parse_args(argv)
    w, h = (int(v) for v in args.size.lower().split("x"))
    out = Path(args.out)

    start = time.perf_counter()
    scene = build_scene(Breakwater(seed=0))
    build_s = time.perf_counter() - start
    left, right = flume_rig(RigSpec(image_size=(w, h), water_level_m=0.158))
    water = js.Interface(0.158)
    options = RenderOptions()

    with jax.enable_x64(True):
        start = time.perf_counter()
        render_view(left, scene.heightfield, water, RenderOptions(chunk=options.chunk))  # compile + first run
        first_s = time.perf_counter() - start
        for levels in (1, 2):  # compile the fewer-level variants outside the timing too
            render_view(left, scene.heightfield, water, RenderOptions(skip_levels=levels))
        rows = []
        for name, interface in (("dry pair", None), ("wet pair, water 0.158 m", water)):
            for levels in (1, 2, 3):
                start = time.perf_counter()
                level_options = RenderOptions(skip_levels=levels)
                views = [render_view(cam, scene.heightfield, interface, level_options) for cam in (left, right)]
                rows.append((name, levels, time.perf_counter() - start))
            tag = "wet" if interface is not None else "dry"
            for side, view in zip(("left", "right"), views):
                write_image(out / f"breakwater_{tag}_{side}.png", view.image)

    print(f"breakwater scene ({scene.rocks['center'].shape[0]} units) built in {build_s:.1f} s; "
          f"first view with compilation {first_s:.1f} s; images in {out}/")
    print(f"| render {w}x{h} stereo pair | bounds that skip empty space (`skip_levels`) | seconds | "
          "ratio to one bound (the baseline) |")
    print("|---|---:|---:|---:|")
    for name, levels, seconds in rows:
        baseline = next(s for n, k, s in rows if n == name and k == 1)
        print(f"| {name} | {levels} | {seconds:.1f} | {seconds / baseline:.2f}x |")


if __name__ == "__main__":
    main()
