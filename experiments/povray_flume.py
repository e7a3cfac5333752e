"""A rubble-mound breakwater flume rendered by POV-Ray at a water depth and rock seed of your choosing, with exact truth.

The development flume (`../shared/data/povray-flume-dev`) holds one water depth and one set of rocks. This renders
others through POV-Ray 3.7 (`povray` on the PATH: a ray tracer independent of jaxstereo, with physical refraction at
the water surface; not a Python dependency, `apt install povray`), through the development flume's own cameras
(its `truth.json`), so that its calibration photographs serve: the folder written is one `flume-score --data`
reads (`--only breakwater,grey,wetdry,refine-dem,refine-floor,damage,speed`). Nothing here uses jaxstereo's
geometry: the cameras are POV-Ray's own (a pinhole from K, R, t; `camera_pov`), the truth a numpy heightfield of the
rocks as POV-Ray draws them (`heightfield`).

Run: python experiments/povray_flume.py OUT --level 0.12 --seed 3 [--dev ../shared/data/povray-flume-dev]

The model: a core 2 Dn50 under a 1:`slope` design line from `toe`, flat at `height` - 2 Dn50, across the whole
flume; two layers of ellipsoidal rocks (nominal diameter Dn50, axes about 1.35 : 1 : 0.75) over the slope and the
crest, painted in random colours with a fine granite texture (or quarry grey); a floor of fine speckle; water
(index 1.333, Fresnel reflection) up to `level`. Stage I is intact; stage III lacks the rocks around a hole centred
on the slope 2 cm below the still water level (2.2 Dn50 across in the top layer, 1.2 Dn50 in the bottom one).
Written: `bw_{I,III}_wet`, `bw_I_dry`, `grey_I_wet`, `grey_I_dry` pairs (JPEG, quality 95), `breakwater_gt.npz`
(the true surfaces, 1 mm grid), `truth.json`, and links to the development flume's calibration photographs.
"""

from __future__ import annotations

import argparse
import colorsys
import json
import os
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from jaxstereo._app.io import atomic_path, write_bytes_atomic, write_text_atomic

DEV = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "povray-flume-dev"
DN50 = 0.036  # m
SLOPE = 2.0  # cot(alpha)
TOE = 0.12  # m, where the design line meets the floor
HEIGHT = 0.31  # m, the design line's top
CREST_END = 0.95  # m, the last rocks' x
AXES = np.array([1.35, 1.0, 0.75])  # the rocks' axis ratios (long, wide, thick)


def core_height(x: np.ndarray) -> np.ndarray:
    """The core's top (m) at `x` (m): 2 Dn50 under the design line, flat past its top; the floor (0) before it."""
    return np.clip((np.asarray(x) - TOE) / SLOPE - 2 * DN50, 0.0, HEIGHT - 2 * DN50)


