"""What the damage's error bars cost: `stretch_damage` once against `stretch_damage_with_sigma`, in one run.

Run: python benchmarks/bench_damage.py [--repeat 3]

On the synthetic breakwater (stage I against stage III, rocks from seed 7), its exact heightfields gridded at
5 mm over the whole model (301 x 201 cells; 27 cross-sections a Dn50 apart), with sigma layers as a survey's DEM
carries them (1 mm of matching noise correlated over 1 cm, 0.5 mm of calibration and of water level, none shared):
- the damage computed once (`stretch_damage`, the baseline), warm, best of `--repeat`;
- the damage with its standard deviations (`stretch_damage_with_sigma`: the same computation on 48 draws of the
  DEMs' errors), warm, best of `--repeat`, and its ratio to the baseline (49 computations at most).
A `batch` and the `damage` command run the second for every stage with error bars.
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np
from bench_reconstruct import _best  # the benchmarks folder is on the path when run as a script


def _dems():
    """Stage I and III DEMs (5 mm) of the synthetic breakwater's exact heightfields, with sigma layers."""
    import jaxstereo as js

    dems = []
    for damage in (None, js.Damage(half_length_dn50=3.0, half_width_dn50=3.0, deep_fraction=0.6, swl_m=0.158)):
        hf = js.build_scene(js.Breakwater(seed=7, damage=damage)).heightfield
        X, Y = np.meshgrid(hf.x, hf.y)
        nodes = np.stack([X.ravel(), Y.ravel(), np.asarray(hf.z).ravel()], axis=-1)
        x, y = (dems[0].x, dems[0].y) if dems else (None, None)
        dem = js.grid_median(nodes, 0.005, x, y)
        layers = {name: np.full(dem.z.shape, value) for name, value in
                  (("sigma_match", 0.001), ("sigma_calibration", 0.0005), ("sigma_level", 0.0005))}
        dems.append(dataclasses.replace(dem, **layers, correlation_m=0.01))
    return dems


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args(argv)
    from jaxstereo import Breakwater, stretch_damage
    from jaxstereo._surface.damage_uncertainty import DRAWS, stretch_damage_with_sigma

    before, after = _dems()
    spec = Breakwater()
    settings = (spec.dn50_m, spec.slope, 0.158, (spec.toe_x_m, 0.0))
    once, _ = _best(lambda: stretch_damage(before, after, *settings), args.repeat)
    result, sigma = stretch_damage_with_sigma(before, after, *settings)
    with_sigma, _ = _best(lambda: stretch_damage_with_sigma(before, after, *settings), args.repeat)
    print(f"synthetic breakwater, stage I against III, DEMs {before.z.shape[1]}x{before.z.shape[0]} cells at 5 mm, "
          f"{len(result.profiles)} profiles, S {result.averaged.S:.2f} +- {sigma.sigma['S']:.2f}")
    print("| step | seconds | ratio |")
    print("|---|---:|---:|")
    print(f"| stretch_damage, once (baseline) | {once:.3f} | 1.00x |")
    print(f"| stretch_damage_with_sigma ({DRAWS} draws) | {with_sigma:.2f} | {with_sigma / once:.1f}x |")


if __name__ == "__main__":
    main()
