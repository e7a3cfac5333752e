"""The POV-Ray development flume seen by its cameras turned 180 degrees about their optical axes.

A rig mounted the other way round: each image turned 180 degrees (the principal point is the image's centre, and
lens distortion, none here, is symmetric about it), left and right swapped (the turned right camera is now on the
left), and the truth's cameras turned with them (`R -> F R`, `t -> F t`, F = diag(-1, -1, 1)). The scene, its
truth surfaces and the water are unchanged. Images are written as PNG: the JPEG pixels turned, with no second
compression. The scorecard then runs on it as on the original:

    python experiments/turned_rig_data.py /tmp/turned
    flume-score --data /tmp/turned --work /tmp/turned-work

Its origin board is seen the other way round, so the calibrated world frame's x runs down the breakwater's slope.
Standalone: not one of the registered experiments (`python -m experiments`).
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import cv2
import numpy as np

DEV = Path(__file__).resolve().parents[2] / "shared" / "data" / "povray-flume-dev"
TURN = np.diag([-1.0, -1.0, 1.0])  # a camera frame turned 180 degrees about its optical axis


def turned_camera(camera: dict) -> dict:
    """A truth.json camera (`R`, `t`: world -> camera) turned 180 degrees about its optical axis."""
    return {"R": (TURN @ np.asarray(camera["R"], float)).tolist(), "t": (TURN @ np.asarray(camera["t"], float)).tolist()}


def write_turned(source: Path, out: Path) -> int:
    """Write the turned copy of the flume `source` into `out`; returns the number of images written."""
    truth = json.loads((source / "truth.json").read_text())
    size = tuple(truth["size"])
    centre = np.asarray(truth["K"], float)[:2, 2]
    if not np.allclose(centre, (np.asarray(size) - 1) / 2):
        raise SystemExit(f"{source}: the principal point {centre} is not the image's centre: turning moves it")
    written = 0
    for left in sorted(source.rglob("*_L.jpg")):
        stem = left.relative_to(source).as_posix()[: -len("_L.jpg")]
        (out / stem).parent.mkdir(parents=True, exist_ok=True)
        for side, other in (("L", "R"), ("R", "L")):
            image = cv2.imread(str(source / f"{stem}_{side}.jpg"), cv2.IMREAD_UNCHANGED)
            if image is None:
                raise SystemExit(f"cannot read {source / f'{stem}_{side}.jpg'}")
            path = out / f"{stem}_{other}.png"
            if not cv2.imwrite(str(path), image[::-1, ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 1]):
                raise SystemExit(f"cannot write {path}")
            written += 1
    for rig in truth["rigs"].values():
        rig["L"], rig["R"] = turned_camera(rig["R"]), turned_camera(rig["L"])
    truth["images"] = "png (the JPEG images turned 180 degrees, left and right swapped)"
    (out / "truth.json").write_text(json.dumps(truth))
    for name in ("breakwater_gt.npz", "opencv-baseline.json"):
        if (source / name).exists():
            shutil.copy(source / name, out / name)
    return written


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("output", type=Path, help="folder for the turned copy (made if missing)")
    parser.add_argument("--data", type=Path, default=DEV, help=f"the flume to turn (default: {DEV})")
    args = parser.parse_args()
    args.output.mkdir(parents=True, exist_ok=True)
    count = write_turned(args.data, args.output)
    print(f"{count} images turned into {args.output}")


if __name__ == "__main__":
    main()