def rocks(seed: int, width: float = 0.6) -> dict:
    """Two layers of ellipsoids over the slope and crest: `centre` (n, 3) m, `R` (n, 3, 3) (columns: the axes in the
    world), `semi` (n, 3) semi-axes m, `layer` (n,) 1 (bottom) or 2, `hue` (n,), `tone` (n, 2) saturation, value."""
    rng = np.random.default_rng(seed)
    spacing = 1.25 * DN50
    centres, layers = [], []
    for layer, (lift, offset) in enumerate(((0.45 * DN50, 0.0), (1.3 * DN50, 0.5)), start=1):
        xs = np.arange(TOE - 0.3 * DN50 + offset * spacing, CREST_END, spacing)
        ys = np.arange(0.5 * DN50 + offset * spacing, width - 0.4 * DN50, spacing)
        X, Y = (a.ravel() for a in np.meshgrid(xs, ys))
        X = X + rng.uniform(-0.3, 0.3, X.size) * spacing
        Y = Y + rng.uniform(-0.3, 0.3, Y.size) * spacing
        Z = core_height(X) + lift + rng.uniform(-0.1, 0.1, X.size) * DN50
        centres.append(np.stack([X, Y, Z], 1))
        layers.append(np.full(X.size, layer))
    centre, layer = np.concatenate(centres), np.concatenate(layers)
    n = len(centre)
    ratios = AXES * rng.uniform(0.85, 1.15, (n, 3))
    semi = ratios * (3 / (4 * np.pi)) ** (1 / 3) * DN50 / np.prod(ratios, axis=1, keepdims=True) ** (1 / 3)
    # thick axis near the local normal (the slope's, or up on the crest), turned at random about it, tilted 20 deg
    normal = np.where((centre[:, 0] > TOE + SLOPE * (HEIGHT - DN50))[:, None], [0.0, 0.0, 1.0],
                      np.array([-1.0, 0.0, SLOPE]) / np.hypot(1.0, SLOPE))
    R = np.empty((n, 3, 3))
    for i in range(n):
        tilt = cv2.Rodrigues(rng.normal(0, np.radians(12), 3))[0]
        up = tilt @ normal[i]
        a = np.cross(up, [0.0, 1.0, 0.0])
        a /= np.linalg.norm(a)
        b = np.cross(up, a)
        turn = rng.uniform(0, 2 * np.pi)
        long_axis = np.cos(turn) * a + np.sin(turn) * b
        R[i] = np.stack([long_axis, np.cross(up, long_axis), up], 1)
    return {"centre": centre, "R": R, "semi": semi, "layer": layer, "hue": rng.uniform(0, 1, n),
            "tone": np.stack([rng.uniform(0.2, 0.75, n), rng.uniform(0.5, 0.95, n)], 1)}


def hole(stones: dict, centre_xy, top_radius: float = 1.1 * DN50, bottom_radius: float = 0.6 * DN50) -> np.ndarray:
    """Which rocks stage III has lost: those centred within `top_radius` (top layer) or `bottom_radius` (bottom) of
    `centre_xy` in plan (n,) bool."""
    r = np.hypot(*(stones["centre"][:, :2] - np.asarray(centre_xy)).T)
    return np.where(stones["layer"] == 2, r < top_radius, r < bottom_radius)


