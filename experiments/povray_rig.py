"""A whole POV-Ray flume through a rig of one's choosing: its calibration photographs, origin board and scenes.

`povray_flume.py` renders new rocks and water depths through the development flume's own cameras. The project is
also judged on rigs it has not seen, so this makes the rig as well: two cameras at a height, a baseline along or
across the flume, toed in by a convergence angle, each tilted and turned by a few tenths of a degree at random (as
every real rig is), and a focal length of one's choosing. It renders with POV-Ray 3.7 (`povray` on the PATH, an
independent ray tracer; not a Python dependency, `apt install povray`):
- `calib/calib_NN_{L,R}.jpg`: a 9x6 chessboard of 40 mm squares at random poses in the air, seen whole by both
  cameras (tilted up to 40 degrees, turned at random);
- `origin_{L,R}.jpg`: the board lying on the floor, its top face at z = 0, its inner corner (0, 0) at `origin`;
- `board_wet_{L,R}.jpg`: the sloping board of the development flume (textured like the floor) half under water;
- the breakwater scenes of `povray_flume.py` (painted and grey rock, stages I and III, wet and dry);
- with `--oblique-deg`, a second rig as the development flume's oblique one: two cameras in front of the model,
  `--oblique-height` m above the floor, their axes tilted that many degrees from the vertical toward the model and
  both aimed at the sloping board's middle, `--oblique-baseline` m apart across the flume, jittered like the main
  rig; its own `calib_oblique/` photographs, `origin_oblique_{L,R}.jpg` (the board on the floor where the rig's
  axes meet it) and `oblique_board_wet_{L,R}.jpg` (flume-score's `oblique` check).
It writes `breakwater_gt.npz` and a `truth.json` that `flume-score --data DIR` reads
(`--only calibration,board,breakwater,grey,wetdry,refine-dem,refine-floor,damage,speed`, and `oblique` with
`--oblique-deg`). Nothing here uses
jaxstereo's geometry: the cameras are POV-Ray's own pinholes (`povray_flume.camera_pov`).

Run: python experiments/povray_rig.py OUT [--height 2.3] [--baseline 0.25] [--across] [--step 0] [--converge-deg 3]
     [--focal-px 3000] [--size 1728 1152] [--level 0.15] [--seed 7] [--oblique-deg 25 [--oblique-height 1.65]
     [--oblique-baseline 0.18]]
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from functools import partial
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a script: `experiments` and the checkout

from experiments import povray_flume as pf
from jaxstereo._app.io import atomic_path, write_text_atomic

SIZE = (1728, 1152)  # pixels, the default image size
SQUARE = 0.04  # m
PATTERN = (9, 6)  # inner corners
MARGIN_PX = 40  # every board corner this far inside both images
AIM = (0.5, 0.3)  # m, the point of the floor under the rig's middle: the model's middle
BOARD_PLANE = {"x0": 0.12, "length": 0.65, "drop": 0.28, "width": 0.6}  # the development flume's sloping board
# The sloping board's middle: where the oblique rig's axes meet (x m along the slope, the flume's middle, on the board)
BOARD_MIDDLE = np.array([BOARD_PLANE["x0"] + 0.3, 0.3, 0.3 * BOARD_PLANE["drop"] / BOARD_PLANE["length"]])


def _turn(axis, angle: float) -> np.ndarray:
    """Rotation matrix (3, 3) by `angle` radians about `axis`."""
    return cv2.Rodrigues(np.asarray(axis, float) / np.linalg.norm(axis) * angle)[0]


def _jitter(rng: np.random.Generator, jitter_deg: float) -> np.ndarray:
    """A camera's small random turn (3, 3): normal angles of `jitter_deg` degrees about x, y and z, drawn from `rng`."""
    tilt, turn, roll = rng.normal(0, np.radians(jitter_deg), 3)
    return _turn([1, 0, 0], tilt) @ _turn([0, 1, 0], turn) @ _turn([0, 0, 1], roll)


