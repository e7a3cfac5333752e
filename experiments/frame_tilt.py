"""How far the world frame's tilt, from the origin board, errs against the std that calibration reports for it.

For each flume folder of `povray_rig.py` (or the development flume) given: detect the boards, calibrate as
`jaxstereo calibrate` does (`calibrate_stereo` with the origin pair in the joint adjustment, then
`world_frame_rig`), and compare the world frame with the truth's: the tilt of its z axis about its x and y axes
(mrad) and the left camera's height (mm), each beside its std from the rig's `frame_cov` (the height's with
`focal_std_rel` too), for each value of the corners' smooth error given (`--smooth-px`, the frame covariance's
`SMOOTH_CORNER_ERROR_PX`; 0: independent corner noise alone). The last lines give the errors in units of their
std: the RMS over every axis and the count past 2 and 3 std, what a std that covers the real error keeps near 1,
5 % and 0.3 %. With `--floor`, the floor around the origin board too: the origin pair surveyed densely in air
(`reconstruct`), a plane fitted to the points outside the board (two squares' margin) by least squares with 3-MAD
rejection, and its tilt's error beside the board's (mrad RMS over the axes, and of their mean).

Run: python experiments/frame_tilt.py FLUME [FLUME ...] [--smooth-px 0 0.01] [--floor]
     (each FLUME with calib/, origin_{L,R}.jpg and truth.json)
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a script: `experiments` and the checkout


def calibrated(folder: Path):
    """`(stereo, board, origin_left, origin_right, truth)` for a flume folder, calibrated as the command does."""
    from jaxstereo import BoardSpec, calibrate_stereo, detect_all

    truth = json.loads((folder / "truth.json").read_text())
    board = BoardSpec.parse("chessboard:%dx%d:%g" % (*truth["pattern"], truth["square"]))
    ext = ".jpg" if (folder / "origin_L.jpg").exists() else ".png"
    paths = {s: sorted((folder / "calib").glob(f"*_{s}{ext}")) for s in "LR"}
    read = [cv2.imread(str(p), cv2.IMREAD_COLOR) for s in "LR" for p in paths[s]]
    origin = [cv2.imread(str(folder / f"origin_{s}{ext}"), cv2.IMREAD_COLOR) for s in "LR"]
    size = (read[0].shape[1], read[0].shape[0])
    found = detect_all(read + origin, board)
    n = len(paths["L"])
    stereo = calibrate_stereo(found[:n], found[n:2 * n], board, size, origin=(found[-2], found[-1]))
    return stereo, board, found[-2], found[-1], truth


def frame_errors(rig, report: dict, truth: dict) -> dict:
    """The frame's tilt errors (mrad, our x and y axes), the left camera's height error (mm) and their stds."""
    R_o, t_o = np.asarray(rig.left.pose.R), np.asarray(rig.left.pose.t)
    true_left = truth["rigs"]["main"]["L"]
    R_t, t_t = np.asarray(true_left["R"]), np.asarray(true_left["t"])
    up_o, up_t = R_o[:, 2], R_t[:, 2]  # world z in the left camera's axes
    tilt = R_o.T @ np.cross(up_t, up_o) * 1e3  # mrad, about our world axes
    centre = -R_o.T @ t_o
    height_err = (centre[2] - (-R_t.T @ t_t)[2]) * 1e3
    cov = np.asarray(report["frame_cov"])
    gradient = np.array([centre[1], -centre[0], 0, 0, 0, 1.0])
    focal = rig.calibration.get("focal_std_rel", 0.0) * centre[2]
    height_std = np.sqrt(gradient @ cov @ gradient + focal**2) * 1e3
    return {"tilt": tilt[:2], "tilt_std": 1e3 * np.sqrt(np.diag(cov)[:2]), "height": height_err,
            "height_std": height_std, "noise": report.get("frame_noise_px", np.nan)}


def floor_tilt_errors(rig, report: dict, board, folder: Path, truth: dict) -> np.ndarray:
    """The tilt error (mrad, slopes of z along our x and y) of the floor's plane around the origin board, surveyed
    from the origin pair, and the board's own (its plane is z = 0): `[[floor x, floor y], [board x, board y]]`."""
    from jaxstereo import reconstruct

    ext = ".jpg" if (folder / "origin_L.jpg").exists() else ".png"
    left, right = (cv2.cvtColor(cv2.imread(str(folder / f"origin_{s}{ext}")), cv2.COLOR_BGR2RGB) for s in "LR")
    points = reconstruct(left, right, rig)[0].points
    margin = 2 * truth["square"]
    lo, hi = board.corners[:, :2].min(axis=0) - margin, board.corners[:, :2].max(axis=0) + margin
    xy = points[:, :2] * (np.array([1.0, -1.0]) if report["z_flipped"] else 1.0)  # board axes
    on_board = np.all((xy > lo) & (xy < hi), axis=1)
    floor = points[~on_board & (np.abs(points[:, 2]) < 0.03)]
    design = np.column_stack([np.ones(len(floor)), floor[:, :2]])
    keep = np.ones(len(floor), bool)
    for _ in range(5):
        coef = np.linalg.lstsq(design[keep], floor[keep, 2], rcond=None)[0]
        residual = floor[:, 2] - design @ coef
        keep = np.abs(residual) < 3 * 1.4826 * np.median(np.abs(residual[keep]))
    up = np.asarray(rig.left.pose.R).T @ np.asarray(truth["rigs"]["main"]["L"]["R"]) @ [0.0, 0.0, 1.0]
    true_slope = -up[:2] / up[2]  # the true floor's slopes in our frame
    return 1e3 * np.array([coef[1:] - true_slope, -true_slope])


