"""The POV-Ray development flume seen by its cameras turned about their optical axes, by a half or a quarter turn.

A half turn (`--turn 180`, the default): a rig mounted the other way round. Each image turned 180 degrees (the
principal point is the image's centre, and lens distortion, none here, is symmetric about it), left and right
swapped (the turned right camera is now on the left), and the truth's cameras turned with them (`R -> F R`,
`t -> F t`, F = diag(-1, -1, 1)). Its origin board is seen the other way round, so the calibrated world frame's x
runs down the breakwater's slope.

A quarter turn (`--turn 90`): the cameras side by side across the images' short side, as on a rig whose cameras sit
across the flume with the images' long side along it. Each image turned 90 degrees clockwise (`np.rot90(image, -1)`:
pixel (u, v) -> (h - 1 - v, u)), portrait, and the truth's cameras turned with it (F maps the camera frame's
x, y to -y, x), the left camera still the left one; the baseline runs down the images.

The scene, its truth surfaces and the water are unchanged. Images are written as PNG: the JPEG pixels turned,
with no second compression. The scorecard then runs on it as on the original:

    python experiments/turned_rig_data.py /tmp/turned [--turn 90]
    flume-score --data /tmp/turned --work /tmp/turned-work

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
TURNS = {  # camera frame turned about its optical axis: world -> camera rotations are left-multiplied by it
    180: np.diag([-1.0, -1.0, 1.0]),
    90: np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
}


def turned_camera(camera: dict, turn: int = 180) -> dict:
    """A truth.json camera (`R`, `t`: world -> camera) turned `turn` degrees (180 or 90, clockwise in the image)
    about its optical axis."""
    F = TURNS[turn]
    return {"R": (F @ np.asarray(camera["R"], float)).tolist(), "t": (F @ np.asarray(camera["t"], float)).tolist()}


def turned_image(image: np.ndarray, turn: int = 180) -> np.ndarray:
    """The image (h, w[, c]) as the camera turned `turn` degrees (180 or 90, clockwise) records it."""
    return np.ascontiguousarray(image[::-1, ::-1] if turn == 180 else np.rot90(image, -1))


def write_turned(source: Path, out: Path, turn: int = 180) -> int:
    """Write the copy of the flume `source` turned `turn` degrees into `out`; returns the number of images written."""
    if turn not in TURNS:
        raise SystemExit(f"turn must be one of {sorted(TURNS)} degrees, got {turn}")
    truth = json.loads((source / "truth.json").read_text())
    size = tuple(truth["size"])
    centre = np.asarray(truth["K"], float)[:2, 2]
    if not np.allclose(centre, (np.asarray(size) - 1) / 2):
        raise SystemExit(f"{source}: the principal point {centre} is not the image's centre: turning moves it")
    sides = (("L", "R"), ("R", "L")) if turn == 180 else (("L", "L"), ("R", "R"))
    written = 0
    for left in sorted(source.rglob("*_L.jpg")):
        stem = left.relative_to(source).as_posix()[: -len("_L.jpg")]
        (out / stem).parent.mkdir(parents=True, exist_ok=True)
        for side, other in sides:
            image = cv2.imread(str(source / f"{stem}_{side}.jpg"), cv2.IMREAD_UNCHANGED)
            if image is None:
                raise SystemExit(f"cannot read {source / f'{stem}_{side}.jpg'}")
            path = out / f"{stem}_{other}.png"
            if not cv2.imwrite(str(path), turned_image(image, turn), [cv2.IMWRITE_PNG_COMPRESSION, 1]):
                raise SystemExit(f"cannot write {path}")
            written += 1
    for rig in truth["rigs"].values():
        if turn == 180:
            rig["L"], rig["R"] = turned_camera(rig["R"]), turned_camera(rig["L"])
        else:
            rig["L"], rig["R"] = turned_camera(rig["L"], 90), turned_camera(rig["R"], 90)
    if turn == 90:  # portrait: the principal point, the image's centre, follows the size
        truth["size"] = [size[1], size[0]]
        K = np.asarray(truth["K"], float)
        K[0, 2], K[1, 2] = K[1, 2], K[0, 2]
        truth["K"] = K.tolist()
    how = "left and right swapped" if turn == 180 else "clockwise, portrait"
    truth["images"] = f"png (the JPEG images turned {turn} degrees, {how})"
    (out / "truth.json").write_text(json.dumps(truth))
    for name in ("breakwater_gt.npz", "opencv-baseline.json") if turn == 180 else ("breakwater_gt.npz",):
        if (source / name).exists():
            shutil.copy(source / name, out / name)
    return written


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("output", type=Path, help="folder for the turned copy (made if missing)")
    parser.add_argument("--data", type=Path, default=DEV, help=f"the flume to turn (default: {DEV})")
    parser.add_argument("--turn", type=int, default=180, choices=sorted(TURNS),
                        help="degrees about the optical axes: 180 (left and right swapped) or 90 (clockwise)")
    args = parser.parse_args()
    args.output.mkdir(parents=True, exist_ok=True)
    count = write_turned(args.data, args.output, args.turn)
    print(f"{count} images turned {args.turn} degrees into {args.output}")


if __name__ == "__main__":
    main()
