"""The POV-Ray development flume as a rig whose right camera records the scene otherwise than its left.

POV-Ray renders both cameras of a rig alike; real cameras differ in exposure, gain, black level, white balance and
tone curve. This writes a copy of the flume whose right images (every one: the calibration boards, the origin board
and the scenes) pass through another response,

    right' = gain * 255 * (right / 255) ** gamma + black     (per channel: gains for R, G, B)

rounded to whole grey levels, and whose left images are the rendered ones. Every image is written as PNG, decoded
from the flume's JPEG once and not compressed again, and the truth is copied unchanged. The scorecard runs on it as
on the original:

    python experiments/exposed_rig_data.py /tmp/exposed --gains 0.90 0.85 0.80 --black 4
    flume-score --data /tmp/exposed --work /tmp/exposed-work

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


def respond(image_rgb: np.ndarray, gains, black: float, gamma: float) -> np.ndarray:
    """`image_rgb` (h, w, 3) uint8 through the response `gain * 255 * (level / 255) ** gamma + black` per channel
    (`gains` for R, G, B), rounded and clipped to 0-255."""
    levels = 255.0 * (image_rgb.astype(np.float64) / 255.0) ** gamma
    return np.clip(np.rint(levels * np.asarray(gains, float) + black), 0, 255).astype(np.uint8)


def write_exposed(source: Path, out: Path, gains, black: float, gamma: float) -> int:
    """Write the copy of the flume `source` into `out`, its right images through `respond`; returns the number of
    right images changed."""
    truth = json.loads((source / "truth.json").read_text())
    changed = 0
    for path in sorted(source.rglob("*.jpg")):
        image = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if image is None:
            raise SystemExit(f"cannot read {path}")
        if path.stem.endswith("_R"):
            image = respond(image[..., ::-1], gains, black, gamma)[..., ::-1]
            changed += 1
        target = out / path.relative_to(source).with_suffix(".png")
        target.parent.mkdir(parents=True, exist_ok=True)
        if not cv2.imwrite(str(target), image, [cv2.IMWRITE_PNG_COMPRESSION, 1]):
            raise SystemExit(f"cannot write {target}")
    truth["images"] = (f"png (the JPEG images; the right ones with gains {', '.join(f'{g:g}' for g in gains)} on "
                       f"R, G, B, black level {black:g}, gamma {gamma:g})")
    (out / "truth.json").write_text(json.dumps(truth))
    for name in ("breakwater_gt.npz", "opencv-baseline.json"):
        if (source / name).exists():
            shutil.copy(source / name, out / name)
    return changed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("output", type=Path, help="folder for the copy (made if missing)")
    parser.add_argument("--gains", type=float, nargs=3, default=(0.90, 0.85, 0.80), metavar=("R", "G", "B"),
                        help="the right camera's gain per channel (default 0.90 0.85 0.80)")
    parser.add_argument("--black", type=float, default=4.0, help="grey levels added (default 4)")
    parser.add_argument("--gamma", type=float, default=1.0, help="the right camera's gamma on 0-1 levels (default 1)")
    parser.add_argument("--data", type=Path, default=DEV, help=f"the flume to copy (default: {DEV})")
    args = parser.parse_args()
    if not all(g > 0 for g in args.gains) or not args.gamma > 0:
        raise SystemExit("--gains and --gamma must be positive")
    args.output.mkdir(parents=True, exist_ok=True)
    count = write_exposed(args.data, args.output, args.gains, args.black, args.gamma)
    print(f"{count} right images passed through the other response into {args.output}")


if __name__ == "__main__":
    main()