def main(argv=None) -> None:
    from jaxstereo import world_frame_rig
    from jaxstereo._calibration import calibration

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("flumes", nargs="+", type=Path)
    parser.add_argument("--smooth-px", type=float, nargs="+", default=[calibration.SMOOTH_CORNER_ERROR_PX],
                        help="the corners' smooth error (px) for the frame's covariance, one run each")
    parser.add_argument("--floor", action="store_true", help="the floor's plane around the board too (slower)")
    args = parser.parse_args(argv)
    floors = []
    z = {s: {"tilt": [], "height": []} for s in args.smooth_px}
    print("| flume | smooth error (px) | tilt error x / y (mrad) | its std x / y | height error (mm) | its std | "
          "noise (px) |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    default = calibration.SMOOTH_CORNER_ERROR_PX
    for folder in args.flumes:
        stereo, board, origin_left, origin_right, truth = calibrated(folder)
        for smooth in args.smooth_px:
            calibration.SMOOTH_CORNER_ERROR_PX = smooth  # the frame is the same for each: only its covariance moves
            rig, report = world_frame_rig(stereo, board, origin_left, origin_right)
            e = frame_errors(rig, report, truth)
            z[smooth]["tilt"] += list(e["tilt"] / e["tilt_std"])
            z[smooth]["height"].append(e["height"] / e["height_std"])
            tilt, std = e["tilt"], e["tilt_std"]
            print(f"| {folder.name} | {smooth:g} | {tilt[0]:+.2f} / {tilt[1]:+.2f} | {std[0]:.2f} / {std[1]:.2f} | "
                  f"{e['height']:+.3f} | {e['height_std']:.3f} | {e['noise']:.3f} |", flush=True)
        calibration.SMOOTH_CORNER_ERROR_PX = default
        if args.floor:
            floors.append(floor_tilt_errors(rig, report, board, folder, truth))
            (fx, fy), (bx, by) = floors[-1]
            print(f"{folder.name}: tilt error of the floor's plane {fx:+.2f} / {fy:+.2f} mrad, of the board's "
                  f"{bx:+.2f} / {by:+.2f}", flush=True)
    for smooth in args.smooth_px:
        for name, values in z[smooth].items():
            values = np.asarray(values)
            print(f"smooth error {smooth:g} px, {name}: errors / std RMS {np.sqrt(np.mean(values**2)):.2f} over "
                  f"{len(values)}, past 2 std {np.sum(abs(values) > 2)}, past 3 std {np.sum(abs(values) > 3)}")
    if floors:
        floor, on_board = (np.concatenate([f[k] for f in floors]) for k in (0, 1))
        rms = {name: float(np.sqrt(np.mean(v**2))) for name, v in
               (("floor", floor), ("board", on_board), ("mean", (floor + on_board) / 2))}
        print(f"tilt error RMS over {len(floor)} axes (mrad): the floor's plane {rms['floor']:.2f}, the board's "
              f"{rms['board']:.2f}, their mean {rms['mean']:.2f}; correlation {np.corrcoef(floor, on_board)[0, 1]:.2f}")


if __name__ == "__main__":
    main()