def make_rig(height: float, baseline: float, across: bool, converge_deg: float, seed: int,
             aim=AIM, jitter_deg: float = 0.4, step: float = 0.0) -> dict:
    """Two nadir cameras `height` m above the floor, `baseline` m apart (horizontally) along the flume (x) or
    `across` it (y), centred over `aim` (x, y) m, each toed in by half of `converge_deg` toward the other, then turned
    by a normal random rotation of `jitter_deg` degrees per axis (`seed`); the right camera `step` m higher than the
    left. **Returns:** {"L": {"R", "t"}, "R": {...}}, world -> camera (OpenCV axes: x right, y down, z forward),
    metres, as lists."""
    rng = np.random.default_rng(seed)
    base = np.array([0.0, 1.0, 0.0]) if across else np.array([1.0, 0.0, 0.0])
    down = np.array([0.0, 0.0, -1.0])
    nadir = np.stack([base, np.cross(down, base), down])  # rows: the camera's axes in the world
    rig = {}
    for side, sign in (("L", -1.0), ("R", 1.0)):
        centre = np.array([aim[0], aim[1], height + (step if side == "R" else 0.0)]) + sign * baseline / 2 * base
        toe_in = _turn(nadir[1], -sign * np.radians(converge_deg) / 2)  # about the camera's y axis, toward the other
        R = _jitter(rng, jitter_deg) @ nadir @ toe_in.T
        rig[side] = {"R": R.tolist(), "t": (-R @ centre).tolist()}
    return rig