def heightfield(stones: dict, keep: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The true surface (len(y), len(x)) float32 m: the highest of the floor, the core and the kept rocks' tops, each
    rock's exactly (the upper root of its quadric along the vertical)."""
    z = np.tile(core_height(x), (len(y), 1))
    for c, R, s in zip(stones["centre"][keep], stones["R"][keep], stones["semi"][keep]):
        M = R @ np.diag(1 / s**2) @ R.T
        reach = s.max()
        ix = np.flatnonzero(np.abs(x - c[0]) <= reach)
        iy = np.flatnonzero(np.abs(y - c[1]) <= reach)
        if ix.size == 0 or iy.size == 0:
            continue
        wx, wy = np.meshgrid(x[ix] - c[0], y[iy] - c[1])
        mz = M[2, 0] * wx + M[2, 1] * wy  # (M w)_z
        q = M[0, 0] * wx**2 + M[1, 1] * wy**2 + 2 * M[0, 1] * wx * wy  # w^T M w
        disc = mz**2 - M[2, 2] * (q - 1)
        top = np.where(disc >= 0, c[2] + (-mz + np.sqrt(np.maximum(disc, 0))) / M[2, 2], -np.inf)
        z[np.ix_(iy, ix)] = np.maximum(z[np.ix_(iy, ix)], top)
    return z.astype(np.float32)


def _v(a) -> str:
    x, y, z = np.asarray(a, float)
    return f"<{x:.12g},{y:.12g},{z:.12g}>"


def camera_pov(K: np.ndarray, R: np.ndarray, t: np.ndarray, size) -> str:
    """POV-Ray's perspective camera for the OpenCV pinhole (K, world -> camera R, t), pixel centres at whole
    coordinates: POV-Ray shoots pixel column i through `direction + ((i + 0.5) / W - 0.5) right`, rows likewise
    with `up` downwards here. (Checked by rendering small spheres: their centroids within 0.002 px of
    cv2.projectPoints on average.)"""
    w, h = size
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    ex, ey, ez = R
    centre = -R.T @ t
    direction = ez + ((w - 1) / 2 - cx) / fx * ex + ((h - 1) / 2 - cy) / fy * ey
    return (f"camera {{ perspective location {_v(centre)} direction {_v(direction)} right {_v(w / fx * ex)} "
            f"up {_v(-h / fy * ey)} }}")


def header_pov(camera: str, background: str | None = "<0.55, 0.6, 0.7>") -> str:
    """A scene's first lines: the version, `camera`, the `background` colour (POV-Ray's rgb text; None: black),
    the two lights and the floor's `Speckle` pigment."""
    parts = ["#version 3.7;", "global_settings { assumed_gamma 1.0 max_trace_level 8 }", camera]
    if background is not None:
        parts.append(f"background {{ rgb {background} }}")
    parts += ["light_source { <0.6, -0.4, 3.5> rgb 1.0 }",
              "light_source { <-0.5, 1.2, 3.0> rgb 0.35 shadowless }",
              ("#declare Speckle = pigment { granite colour_map { [0 rgb <0.45, 0.38, 0.4>] "
               "[1 rgb <0.82, 0.74, 0.76>] } scale 0.015 }")]
    return "\n".join(parts)


def floor_pov(top: float = 0.0) -> str:
    """The flume's floor, its top face at z = `top` (m)."""
    return (f"box {{ <-1.5, -1.5, -0.05>, <2.5, 2.5, {top:g}> texture {{ pigment {{ Speckle }} "
            "finish { ambient 0.3 diffuse 0.7 } } }")


def water_pov(level: float) -> str:
    """Fresh water (index 1.333, Fresnel reflection) up to z = `level` (m)."""
    return (f"box {{ <-1.5, -1.5, -0.1>, <2.5, 2.5, {level}> material {{ texture {{ pigment {{ rgbf 1 }} "
            "finish { ambient 0 diffuse 0 reflection { 0, 1 fresnel on } conserve_energy } } "
            "interior { ior 1.333 } } }")


def scene_pov(stones: dict, keep: np.ndarray, level: float | None, camera: str, grey: bool) -> str:
    """The POV-Ray scene: camera, light, floor, core, the kept rocks, and the water up to `level` (None: dry)."""
    parts = [header_pov(camera), floor_pov()]
    top = HEIGHT - 2 * DN50
    x_top = TOE + SLOPE * HEIGHT
    x_foot = TOE + SLOPE * 2 * DN50
    # POV-Ray's prism: an outline in its x-z plane (here x and height), swept along y (across the flume)
    parts.append(f"prism {{ linear_sweep linear_spline -1.5, 2.5, 5, <{x_foot}, 0>, <{x_top}, {top}>, "
                 f"<2.5, {top}>, <2.5, 0>, <{x_foot}, 0> "
                 "texture { pigment { Speckle scale 0.7 } finish { ambient 0.25 diffuse 0.65 } } }")
    for i in np.flatnonzero(keep):
        hue, (sat, val) = stones["hue"][i], stones["tone"][i]
        colour = np.array(colorsys.hsv_to_rgb(hue, sat * (0.12 if grey else 1.0), val * (0.75 if grey else 1.0)))
        R, s, c = stones["R"][i], stones["semi"][i], stones["centre"][i]
        matrix = ", ".join(f"{a:.10g}" for a in (*R[:, 0], *R[:, 1], *R[:, 2], *c))
        parts.append(f"sphere {{ 0, 1 scale {_v(s)} matrix <{matrix}> texture {{ pigment {{ granite colour_map {{ "
                     f"[0 rgb {_v(0.72 * colour)}] [1 rgb {_v(np.minimum(1.12 * colour, 1))}] }} scale 0.02 "
                     f"translate {_v(c * 37)} }} finish {{ ambient 0.22 diffuse 0.75 specular 0.05 }} }} }}")
    if level is not None:
        parts.append(water_pov(level))
    return "\n".join(parts) + "\n"


def render(scene: str, out: Path, size, threads: int = os.cpu_count() or 1) -> None:
    """Render `scene` with POV-Ray (anti-aliased, no jitter) and save it as JPEG quality 95 at `out`."""
    with tempfile.TemporaryDirectory() as tmp:
        pov, png = Path(tmp) / "scene.pov", Path(tmp) / "image.png"
        pov.write_text(scene)
        done = subprocess.run(["povray", f"+I{pov}", f"+O{png}", f"+W{size[0]}", f"+H{size[1]}", "+A0.05", "+AM2",
                               "+R3", "-J", "-D", "+FN", f"+WT{threads}", "Display=off"], capture_output=True, text=True, check=False)
        if done.returncode != 0 or not png.exists():
            raise RuntimeError(f"povray failed on {out.name}: {done.stderr[-500:]}")
        ok, jpeg = cv2.imencode(".jpg", cv2.imread(str(png)), [cv2.IMWRITE_JPEG_QUALITY, 95])
    if not ok:
        raise RuntimeError(f"cannot encode {out.name} as JPEG")
    write_bytes_atomic(out, jpeg.tobytes())  # a stopped run leaves no half image: it is rendered again


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, help="the flume folder to write")
    parser.add_argument("--level", type=float, default=0.12, help="water level above the floor, m (default 0.12)")
    parser.add_argument("--seed", type=int, default=3, help="the rocks' seed (default 3)")
    parser.add_argument("--dev", type=Path, default=DEV, help="the development flume (its cameras and boards)")
    parser.add_argument("--scenes", default="bw_I_wet,bw_I_dry,bw_III_wet,grey_I_wet,grey_I_dry",
                        help="comma list of the scenes to render")
    args = parser.parse_args(argv)
    if shutil.which("povray") is None:
        raise SystemExit("povray_flume: no `povray` on the PATH (POV-Ray 3.7: apt install povray)")
    truth = json.loads((args.dev / "truth.json").read_text())
    K, size = np.array(truth["K"]), truth["size"]
    args.out.mkdir(parents=True, exist_ok=True)
    for name in ["calib", "origin_L.jpg", "origin_R.jpg"]:
        link = args.out / name
        if not link.exists():
            link.symlink_to((args.dev / name).resolve())
    stones = rocks(args.seed)
    hole_xy = (TOE + SLOPE * (args.level - 0.02), 0.3)
    lost = hole(stones, hole_xy)
    x = np.round(np.arange(-0.1, 1.1005, 0.001), 6)
    y = np.round(np.arange(-0.05, 0.6495, 0.001), 6)
    surfaces = {"I": heightfield(stones, np.ones(len(lost), bool), x, y), "III": heightfield(stones, ~lost, x, y)}
    with atomic_path(args.out / "breakwater_gt.npz") as tmp:
        np.savez_compressed(tmp, x=x, y=y, **surfaces)
    scenes = {}
    for name in args.scenes.split(","):
        kind, stage, wet = name.split("_")
        level = args.level if wet == "wet" else None
        scenes[name] = {"rig": "main", "water_level": level, "kind": "heightfield", "stage": stage,
                        "removed": np.flatnonzero(lost).tolist() if stage == "III" else []}
        keep = ~lost if stage == "III" else np.ones(len(lost), bool)
        for side in "LR":
            out = args.out / f"{name}_{side}.jpg"
            if out.exists():
                continue
            camera = truth["rigs"]["main"][side]
            t0 = time.perf_counter()
            render(scene_pov(stones, keep, level, camera_pov(K, np.array(camera["R"]), np.array(camera["t"]), size),
                             kind == "grey"), out, size)
            print(f"{out.name}: {time.perf_counter() - t0:.0f} s", flush=True)
    written = {k: truth[k] for k in ("K", "size", "n_water", "square", "pattern", "origin", "rigs", "images")}
    written.update(scenes=scenes, breakwater={"dn50": DN50, "slope": SLOPE, "toe": TOE, "height": HEIGHT,
                                              "hole_centre_xy": list(hole_xy), "width": 0.6},
                   made_by=f"experiments/povray_flume.py --level {args.level} --seed {args.seed}")
    write_text_atomic(args.out / "truth.json", json.dumps(written, indent=1))


if __name__ == "__main__":
    main()
