"""Water-level refinement as users run it: `refine_rig` twice in one process, scipy on the same problem,
and the `jaxstereo refine` command on a 1728x1152 pair of the POV-Ray development flume.

Run: python benchmarks/bench_refine.py [--correspondences 2000] [--data ../shared/data/povray-flume-dev]

- `refine_rig` on exact synthetic correspondences (realistic rig, 0.2 px noise, floor control, level only):
  the first call compiles, the second (same padded size) must not;
- scipy's `least_squares` (MINPACK LM, the same jitted residuals and Jacobian) from the same start to the
  same minimum, as a baseline;
- a fresh `jaxstereo refine` process (dense correspondences, floor control), run twice: the second finds
  JAX's persistent compilation cache warm.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from scipy.optimize import least_squares

import jaxstereo as js
from jaxstereo._stereo.refine import refine_problem
from jaxstereo._synthetic.flume_rig import flume_rig, realistic_rig_spec
from jaxstereo._synthetic.matches import surface_correspondences
from jaxstereo._synthetic.scenes import Breakwater, build_scene

ROOT = Path(__file__).resolve().parents[1]
LEVEL = 0.158


def _timed(fn):
    start = time.perf_counter()
    out = fn()
    return time.perf_counter() - start, out


def _library(n: int):
    spec = Breakwater(seed=3)
    scene = build_scene(spec)
    left, right = flume_rig(realistic_rig_spec(water_level_m=LEVEL))
    pl, pr, xyz = surface_correspondences(scene.heightfield, left, right, js.Interface(LEVEL), n, 0.2, 0)
    region = (-0.75, spec.toe_x_m - 2 * spec.dn50_m)
    call = lambda: js.refine_rig(js.Rig(left, right), pl, pr, LEVEL + 0.05, refine=("water",), control="floor",  # noqa: E731
                                 floor_region=region)
    first, result = _timed(call)
    second, result = _timed(call)
    floor = (np.asarray(xyz)[:, 2] < 1e-6) & (np.asarray(xyz)[:, 0] >= region[0]) & (np.asarray(xyz)[:, 0] <= region[1])
    with jax.enable_x64(True):
        fn, theta0, args = refine_problem(js.Rig(left, right), pl, pr, LEVEL + 0.05, refine=("water",), floor_mask=floor)
        f = jax.jit(lambda t: fn(t, args))
        J = jax.jit(jax.jacfwd(lambda t: fn(t, args)))
        f(theta0).block_until_ready(), J(theta0).block_until_ready()
        scipy_s, ref = _timed(lambda: least_squares(lambda t: np.asarray(f(jnp.asarray(t))), np.asarray(theta0),
                                                    jac=lambda t: np.asarray(J(jnp.asarray(t))), method="lm"))
    return first, second, result, scipy_s, LEVEL + 0.05 + ref.x[0] * 1e-2


def _command(data: Path):
    work = Path(tempfile.mkdtemp(prefix="jaxstereo-bench-refine-"))
    rig = work / "rig.json"
    subprocess.run([sys.executable, "-m", "jaxstereo", "calibrate", "--left", str(data / "calib" / "*_L.jpg"),
                    "--right", str(data / "calib" / "*_R.jpg"), "--board", "chessboard:9x6:0.04",
                    "--origin-left", str(data / "origin_L.jpg"), "--origin-right", str(data / "origin_R.jpg"),
                    "-o", str(rig)], check=True, capture_output=True)
    level = json.loads((data / "truth.json").read_text())["scenes"]["bw_I_wet"]["water_level"]
    command = [sys.executable, "-m", "jaxstereo", "refine", str(data / "bw_I_wet_L.jpg"), str(data / "bw_I_wet_R.jpg"),
               "--rig", str(rig), "--water-level-guess", str(level + 0.012), "--control", "floor", "--floor-x",
               "-0.15", "0.04", "--keep-guess", "-o", str(work / "wet.json")]
    return [_timed(lambda: subprocess.run(command, check=True, capture_output=True))[0] for _ in range(2)]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--correspondences", type=int, default=2000)
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data" / "povray-flume-dev")
    args = parser.parse_args(argv)
    first, second, result, scipy_s, scipy_level = _library(args.correspondences)
    level = result.parameters["water level (m)"][0]
    print(f"refine_rig, {args.correspondences} correspondences, floor control, level only (jax {jax.__version__})")
    print("| step | seconds | ratio |")
    print("|---|---:|---:|")
    print(f"| scipy least_squares (MINPACK LM), same residuals, compiled (baseline) | {scipy_s:.3f} | 1.00x |")
    print(f"| refine_rig, second call in this process (whole: gating, 3 solves, covariance) | {second:.3f} | "
          f"{second / scipy_s:.2f}x |")
    print(f"| refine_rig, first call (compiling) | {first:.3f} | {first / scipy_s:.2f}x |")
    print(f"\nsame minimum: refine_rig level {level:.6f} m, scipy {scipy_level:.6f} m "
          f"(difference {1e6 * abs(level - scipy_level):.1f} um)")
    if (args.data / "truth.json").exists():
        fresh = _command(args.data)
        print(f"\n`jaxstereo refine` on the POV-Ray flume's 1728x1152 pair, fresh process: {fresh[0]:.1f} s, "
              f"then {fresh[1]:.1f} s with the compilation cache warm")


if __name__ == "__main__":
    main()
