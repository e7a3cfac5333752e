"""The POV-Ray development flume seen by cameras of another resolution: every image resampled by one factor.

A rig whose cameras have fewer (or more) pixels over the same field of view, as a camera of another sensor or
mode would: each JPEG image resampled by `--scale` (OpenCV's area interpolation when shrinking, bilinear when
growing; pixel centres mapped as `x' = (x + 0.5) s - 0.5`) and written as PNG, with no second compression, and the
truth's camera matrix scaled with it. The scene, its truth surfaces, the water and the rigs' poses are unchanged.
Every setting of jaxstereo counted in pixels (SGBM's block, the sub-pixel windows, the reach of the occlusion and
fattening filters, the ray-gap tolerance) then meets the scene at another size. The scorecard runs on it as on the
original:

    python experiments/scaled_rig_data.py /tmp/scaled --scale 0.75
    flume-score --data /tmp/scaled --work /tmp/scaled-work

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


def scaled_matrix(K, scale: float) -> list:
    """The camera matrix `K` (3x3, pixels) of an image resampled by `scale`, pixel centres at whole numbers."""
    K = np.asarray(K, float).copy()
    K[0, 0] *= scale
    K[1, 1] *= scale
    K[:2, 2] = (K[:2, 2] + 0.5) * scale - 0.5
    return K.tolist()


def write_scaled(source: Path, out: Path, scale: float) -> int:
    """Write the copy of the flume `source` resampled by `scale` into `out`; returns the number of images written."""
    if not 0.1 <= scale <= 4.0:
        raise SystemExit(f"--scale must lie between 0.1 and 4, got {scale}")
    truth = json.loads((source / "truth.json").read_text())
    width, height = (round(n * scale) for n in truth["size"])
    if not np.isclose(width / truth["size"][0], height / truth["size"][1], rtol=1e-3):
        raise SystemExit(f"--scale {scale} does not keep the {truth['size'][0]}x{truth['size'][1]} images' aspect")
    interpolation = cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
    written = 0
    for path in sorted(source.rglob("*.jpg")):
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise SystemExit(f"cannot read {path}")
        target = out / path.relative_to(source).with_suffix(".png")
        target.parent.mkdir(parents=True, exist_ok=True)
        resized = cv2.resize(image, (width, height), interpolation=interpolation)
        if not cv2.imwrite(str(target), resized, [cv2.IMWRITE_PNG_COMPRESSION, 1]):
            raise SystemExit(f"cannot write {target}")
        written += 1
    truth["K"] = scaled_matrix(truth["K"], width / truth["size"][0])
    truth["size"] = [width, height]
    truth["images"] = f"png (the JPEG images resampled by {scale:g})"
    (out / "truth.json").write_text(json.dumps(truth))
    for name in ("breakwater_gt.npz", "opencv-baseline.json"):
        if (source / name).exists():
            shutil.copy(source / name, out / name)
    return written


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("output", type=Path, help="folder for the resampled copy (made if missing)")
    parser.add_argument("--scale", type=float, default=0.75, help="the images' size factor (default 0.75)")
    parser.add_argument("--data", type=Path, default=DEV, help=f"the flume to resample (default: {DEV})")
    args = parser.parse_args()
    args.output.mkdir(parents=True, exist_ok=True)
    count = write_scaled(args.data, args.output, args.scale)
    print(f"{count} images resampled by {args.scale:g} into {args.output}")


if __name__ == "__main__":
    main()
