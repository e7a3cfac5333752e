"""The POV-Ray development flume seen through real lenses: every image warped by a known lens distortion.

The flume's cameras are ideal pinholes. A real rig's are not: each lens bends the image by its own radial and
tangential distortion, and calibration, rectification and every ray of the survey must undo it. Here each camera
gets OpenCV's distortion model with the coefficients of a 35 mm lens, different for the left and the right one
(`LENSES`: barrel distortion, the corners moved inward by about 9 pixels), and each image is resampled as that
camera would have recorded it: a pixel of the distorted image takes the colour the ideal image has where its ray
lands (cubic B-spline interpolation; written as PNG, with no second compression). The focal length grows by `ZOOM`, so
that every pixel's ray, the corners' too, lands inside the ideal image and no pixel is left black. The truth's
camera matrix follows (`distorted_matrix`) and records the coefficients (`lens_distortion`); the poses, the scene,
its truth surfaces and the water are unchanged. The scorecard then runs on it as on the original:

    python experiments/distorted_rig_data.py /tmp/distorted
    flume-score --data /tmp/distorted --work /tmp/distorted-work

Standalone: not one of the registered experiments (`python -m experiments`).
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
from scipy import ndimage

DEV = Path(__file__).resolve().parents[2] / "shared" / "data" / "povray-flume-dev"
# OpenCV's (k1, k2, p1, p2, k3) of each camera's lens, in normalised image coordinates.
LENSES = {"L": (-0.08, 0.12, 4e-4, -3e-4, 0.0), "R": (-0.07, 0.10, -2e-4, 5e-4, 0.0)}
ZOOM = 1.015  # the distorted cameras' focal length over the ideal ones'


def distorted_matrix(K, zoom: float = ZOOM) -> np.ndarray:
    """The camera matrix (3x3, pixels) of the distorted camera: the focal lengths times `zoom`, the same
    principal point."""
    K = np.asarray(K, float).copy()
    K[0, 0] *= zoom
    K[1, 1] *= zoom
    return K


def ideal_pixels(K, dist, size: tuple[int, int], zoom: float = ZOOM) -> tuple[np.ndarray, np.ndarray]:
    """For each pixel of the distorted image (`size` (w, h)), the pixel of the ideal pinhole image (camera matrix
    `K`) its ray lands on: two (h, w) float32 maps, x and y, for `resample`. The distortion `dist` (k1, k2, p1, p2,
    k3) is inverted by fixed-point iteration on the normalised plane, until it moves no point by more than 1e-12."""
    w, h = size
    Kd = distorted_matrix(K, zoom)
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    xd, yd = (u - Kd[0, 2]) / Kd[0, 0], (v - Kd[1, 2]) / Kd[1, 1]
    k1, k2, p1, p2, k3 = (float(c) for c in dist)
    x, y = xd.copy(), yd.copy()
    for _ in range(100):
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        nx = (xd - (2 * p1 * x * y + p2 * (r2 + 2 * x * x))) / radial
        ny = (yd - (p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)) / radial
        step = max(np.abs(nx - x).max(), np.abs(ny - y).max())
        x, y = nx, ny
        if step < 1e-12:
            break
    else:
        raise SystemExit(f"the distortion {dist} could not be inverted over the image")
    K = np.asarray(K, float)
    return (K[0, 0] * x + K[0, 2]).astype(np.float32), (K[1, 1] * y + K[1, 2]).astype(np.float32)


def resample(image: np.ndarray, map_x: np.ndarray, map_y: np.ndarray) -> np.ndarray:
    """`image` (h, w[, c]) uint8 sampled at the (h, w) pixel positions `map_x`, `map_y` by cubic B-spline
    interpolation (scipy), rounded to uint8. (OpenCV's `remap` quantises the positions to 1/32 pixel and its
    cubic kernel moves the chessboards' corners found in its output by 0.04-0.05 px RMS, against 0.006-0.011 px
    here: a camera's own images carry no such error.)"""
    channels = image.reshape(*image.shape[:2], -1).astype(np.float32)
    out = np.stack([ndimage.map_coordinates(channels[..., c], [map_y, map_x], order=3, mode="nearest")
                    for c in range(channels.shape[2])], axis=-1)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8).reshape(image.shape)


def write_distorted(source: Path, out: Path, lenses: dict = LENSES, zoom: float = ZOOM) -> int:
    """Write the copy of the flume `source` seen through `lenses` ({"L": dist, "R": dist}) into `out`; returns the
    number of images written. Refused when a distorted pixel's ray leaves the ideal image (a larger `zoom` is
    needed)."""
    truth = json.loads((source / "truth.json").read_text())
    size = tuple(truth["size"])
    maps = {side: ideal_pixels(truth["K"], dist, size, zoom) for side, dist in lenses.items()}
    for side, (mx, my) in maps.items():
        if mx.min() < 0 or my.min() < 0 or mx.max() > size[0] - 1 or my.max() > size[1] - 1:
            raise SystemExit(f"the {side} lens's corners see outside the ideal image: raise the zoom above {zoom}")
    written = 0
    for path in sorted(source.rglob("*.jpg")):
        side = path.stem.rsplit("_", 1)[-1]
        if side not in maps:
            raise SystemExit(f"{path}: not a left (_L) or right (_R) image")
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise SystemExit(f"cannot read {path}")
        warped = resample(image, *maps[side])
        target = out / path.relative_to(source).with_suffix(".png")
        target.parent.mkdir(parents=True, exist_ok=True)
        if not cv2.imwrite(str(target), warped, [cv2.IMWRITE_PNG_COMPRESSION, 1]):
            raise SystemExit(f"cannot write {target}")
        written += 1
    truth["K"] = distorted_matrix(truth["K"], zoom).tolist()
    truth["lens_distortion"] = {side: list(dist) for side, dist in lenses.items()}
    truth["images"] = f"png (the JPEG images seen through lenses with distortion {lenses}, focal length x {zoom:g})"
    (out / "truth.json").write_text(json.dumps(truth))
    for name in ("breakwater_gt.npz", "opencv-baseline.json"):
        if (source / name).exists():
            shutil.copy(source / name, out / name)
    return written


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("output", type=Path, help="folder for the distorted copy (made if missing)")
    parser.add_argument("--data", type=Path, default=DEV, help=f"the flume to distort (default: {DEV})")
    args = parser.parse_args()
    args.output.mkdir(parents=True, exist_ok=True)
    count = write_distorted(args.data, args.output)
    print(f"{count} images seen through the lenses into {args.output}")


if __name__ == "__main__":
    main()
