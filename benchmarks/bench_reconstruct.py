"""Reconstruction speed on the POV-Ray development flume: jaxstereo against the plain OpenCV pipeline.

Run: python benchmarks/bench_reconstruct.py [--data ../shared/data/povray-flume-dev] [--repeat 3]

One table, all in this run, on the 1728x1152 wet breakwater pair (bw_I_wet) with a rig calibrated from the
flume's own boards:
- the plain OpenCV pipeline a user would write (baseline): load, stereoRectify + remap, colour SGBM 3-way,
  reprojectImageTo3D, save; warm, best of `--repeat`;
- jaxstereo's warm `reconstruct` in this process (load, rectify through the water, colour SGBM, exact
  epipolar curves, exact triangulation, save), best of `--repeat`;
- bare colour SGBM as flume-score runs it, and a fresh `jaxstereo reconstruct` process (the command line,
  imports, the persistent compilation cache warm from an earlier run, the preview figure included; best of
  `--repeat` after a first run that may fill the cache).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import jax
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DATA = ROOT.parent / "shared" / "data" / "povray-flume-dev"


def _calibrate(data: Path, work: Path) -> Path:
    rig = work / "rig.json"
    from jaxstereo._app.cli import main

    if main(["calibrate", "--left", str(data / "calib" / "*_L.jpg"), "--right", str(data / "calib" / "*_R.jpg"),
             "--board", "chessboard:9x6:0.04", "--origin-left", str(data / "origin_L.jpg"),
             "--origin-right", str(data / "origin_R.jpg"), "-o", str(rig)]) != 0:
        sys.exit("calibration failed")
    return rig


def _plain_opencv(left_path, right_path, rig: dict, out: Path) -> int:
    """What a user writes with OpenCV alone (refraction ignored): the baseline's work, step for step."""
    L, R = cv2.imread(str(left_path)), cv2.imread(str(right_path))
    size = tuple(rig["image_size"])
    Ks = [np.array([[c["fx"], 0, c["cx"]], [0, c["fy"], c["cy"]], [0, 0, 1]]) for c in (rig["left"], rig["right"])]
    ds = [np.asarray(c["dist"][:5], float) for c in (rig["left"], rig["right"])]
    Rl, Rr = (np.asarray(rig[s]["R"], float) for s in ("left", "right"))
    tl, tr = (np.asarray(rig[s]["t"], float) for s in ("left", "right"))
    Rrel, Trel = Rr @ Rl.T, (tr - Rr @ Rl.T @ tl).reshape(3, 1)
    R1, R2, P1, P2, Q, _, _ = cv2.stereoRectify(Ks[0], ds[0], Ks[1], ds[1], size, Rrel, Trel, alpha=0)
    maps = [cv2.initUndistortRectifyMap(K, d, Rx, P, size, cv2.CV_32FC1) for K, d, Rx, P in
            ((Ks[0], ds[0], R1, P1), (Ks[1], ds[1], R2, P2))]
    a = cv2.remap(L, *maps[0], cv2.INTER_LINEAR)
    b = cv2.remap(R, *maps[1], cv2.INTER_LINEAR)
    sgbm = cv2.StereoSGBM_create(0, 256, 5, 8 * 3 * 25, 32 * 3 * 25, 1, 0, 10, 100, 2, cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    disparity = sgbm.compute(a, b).astype(np.float32) / 16.0
    points = cv2.reprojectImageTo3D(disparity, Q)
    ok = disparity > 0
    np.savez(out, points=points[ok], colors=a[ok])
    return int(ok.sum())


def _bare_sgbm(left_path, right_path) -> float:
    """Bare colour SGBM as flume-score times it: both JPEGs read, the matcher made, the pair matched."""
    start = time.perf_counter()
    L, R = cv2.imread(str(left_path)), cv2.imread(str(right_path))
    sgbm = cv2.StereoSGBM_create(0, 256, 5, 8 * 3 * 25, 32 * 3 * 25, 1, 0, 10, 100, 2, cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    sgbm.compute(L, R)
    return time.perf_counter() - start


def _best(fn, repeat: int) -> tuple[float, object]:
    times, result = [], None
    for _ in range(repeat):
        start = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - start)
    return min(times), result


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args(argv)
    if not (args.data / "truth.json").exists():
        sys.exit(f"no development flume at {args.data}")
    work = Path(tempfile.mkdtemp(prefix="jaxstereo-bench-"))
    rig_path = _calibrate(args.data, work)
    rig_json = json.loads(rig_path.read_text())
    left, right = args.data / "bw_I_wet_L.jpg", args.data / "bw_I_wet_R.jpg"
    level = json.loads((args.data / "truth.json").read_text())["scenes"]["bw_I_wet"]["water_level"]

    import jaxstereo as js

    rig = js.load_rig(rig_path)

    def ours():
        survey, _ = js.reconstruct(js.read_image(left), js.read_image(right), rig, level)
        js.save_survey(survey, work / "survey.npz")
        return len(survey)

    ours()  # compile
    t_plain, n_plain = _best(lambda: _plain_opencv(left, right, rig_json, work / "plain.npz"), args.repeat)
    t_ours, n_ours = _best(ours, args.repeat)
    t_sgbm = min(_bare_sgbm(left, right) for _ in range(args.repeat))
    command = [sys.executable, "-m", "jaxstereo", "reconstruct", str(left), str(right), "--rig", str(rig_path),
               "--water-level", str(level), "-o", str(work / "cli.npz")]
    fresh = []
    for _ in range(1 + args.repeat):  # the first may fill the persistent compilation cache; the rest find it warm
        start = time.perf_counter()
        subprocess.run(command, check=True, capture_output=True)
        fresh.append(time.perf_counter() - start)
    print(f"POV-Ray development flume, bw_I_wet, 1728x1152, jax {jax.__version__}")
    print("| step | seconds | ratio |")
    print("|---|---:|---:|")
    print(f"| plain OpenCV pipeline, warm ({n_plain} points, refraction ignored) (baseline) | {t_plain:.2f} | 1.00x |")
    print(f"| jaxstereo reconstruct, warm ({n_ours} points, exact refraction) | {t_ours:.2f} | "
          f"{t_ours / t_plain:.2f}x |")
    print(f"| bare colour SGBM, as flume-score runs it (baseline) | {t_sgbm:.2f} | 1.00x |")
    warm = min(fresh[1:])
    print(f"| fresh `jaxstereo reconstruct` process, compilation cache warm (best of {args.repeat}) | {warm:.2f} | "
          f"{warm / t_sgbm:.2f}x |")
    print(f"| fresh process, first run (may compile) | {fresh[0]:.2f} | {fresh[0] / t_sgbm:.2f}x |")


if __name__ == "__main__":
    main()
