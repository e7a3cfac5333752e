"""What the error bars cost: warm `reconstruct` with and without uncertainty propagation, in one run.

Run: python benchmarks/bench_uncertainty.py [--data ../shared/data/povray-flume-dev] [--repeat 3]

On the 1728x1152 wet board and breakwater pairs of the POV-Ray development flume, with a rig calibrated from
its own boards: `reconstruct` with `ReconstructOptions(uncertainty=False)` (the baseline: no disparity std,
no JVP, no covariance table) against the default (each point's covariance), warm, best of `--repeat`, and
the ratio. The issue's bound: propagation costs at most 50 % on top (ratio <= 1.5).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

from bench_reconstruct import _best  # the benchmarks folder is on the path when run as a script

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DATA = ROOT.parent / "shared" / "data" / "povray-flume-dev"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", default=str(DEFAULT_DATA), help="the development flume's folder")
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    data = Path(args.data)
    if not (data / "truth.json").is_file():
        sys.exit(f"no development flume at {data}")
    import jaxstereo as js
    from jaxstereo._app.cli import main as cli

    with tempfile.TemporaryDirectory() as work:
        rig_path = Path(work) / "rig.json"
        if cli(["calibrate", "--left", str(data / "calib" / "*_L.jpg"), "--right", str(data / "calib" / "*_R.jpg"),
                "--board", "chessboard:9x6:0.04", "--origin-left", str(data / "origin_L.jpg"),
                "--origin-right", str(data / "origin_R.jpg"), "-o", str(rig_path)]) != 0:
            sys.exit("calibration failed")
        rig = js.load_rig(rig_path)
    rows = []
    for scene in ("board_wet", "bw_I_wet"):
        left, right = (js.read_image(data / f"{scene}_{side}.jpg") for side in "LR")
        timings = {}
        for label, flag in (("without", False), ("with", True)):
            options = js.ReconstructOptions(uncertainty=flag)
            js.reconstruct(left, right, rig, 0.165, options)  # compile
            timings[label], (survey, summary) = _best(lambda: js.reconstruct(left, right, rig, 0.165, options),
                                                      args.repeat)
        rows.append((scene, len(survey), timings["without"], timings["with"], summary["seconds"]))
    print("\n| pair (1728x1152) | points | reconstruct, no uncertainty (s) | with covariance (s) | ratio |")
    print("|---|---:|---:|---:|---:|")
    for scene, n, base, full, _ in rows:
        print(f"| {scene} | {n} | {base:.2f} | {full:.2f} | {full / base:.2f}x |")
    print("\nstages of the last run with covariance (s): " +
          ", ".join(f"{k} {v:.2f}" for scene, *_, seconds in rows[-1:] for k, v in seconds.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