def make_oblique_rig(tilt_deg: float, height: float, baseline: float, seed: int, aim=BOARD_MIDDLE,
                     jitter_deg: float = 0.4) -> dict:
    """Two cameras in front of the model (toward -x), `height` m above the floor, `baseline` m apart across the flume
    (the left one at +y), each aimed at `aim` (x, y, z) m, their mid-axis tilted `tilt_deg` degrees from the vertical
    toward +x, then turned by a normal random rotation of `jitter_deg` degrees per axis (`seed`): the development
    flume's oblique rig (25 degrees, 1.65 m, 0.18 m) in general. Image x runs toward -y, image y toward -x.
    **Returns:** {"L": {"R", "t"}, "R": {...}}, world -> camera (OpenCV axes), metres, as lists."""
    rng = np.random.default_rng(seed + 1000)  # not the main rig's draws
    tilt = np.radians(tilt_deg)
    reach = (height - aim[2]) / np.cos(tilt)
    middle = np.asarray(aim, float) - reach * np.array([np.sin(tilt), 0.0, -np.cos(tilt)])
    rig = {}
    for side, sign in (("L", 1.0), ("R", -1.0)):
        centre = middle + [0.0, sign * baseline / 2, 0.0]
        forward = (aim - centre) / np.linalg.norm(aim - centre)
        right = np.cross(forward, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        axes = np.stack([right, np.cross(forward, right), forward])  # rows: the camera's x, y, z in the world
        R = _jitter(rng, jitter_deg) @ axes
        rig[side] = {"R": R.tolist(), "t": (-R @ centre).tolist()}
    return rig


def project(K: np.ndarray, camera: dict, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole pixels (n, 2) of world points `X` (n, 3) and their depths (n,) in `camera` ({"R", "t"})."""
    x = X @ np.asarray(camera["R"]).T + np.asarray(camera["t"])
    return (x[:, :2] / x[:, 2:]) * [K[0, 0], K[1, 1]] + K[:2, 2], x[:, 2]


def board_corners() -> np.ndarray:
    """The board's inner corners (54, 3) and its sheet's four corners, in the board's frame (m)."""
    i, j = np.meshgrid(np.arange(PATTERN[0]), np.arange(PATTERN[1]))
    inner = np.stack([i.ravel() * SQUARE, j.ravel() * SQUARE, 0 * i.ravel()], 1)
    lo, hi = -1.6 * SQUARE, np.array(PATTERN) * SQUARE + 0.6 * SQUARE
    sheet = np.array([[lo, lo, 0], [hi[0], lo, 0], [hi[0], hi[1], 0], [lo, hi[1], 0]])
    return np.concatenate([inner, sheet])


def board_poses(K: np.ndarray, rig: dict, count: int, seed: int, max_tilt_deg: float = 40.0,
                size: tuple[int, int] = SIZE, follow_axis: bool = False) -> list[tuple]:
    """`count` poses (R, c) of the board in the air (board -> world: X = R p + c) whose every corner both cameras
    see `MARGIN_PX` inside their images of `size` (w, h) pixels, facing them: centres spread over the cameras'
    common view at 0.3-1.3 m above the floor (about the point under the cameras' middle, or with `follow_axis` about
    where their mean axis passes that height: an oblique rig), the board tilted up to `max_tilt_deg` from level
    toward a random azimuth, turned at random."""
    rng = np.random.default_rng(seed)
    local = board_corners()
    middle = local[:-4].mean(0)
    centres = [-np.asarray(rig[s]["R"]).T @ np.asarray(rig[s]["t"]) for s in "LR"]
    mid = np.mean(centres, 0)
    axis = np.mean([np.asarray(rig[s]["R"])[2] for s in "LR"], 0)
    # per metre below the cameras: how far the view's middle moves, and the spread's growth
    drift, widen = (axis[:2] / -axis[2], 1.0 / -axis[2]) if follow_axis else (np.zeros(2), 1.0)
    poses = []
    for _ in range(20000):
        if len(poses) == count:
            break
        z = rng.uniform(0.3, 1.3)
        reach = 0.45 * (centres[0][2] - z) * widen
        c = np.array([*(mid[:2] + drift * (mid[2] - z) + rng.uniform(-reach, reach, 2)), z])
        turned = _turn([0, 0, 1], rng.uniform(0, 2 * np.pi))
        azimuth = rng.uniform(0, 2 * np.pi)
        R = _turn([np.cos(azimuth), np.sin(azimuth), 0], np.radians(rng.uniform(0, max_tilt_deg))) @ turned
        X = (local - middle) @ R.T + c
        ok = True
        for side, centre in zip("LR", centres):
            uv, depth = project(K, rig[side], X)
            facing = np.dot(R[:, 2], centre - c) / np.linalg.norm(centre - c)
            ok &= bool((depth > 0).all() and facing > np.cos(np.radians(60))
                       and (uv >= MARGIN_PX).all() and (uv[:, 0] <= size[0] - 1 - MARGIN_PX).all()
                       and (uv[:, 1] <= size[1] - 1 - MARGIN_PX).all())
        if ok:
            poses.append((R, c - R @ middle))
    if len(poses) < count:
        raise RuntimeError(f"only {len(poses)} board poses fit both cameras' views")
    return poses


def board_pov(R: np.ndarray, c: np.ndarray) -> str:
    """The chessboard as POV-Ray draws it: a white sheet, 10 x 7 squares of `SQUARE` whose inner corners lie at
    (i, j) `SQUARE` in its frame (its top face z = 0, 4 mm thick), placed by X = R p + c."""
    s, (nx, ny) = SQUARE, PATTERN
    lo, hi = -1.6 * s, np.array(PATTERN) * s + 0.6 * s
    squares = (f"function {{ select(x + {s}, 0, select({nx * s} - x, 0, select(y + {s}, 0, select({ny * s} - y, 0, "
               f"mod(floor(x / {s} + 1) + floor(y / {s} + 1), 2))))) }}")
    matrix = ", ".join(f"{a:.12g}" for a in (*R[:, 0], *R[:, 1], *R[:, 2], *c))
    return (f"box {{ <{lo}, {lo}, -0.004>, <{hi[0]}, {hi[1]}, 0> texture {{ pigment {{ {squares} colour_map {{ "
            "[0 rgb 0.92] [1 rgb 0.04] } } finish { ambient 0.35 diffuse 0.6 } } "
            f"matrix <{matrix}> }}")


def _scene(camera: str, body: list[str], background: float | None = None) -> str:
    """A POV-Ray scene: `povray_flume.header_pov` with a grey `background` (None: black), which the water's surface
    reflects, then the objects in `body`."""
    return "\n".join([pf.header_pov(camera, None if background is None else f"{background:g}"), *body]) + "\n"


def _rubble_scene(stones: dict, keep: np.ndarray, level: float | None, grey: bool, camera: str) -> str:
    """`povray_flume`'s breakwater scene through `camera`."""
    return pf.scene_pov(stones, keep, level, camera, grey)


def sloping_board_pov(plane: dict) -> str:
    """The development flume's sloping board: from the floor at x0 up `drop` over `length`, then level for 0.3 m,
    across y 0 to `width`; textured like the floor."""
    x0, x1, top = plane["x0"], plane["x0"] + plane["length"], plane["drop"]
    return (f"prism {{ linear_sweep linear_spline 0, {plane['width']}, 5, <{x0}, 0>, <{x1}, {top}>, "
            f"<{x1 + 0.3}, {top}>, <{x1 + 0.3}, 0>, <{x0}, 0> "
            "texture { pigment { Speckle } finish { ambient 0.3 diffuse 0.7 } } }")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, help="the flume folder to write")
    parser.add_argument("--height", type=float, default=2.3, help="the cameras' height above the floor, m")
    parser.add_argument("--baseline", type=float, default=0.25, help="distance between the cameras, m")
    parser.add_argument("--across", action="store_true", help="baseline across the flume (y) instead of along it")
    parser.add_argument("--step", type=float, default=0.0, help="the right camera's height over the left's, m")
    parser.add_argument("--converge-deg", type=float, default=3.0, help="angle between the optical axes, degrees")
    parser.add_argument("--focal-px", type=float, default=3000.0, help="focal length, pixels")
    parser.add_argument("--size", type=int, nargs=2, default=SIZE, metavar=("W", "H"), help="image size, pixels")
    parser.add_argument("--level", type=float, default=0.15, help="water level above the floor, m")
    parser.add_argument("--seed", type=int, default=7, help="the rig's jitter, the boards' poses and the rocks")
    parser.add_argument("--boards", type=int, default=14, help="calibration photographs")
    parser.add_argument("--scenes", default="board_wet,bw_I_wet,bw_I_dry,bw_III_wet,grey_I_wet,grey_I_dry",
                        help="comma list of the scenes to render")
    parser.add_argument("--oblique-deg", type=float, default=0.0,
                        help="also an oblique rig, its axes this many degrees off the vertical (0: none)")
    parser.add_argument("--oblique-height", type=float, default=1.65,
                        help="the oblique rig's height above the floor, m")
    parser.add_argument("--oblique-baseline", type=float, default=0.18, help="the oblique rig's baseline (across), m")
    args = parser.parse_args(argv)
    if shutil.which("povray") is None:
        raise SystemExit("povray_rig: no `povray` on the PATH (POV-Ray 3.7: apt install povray)")
    size = tuple(args.size)
    K = np.array([[args.focal_px, 0, (size[0] - 1) / 2], [0, args.focal_px, (size[1] - 1) / 2], [0, 0, 1]])
    rig = make_rig(args.height, args.baseline, args.across, args.converge_deg, args.seed, step=args.step)
    print(f"rig: {args.height} m high, baseline {args.baseline} m {'across' if args.across else 'along'} the flume, "
          f"converging {args.converge_deg} deg, the right camera {args.step} m higher, f {args.focal_px} px",
          flush=True)
    cams = {s: pf.camera_pov(K, np.array(rig[s]["R"]), np.array(rig[s]["t"]), size) for s in "LR"}
    (args.out / "calib").mkdir(parents=True, exist_ok=True)
    shots = {}  # image name -> the scene's text for a camera's POV-Ray text
    for k, (R, c) in enumerate(board_poses(K, rig, args.boards, args.seed, size=size)):
        shots[f"calib/calib_{k:02d}"] = partial(_scene, body=[board_pov(R, c)], background=0.25)
    origin = np.array([*AIM, 0.0]) - [4 * SQUARE, 2.5 * SQUARE, 0]  # the board's middle under the rig
    shots["origin"] = partial(_scene, body=[pf.floor_pov(-0.004), board_pov(np.eye(3), origin)])
    scenes = {}
    rigs, origins = {"main": rig}, {"origin": origin.tolist()}
    main_shots = set(shots)  # the shots through the main rig; the oblique rig's are added next
    if args.oblique_deg:
        oblique = make_oblique_rig(args.oblique_deg, args.oblique_height, args.oblique_baseline, args.seed)
        rigs["oblique"] = oblique
        cams.update({f"oblique {s}": pf.camera_pov(K, np.array(oblique[s]["R"]), np.array(oblique[s]["t"]), size)
                     for s in "LR"})
        (args.out / "calib_oblique").mkdir(parents=True, exist_ok=True)
        for k, (R, c) in enumerate(board_poses(K, oblique, args.boards, args.seed, size=size, follow_axis=True)):
            shots[f"calib_oblique/calib_{k:02d}"] = partial(_scene, body=[board_pov(R, c)], background=0.25)
        tilt = np.radians(args.oblique_deg)  # the board's middle where the rig's mean axis meets the floor
        floor_hit = BOARD_MIDDLE[0] + BOARD_MIDDLE[2] * np.tan(tilt)
        origins["origin_oblique"] = [floor_hit - 4 * SQUARE, BOARD_MIDDLE[1] - 2.5 * SQUARE, 0.0]
        shots["origin_oblique"] = partial(_scene, body=[pf.floor_pov(-0.004),
                                                        board_pov(np.eye(3), np.array(origins["origin_oblique"]))])
        scenes["oblique_board_wet"] = {"rig": "oblique", "water_level": args.level, "kind": "plane",
                                       "plane": BOARD_PLANE}
        body = [pf.floor_pov(), sloping_board_pov(BOARD_PLANE), pf.water_pov(args.level)]
        shots["oblique_board_wet"] = partial(_scene, body=body, background=0.6)
    oblique_shots = set(shots) - main_shots
    stones = pf.rocks(args.seed)
    hole_xy = (pf.TOE + pf.SLOPE * (args.level - 0.02), 0.3)
    lost = pf.hole(stones, hole_xy)
    for name in filter(None, args.scenes.split(",")):
        if name == "board_wet":
            scenes[name] = {"rig": "main", "water_level": args.level, "kind": "plane", "plane": BOARD_PLANE}
            body = [pf.floor_pov(), sloping_board_pov(BOARD_PLANE), pf.water_pov(args.level)]
            shots[name] = partial(_scene, body=body, background=0.6)  # 0.6: the sky the water reflects
            continue
        kind, stage, wet = name.split("_")
        level = args.level if wet == "wet" else None
        scenes[name] = {"rig": "main", "water_level": level, "kind": "heightfield", "stage": stage,
                        "removed": np.flatnonzero(lost).tolist() if stage == "III" else []}
        keep = ~lost if stage == "III" else np.ones(len(lost), bool)
        shots[name] = partial(_rubble_scene, stones, keep, level, kind == "grey")
    x = np.round(np.arange(-0.1, 1.1005, 0.001), 6)
    y = np.round(np.arange(-0.05, 0.6495, 0.001), 6)
    if not (args.out / "breakwater_gt.npz").exists():
        surfaces = {"I": pf.heightfield(stones, np.ones(len(lost), bool), x, y),
                    "III": pf.heightfield(stones, ~lost, x, y)}
        with atomic_path(args.out / "breakwater_gt.npz") as tmp:
            np.savez_compressed(tmp, x=x, y=y, **surfaces)
    for name, shot in shots.items():
        oblique = name in oblique_shots
        for side in "LR":
            out = args.out / f"{name}_{side}.jpg"
            if out.exists():
                continue
            t0 = time.perf_counter()
            pf.render(shot(cams[f"oblique {side}" if oblique else side]), out, size)
            print(f"{out.relative_to(args.out)}: {time.perf_counter() - t0:.0f} s", flush=True)
    truth = {"K": K.tolist(), "size": list(size), "n_water": 1.333, "square": SQUARE, "pattern": list(PATTERN),
             **origins, "images": "jpg (quality 95)", "rigs": rigs, "scenes": scenes,
             "breakwater": {"dn50": pf.DN50, "slope": pf.SLOPE, "toe": pf.TOE, "height": pf.HEIGHT,
                            "hole_centre_xy": list(hole_xy), "width": 0.6},
             "made_by": "experiments/povray_rig.py " + " ".join(argv if argv is not None else sys.argv[1:])}
    write_text_atomic(args.out / "truth.json", json.dumps(truth, indent=1))


if __name__ == "__main__":
    main()
