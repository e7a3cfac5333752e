"""How much of a POV-Ray flume's central-profile damage is the grid's: the scorecard's damage row over grid offsets.

flume-score compares the damage profile nearest the hole's centre with the true sweep at the centre itself (the true
1 mm surfaces closed by a Dn50/4 ball). Where the 5 mm cells and the profiles fall about the hole is chance: this
grids the stage I and III wet surveys of a scored work folder (moved into the truth frame through the left camera, as
flume-score moves them) with the cells moved by 0, 1/3 and 2/3 of a cell in x and y, and prints the central A_e and
d_e errors at each offset; `--surface truth` grids the true surfaces the same way (what perfect surveys would give),
`--surface oracle` the surveys with their empty cells given the true heights. A survey's empty cells are filled as
`jaxstereo damage` fills them (along the baseline from the lower side, since round 69; this script since round 70).
The truth's sweep is flume-score's own (`true_profile_damage`, read from `../shared/tools/flume-score`).

Run: python experiments/damage_grid_offsets.py DATA WORK [--spacing 0.005] [--surface survey|truth|oracle]
(WORK: a `flume-score --work` folder holding `bw_I_wet_exact.npz`, `bw_III_wet_exact.npz` and `rig_main.json`).
"""

from __future__ import annotations

import argparse
import importlib.machinery
import importlib.util
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a script: the checkout

from jaxstereo._surface.damage_report import stretch_damage
from jaxstereo._surface.gap_fill import survey_baseline_xy
from jaxstereo._surface.grid import DEM, fill_holes, grid_median

SCORER = Path(__file__).resolve().parents[1].parent / "shared" / "tools" / "flume-score"
OFFSETS = (0.0, 1 / 3, 2 / 3)  # of a cell, in x and in y
HALF_WIDTH = 0.1  # m across the flume each side of the hole's centre that is gridded
MAX_GAP = 0.01  # m, as `jaxstereo damage` fills


def _scorer():
    loader = importlib.machinery.SourceFileLoader("flume_score", str(SCORER))
    spec = importlib.util.spec_from_loader("flume_score", loader)
    module = importlib.util.module_from_spec(spec)
    loader.exec_module(module)
    return module


def _baseline_in_truth(rig_json: str, to_truth) -> tuple[float, float] | None:
    """The survey's stereo baseline in the truth frame's (x, y): gaps are filled along it from their lower side,
    as `jaxstereo damage` fills them in the survey's own frame (`gap_fill.survey_baseline_xy`)."""
    b = survey_baseline_xy(rig_json)
    if b is None:
        return None
    ends = to_truth(np.array([[0.0, 0.0, 0.0], [b[0], b[1], 0.0]]))
    return float(ends[1, 0] - ends[0, 0]), float(ends[1, 1] - ends[0, 1])


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", help="the flume folder (truth.json, breakwater_gt.npz)")
    parser.add_argument("work", help="the flume-score work folder with its wet surveys and rig")
    parser.add_argument("--spacing", type=float, default=0.005, help="cell size, m")
    parser.add_argument("--surface", choices=("survey", "truth", "oracle"), default="survey")
    args = parser.parse_args(argv)
    fs = _scorer()
    score = fs.Score(args.data, args.work)
    to_truth, _ = score.frames()
    bw, g = score.T["breakwater"], score.gt()
    level = score.T["scenes"]["bw_I_wet"]["water_level"]
    yc = bw["hole_centre_xy"][1]
    X, Y = np.meshgrid(g["x"], g["y"])

    def near(P):
        return P[np.abs(P[:, 1] - yc) < HALF_WIDTH]

    files = {st: np.load(Path(args.work) / f"bw_{st}_wet_exact.npz") for st in ("I", "III")}
    surveyed = {st: near(to_truth(files[st]["points"])) for st in ("I", "III")}
    baseline = _baseline_in_truth(str(files["I"]["rig"]), to_truth)
    true = {st: near(np.stack([X.ravel(), Y.ravel(), g[st].astype(float).ravel()], 1)) for st in ("I", "III")}
    truth = fs.true_profile_damage(g, bw, yc)
    sp, rows = args.spacing, []
    for fx in OFFSETS:
        for fy in OFFSETS:
            x = np.arange(g["x"][0] + fx * sp, g["x"][-1], sp)
            y = np.arange(yc - HALF_WIDTH + fy * sp, yc + HALF_WIDTH, sp)
            dems = {}
            for st in ("I", "III"):
                exact = grid_median(true[st], sp, x, y) if args.surface != "survey" else None
                dem = exact if args.surface == "truth" else grid_median(surveyed[st], sp, x, y)
                if args.surface == "oracle":
                    dem = DEM(x, y, np.where(np.isfinite(dem.z), dem.z, exact.z), sp)
                dems[st] = fill_holes(dem, MAX_GAP, baseline if args.surface != "truth" else None)
            result = stretch_damage(dems["I"], dems["III"], bw["dn50"], bw["slope"], level, (bw["toe"], 0.0), 0.005)
            y_profile, p = min(result.profiles, key=lambda item: abs(item[0] - yc))
            rows.append((fx * sp, fy * sp, y_profile - yc, (p.A_e / truth["Ae"] - 1) * 100,
                         (p.d_e - truth["de"]) * 1e3))
    print(f"{args.data}: {args.surface}, {sp * 1e3:g} mm cells; truth A_e {truth['Ae'] * 1e4:.2f} cm2, d_e "
          f"{truth['de'] * 1e3:.1f} mm")
    print("| cells moved x, y (mm) | profile from the centre (mm) | A_e error (%) | d_e error (mm) |")
    print("|---|---:|---:|---:|")
    for dx, dy, off, ea, ed in rows:
        print(f"| {dx * 1e3:.1f}, {dy * 1e3:.1f} | {off * 1e3:+.1f} | {ea:+.1f} | {ed:+.1f} |")
    ea, ed = np.array([r[3] for r in rows]), np.array([r[4] for r in rows])
    print(f"past 10 % (A_e): {(np.abs(ea) > 10).sum()} of {len(rows)}; past 5 mm (d_e): {(np.abs(ed) > 5).sum()} of "
          f"{len(rows)}")


if __name__ == "__main__":
    main()
