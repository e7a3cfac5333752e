"""Calibration and surveys on the POV-Ray development flume: images from an independent ray tracer, exact truth.

The data set lives beside the checkout (`../shared/data/povray-flume-dev`, as in CI); its README describes it.
Everything runs at the full 1728x1152 resolution through the command line, as a user would, and every
result is mapped into the truth frame through the calibrated left camera (as `flume-score` does), so that
the calibration's own error is part of every figure. The bounds are the figures this project reaches
today (see the README's accuracy table), not the issue's targets where those are not met yet.
"""

import json
import os
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree

from jaxstereo import load_survey
from jaxstereo._app.cli import main
from jaxstereo._surface.damage_report import profile_figures

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "povray-flume-dev"
pytestmark = pytest.mark.skipif(not DATA.is_dir() and os.environ.get("CI") != "true",
                                reason=f"the development flume is not at {DATA}")


@pytest.fixture(scope="module")
def flume(tmp_path_factory):
    work = tmp_path_factory.mktemp("povray")
    truth = json.loads((DATA / "truth.json").read_text())
    assert main(["calibrate", "--left", str(DATA / "calib" / "*_L.jpg"), "--right", str(DATA / "calib" / "*_R.jpg"),
                 "--board", "chessboard:9x6:%g" % truth["square"], "--origin-left", str(DATA / "origin_L.jpg"),
                 "--origin-right", str(DATA / "origin_R.jpg"), "-o", str(work / "rig.json")]) == 0
    return work, truth, json.loads((work / "rig.json").read_text())


def _centre(cam):
    return -np.asarray(cam["R"], float).T @ np.asarray(cam["t"], float)


def _to_truth(rig, truth):
    R_c, t_c = np.asarray(rig["left"]["R"], float), np.asarray(rig["left"]["t"], float)
    true = truth["rigs"]["main"]["L"]
    R_t, t_t = np.asarray(true["R"], float), np.asarray(true["t"], float)
    return lambda P: (R_t.T @ (R_c @ P.T + t_c[:, None] - t_t[:, None])).T


def _survey(flume, scene):
    work, truth, rig = flume
    out = work / f"{scene}.npz"
    if not out.exists():
        level = truth["scenes"][scene]["water_level"]
        assert main(["reconstruct", str(DATA / f"{scene}_L.jpg"), str(DATA / f"{scene}_R.jpg"), "--rig",
                     str(work / "rig.json"), "-o", str(out)] + (["--water-level", str(level)] if level else [])) == 0
    return _to_truth(rig, truth)(load_survey(out).points)


def test_calibration_focal_baseline_and_height(flume):
    _, truth, rig = flume
    f_true = truth["K"][0][0]
    # 0.003 % measured with the corners from the board's edge lines (0.046 % from OpenCV's corners alone)
    assert abs(rig["left"]["fx"] - f_true) / f_true <= 2e-4
    true_l, true_r = (_centre(truth["rigs"]["main"][s]) for s in "LR")
    base = np.linalg.norm(_centre(rig["left"]) - _centre(rig["right"]))
    assert abs(base - np.linalg.norm(true_l - true_r)) <= 2e-4
    # The height follows the focal length: -0.07 mm measured (-0.98 mm from OpenCV's corners alone).
    assert abs(_centre(rig["left"])[2] - true_l[2]) <= 0.5e-3


def test_sloping_board_one_clean_point_per_pixel(flume):
    _, truth, _ = flume
    P = _survey(flume, "board_wet")
    p = truth["scenes"]["board_wet"]["plane"]
    a = np.arctan2(p["drop"], p["length"])
    x = P[:, 0] - p["x0"]
    e = (P[:, 2] - x * np.tan(a)) * np.cos(a) * 1e3
    on = (x > 0.02) & (x < p["length"] - 0.02) & (P[:, 1] > 0.02) & (P[:, 1] < p["width"] - 0.02)
    e, z = e[on], P[on, 2]
    assert np.mean(np.abs(e) > 20) <= 0.005  # gross outliers: 1.8 % before one match per pixel, 0.00 % now
    summary = json.loads((flume[0] / "board_wet_summary.json").read_text())
    assert summary["dropped_photometric"] <= 0.005 * summary["matches"]  # correct matches stay: 0.1 % dropped
    # SGBM's values off the board's plane that no patch fit could refine: 0.03 % of the matches (513), measured
    assert 0 < summary["dropped_off_surface"] <= 0.002 * summary["matches"]
    medians = [np.median(e[(z >= lo) & (z < lo + 0.05)]) for lo in np.arange(0.0, 0.30, 0.05)]
    assert max(abs(m) for m in medians) <= 0.5, medians  # 0.23 measured (1.02 with OpenCV's corners alone)
    sub = (z < truth["scenes"]["board_wet"]["water_level"]) & (np.abs(e) < 20)
    # 1.15 measured (1.20 with the matches off the smooth surface kept; 1.33 with each patch's SGBM disparities
    # judged by their spread about their mean, not their plane; 1.29 before the refined disparities were checked
    # against SGBM's own block; 1.85 with the sub-pixel fit's two linearisations blended after the window sums;
    # SGBM's own sub-pixel values 3.09; plain OpenCV 3.49)
    assert np.sqrt(np.mean(e[sub] ** 2)) <= 1.5


def _c2m(P, surface, x, y, box):
    x0, x1, y0, y1 = box
    jx, iy = (x >= x0 - 0.02) & (x < x1 + 0.02), (y >= y0 - 0.02) & (y < y1 + 0.02)
    X, Y = np.meshgrid(x[jx], y[iy])
    S = np.stack([X.ravel(), Y.ravel(), surface[np.ix_(iy, jx)].ravel()], 1)
    m = (P[:, 0] >= x0) & (P[:, 0] < x1) & (P[:, 1] >= y0) & (P[:, 1] < y1)
    Q = P[m][:: max(1, m.sum() // 100000)]
    d, idx = cKDTree(S).query(Q)
    return d * 1e3, S[idx, 2]


def test_breakwater_wet_survey_has_no_refracted_mismatches(flume):
    _, truth, _ = flume
    wet, dry = _survey(flume, "bw_I_wet"), _survey(flume, "bw_I_dry")
    assert np.mean(wet[:, 2] < -0.02) <= 5e-4  # 0.84 % before (mismatches refracted below the floor)
    gt = np.load(DATA / "breakwater_gt.npz")
    bw = truth["breakwater"]
    box = (bw["toe"] + 0.05, bw["toe"] + bw["slope"] * bw["height"] + 0.03, 0.05, bw["width"] - 0.05)
    level = truth["scenes"]["bw_I_wet"]["water_level"]
    d_wet, z_wet = _c2m(wet, gt["I"].astype(float), gt["x"], gt["y"], box)
    d_dry, z_dry = _c2m(dry, gt["I"].astype(float), gt["x"], gt["y"], box)
    emerged_wet = np.mean(d_wet[z_wet >= level + 0.01])
    emerged_dry = np.mean(d_dry[z_dry >= level + 0.01])
    assert emerged_wet - emerged_dry <= 0.2  # the emerged rock matched once, as in the dry survey
    submerged = d_wet[z_wet < level - 0.01]
    # 1.82 / 5.67 measured (1.82 / 5.37 with the patches judged about their mean, not their plane; 1.96 / 5.84
    # before the check against SGBM's own block; 3.54 / 11.46 before the photometric check; plain OpenCV
    # 3.56 / 11.31)
    assert np.mean(submerged) <= 2.5
    assert np.percentile(submerged, 95) <= 8.0


def _cell_medians(P, box, cell=0.005):
    """Median height of the points in each `cell` square over `box` (x0, x1, y0, y1), NaN where empty."""
    x0, x1, y0, y1 = box
    nx, ny = round((x1 - x0) / cell), round((y1 - y0) / cell)
    m = (P[:, 0] >= x0) & (P[:, 0] < x1) & (P[:, 1] >= y0) & (P[:, 1] < y1)
    flat = ((P[m, 1] - y0) // cell).astype(int) * nx + ((P[m, 0] - x0) // cell).astype(int)
    order = np.argsort(flat, kind="stable")
    cells, start = np.unique(flat[order], return_index=True)
    Z = np.full(nx * ny, np.nan)
    Z[cells] = [np.median(c) for c in np.split(P[m, 2][order], start[1:])]
    return Z.reshape(ny, nx)


def test_wet_and_dry_surveys_of_one_model_agree_cell_by_cell(flume):
    """The same undamaged model surveyed dry and through 16.5 cm of water, 5 mm cells, submerged part."""
    _, truth, _ = flume
    level = truth["scenes"]["bw_I_wet"]["water_level"]
    box = (0.15, 0.72, 0.05, 0.53)
    wet, dry = (_cell_medians(_survey(flume, scene), box) for scene in ("bw_I_wet", "bw_I_dry"))
    d = (wet - dry) * 1e3
    sub = np.isfinite(d) & (dry < level - 0.01)
    assert sub.sum() > 3000
    assert np.median(np.abs(d[sub])) <= 1.5  # 1.06 measured (1.65 with the 31 px patch alone; plain OpenCV 1.75)
    assert abs(np.median(d[sub])) <= 0.3  # -0.11 measured


QUARTER = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # camera frame: x' = -y, y' = x


def _quarter_turned_rig(rig: dict) -> dict:
    """The rig JSON with both cameras turned a quarter about their axes, as their images are by `np.rot90(image, -1)`
    (pixel (u, v) -> (h - 1 - v, u)); the world frame as it was."""
    w, h = rig["image_size"]
    out = json.loads(json.dumps(rig))
    out["image_size"] = [h, w]
    for side in ("left", "right"):
        cam, dist = rig[side], list(rig[side]["dist"])
        dist[2], dist[3] = cam["dist"][3], -cam["dist"][2]  # the tangential terms turn with the axes
        out[side].update(fx=cam["fy"], fy=cam["fx"], cx=h - 1 - cam["cy"], cy=cam["cx"], dist=dist,
                         R=(QUARTER @ np.asarray(cam["R"], float)).tolist(),
                         t=(QUARTER @ np.asarray(cam["t"], float)).tolist())
    return out


def test_a_rig_turned_a_quarter_surveys_the_whole_scene(flume):
    """The wet stage I pair and its rig turned a quarter: the baseline now runs down the images, along their short
    side, as on a rig whose cameras sit side by side across the flume with the images' long side along it. The
    survey must hold the same scene as the rig as mounted. Before the rectified images took the real ones' shape
    turned, it held 56 % of the points (a band about 900 px long of the 1728 px image), and on the flume turned so
    (its boards too) the water level refined with a dry DEM as control, from half the correspondences, came out
    0.79 mm off."""
    work, truth, rig = flume
    folder = work / "quarter-turned"
    folder.mkdir(exist_ok=True)
    (folder / "rig.json").write_text(json.dumps(_quarter_turned_rig(rig)))
    for side in "LR":
        image = cv2.imread(str(DATA / f"bw_I_wet_{side}.jpg"), cv2.IMREAD_UNCHANGED)
        assert cv2.imwrite(str(folder / f"{side}.png"), np.ascontiguousarray(np.rot90(image, -1)))
    level = truth["scenes"]["bw_I_wet"]["water_level"]
    assert main(["reconstruct", str(folder / "L.png"), str(folder / "R.png"), "--rig", str(folder / "rig.json"),
                 "--water-level", str(level), "-o", str(folder / "survey.npz")]) == 0
    turned, as_mounted = _to_truth(rig, truth)(load_survey(folder / "survey.npz").points), _survey(flume, "bw_I_wet")
    assert abs(len(turned) / len(as_mounted) - 1) < 0.01  # 1,242,907 against 1,242,890 measured (693,900 before)
    gt = np.load(DATA / "breakwater_gt.npz")
    bw = truth["breakwater"]
    box = (bw["toe"] + 0.05, bw["toe"] + bw["slope"] * bw["height"] + 0.03, 0.05, bw["width"] - 0.05)
    mae = []
    for P in (turned, as_mounted):
        d, z = _c2m(P, gt["I"].astype(float), gt["x"], gt["y"], box)
        mae.append(np.mean(d[z < level - 0.01]))
    assert abs(mae[0] - mae[1]) <= 0.05  # the same scene to the same accuracy: 1.653 and 1.654 mm


def test_level_refined_against_a_dry_survey_is_within_half_a_millimetre_and_its_std(flume):
    """`refine` of the wet stage III pair with the dry survey of stage I as control (level and right pose), as the
    scorecard runs it. Its correspondences are measured along the rows as the survey measures its points; with the
    31 px Lucas-Kanade window (which put emerged rock 1.4-1.5 mm low against a DEM 0.3-0.4 mm low) the level came
    out -0.21 mm off here and 2.1 mm off (std 0.7 mm) on a POV-Ray flume of other rocks under 0.12 m of water."""
    work, truth, rig = flume
    _survey(flume, "bw_I_dry")
    true = truth["rigs"]["main"]["L"]
    R_c, t_c = np.asarray(rig["left"]["R"], float), np.asarray(rig["left"]["t"], float)
    level_in = lambda z: float((R_c.T @ (np.asarray(true["R"]) @ [0.4, 0.3, z] + true["t"] - t_c))[2])
    level = level_in(truth["scenes"]["bw_III_wet"]["water_level"])
    out = work / "rig_wet_dem.json"
    assert main(["refine", str(DATA / "bw_III_wet_L.jpg"), str(DATA / "bw_III_wet_R.jpg"), "--rig",
                 str(work / "rig.json"), "--water-level-guess", str(level + 0.012), "--control",
                 str(work / "bw_I_dry.npz"), "--refine", "water,right-pose", "-o", str(out)]) == 0
    refined = json.loads(out.read_text())["calibration"]["refine"]
    found, std = refined["parameters"]["water level (m)"]
    assert abs(found - level) <= 0.0005  # -0.18 mm measured, std 0.29 mm (from 2000 correspondences: +0.23, 0.32)
    assert abs(found - level) <= 2 * std
    # 6000 drawn against a DEM (`DEM_CORRESPONDENCES`): 2641 consistent with the rig here, 901 of 2000 before
    assert refined["correspondences"] > 2000


@pytest.fixture(scope="module")
def oblique_rig(flume):
    work, truth, _ = flume
    assert main(["calibrate", "--left", str(DATA / "calib_oblique" / "*_L.jpg"), "--right",
                 str(DATA / "calib_oblique" / "*_R.jpg"), "--board", "chessboard:9x6:%g" % truth["square"],
                 "--origin-left", str(DATA / "origin_oblique_L.jpg"), "--origin-right",
                 str(DATA / "origin_oblique_R.jpg"), "-o", str(work / "rig_oblique.json")]) == 0
    return work / "rig_oblique.json"


@pytest.mark.parametrize("scene", ["board_wet", "oblique_board_wet"])
def test_board_error_bars_are_honest_in_every_layer(flume, oblique_rig, scene):
    """Each point's predicted std normal to the board against its true error, per 5 cm layer: between 85 % and
    99.7 % of the points within 2 sigma, and the predicted RMS within 0.7-1.4 times the measured (issue #16)."""
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
    from experiments.uncertainty import board_errors
    from jaxstereo._stereo.evaluation import uncertainty_coverage

    work, truth, rig = flume
    rig_path = work / "rig.json" if scene == "board_wet" else oblique_rig
    out = work / f"{scene}.npz"  # the nadir board's survey is shared with the test above
    if not out.exists():
        assert main(["reconstruct", str(DATA / f"{scene}_L.jpg"), str(DATA / f"{scene}_R.jpg"), "--rig",
                     str(rig_path), "--water-level", str(truth["scenes"][scene]["water_level"]), "-o", str(out)]) == 0
    error, sigma, z, _ = board_errors(load_survey(out), json.loads(rig_path.read_text()), truth, scene)
    layers = uncertainty_coverage(error, sigma, z)
    assert len(layers) >= 5
    for layer in layers:
        # measured: nadir 93.2-99.6 %, ratio 0.82-1.18; oblique 92.8-97.7 %, ratio 0.94-1.36 (round 69; its
        # deepest layer 1.30 with the patches judged about their mean, not their plane; 1.36 before the check
        # against SGBM's own block): with the sub-pixel fit's linearisations blended inside the window sums, one
        # noise factor no longer fits both rigs (see `MATCH_NOISE_SCALE`; over 63 px patches the ratios were
        # 0.64-1.71). The nadir board's top layer (0.25-0.30 m, above the water) read 99.50 % (ratio 1.09) until
        # round 69's check on rows in pairs took 8 % off its RMS error (0.554 -> 0.508 mm) and left its bars:
        # 99.57 %, ratio 1.18, errors lighter-tailed than a normal law's (which puts 98.2 % within 2 sigma there).
        # For a normal law 99.7 % within 2 sigma means bars 1.5 times too wide; the ratio's 1.4 is the tighter cap.
        assert 0.85 <= layer["within_2_sigma"] <= 0.997, layer
        assert 0.7 <= layer["ratio"] <= 1.4, layer


def _to_ours(rig, truth):
    """The truth frame's points (n, 3) in the calibration's frame (the inverse of `_to_truth`)."""
    R_c, t_c = np.asarray(rig["left"]["R"], float), np.asarray(rig["left"]["t"], float)
    true = truth["rigs"]["main"]["L"]
    R_t, t_t = np.asarray(true["R"], float), np.asarray(true["t"], float)
    return lambda P: (R_c.T @ (R_t @ P.T + t_t[:, None] - t_c[:, None])).T


def _damage(flume, before, after, name, swl_offset=0.0):
    """`jaxstereo damage` between two surveys, one profile per 5 mm row, the design slope's toe and the SWL (plus
    `swl_offset`, metres) mapped from the truth into the calibration's frame (as `flume-score` gives them); the
    report's folder (made once per name)."""
    work, truth, rig = flume
    for scene in (before, after):
        _survey(flume, scene)
    bw = truth["breakwater"]
    level = truth["scenes"]["bw_I_wet"]["water_level"] + swl_offset
    toe, water = _to_ours(rig, truth)(np.array([[bw["toe"], 0.3, 0.0], [bw["toe"], 0.3, level]]))
    assert np.allclose(_to_truth(rig, truth)(toe[None])[0], [bw["toe"], 0.3, 0.0])
    out = work / name
    if (out / "damage.json").exists():
        return out
    assert main(["damage", str(work / f"{before}.npz"), str(work / f"{after}.npz"), "--dn50", str(bw["dn50"]),
                 "--slope", str(bw["slope"]), "--swl", f"{water[2]:.5f}", "--slope-origin", f"{toe[0]:.5f}",
                 f"{toe[2]:.5f}", "--profile-spacing", "0.005", "-o", str(out)]) == 0
    return out


def test_undamaged_model_dry_against_wet_reports_S_within_its_error_bars(flume):
    """`jaxstereo damage` between the dry and the wet survey of the undamaged model, one profile per 5 mm row:
    every true S is 0, so every profile's S is at most 0.5 (issue #13) and lies within its sigma. Along a rock's
    edge the dry survey shows the rock's top and the wet one the crevice beside it (cells seen in part, filled, or
    across the edge): those cells take the change of the cells around them that both surveys saw wholly."""
    out = _damage(flume, "bw_I_dry", "bw_I_wet", "damage_undamaged")
    report = json.loads((out / "damage.json").read_text())
    profiles = [p for p in report["profiles"] if p["S_sigma"] is not None]
    z = np.array([p["S"] / p["S_sigma"] for p in profiles])
    assert len(profiles) >= 60
    # 0.10 measured since round 68's wider neighbourhood of the carried change (0.07 before; 0.64 comparing every
    # cell as surveyed), 35 % of the cells carried
    assert report["S_max"] <= 0.5 and report["averaged_profile"]["S"] <= 0.1
    assert 0.1 <= report["change_carried_from_seen_cells"]["share_of_cells"] <= 0.5
    # 116 of 116 measured; with 72 profiles a calibrated sigma gives 95 +- 2.5 %, hence the bound of issue #16's
    # trials, 90 %
    assert np.mean(z <= 2) >= 0.9
    # 0.97 measured: S 0.054 +- 0.056 at y = 0.275 m; the largest S, 0.098, has sigma 0.124 (before round 68: 1.74,
    # S 0.050 +- 0.029 at y = 0.210 m)
    assert z.max() <= 3
    # Every true d_e and L_e is 0 too. Measured: the largest d_e 8.3 mm (E2D 0.24; 18.9 mm before round 66, 25.9 mm
    # in round 66, where two zones 0.2 mm apart at a rock's face joined into one whose depth was the sliver between
    # the two surveys' envelopes at that face, and 17.1 mm elsewhere from a face that overhung the slope in one survey
    # and not in the other: since round 67 both are edges of one face, bridged, see `_paired_edges`), and each
    # profile's 95 % intervals of d_e and L_e hold 0 at 116 of 116 profiles, as do the stretch's largest d_e's and
    # L_e's (185 mm, [0, 385]). While the two surveys' edges of one overhanging face were two edges, the slivers
    # between them read 110 mm (E2D 3.1), and 89 of 115 d_e intervals held 0; while a zone's length and depth were
    # bounded on their own draws alone, 112 of 115, and no L_e interval held 0 ([131, 281] mm over the stretch).
    assert report["d_e_max_m"] <= 0.015
    held = [p["interval_95"]["d_e_m"][0] == 0.0 and p["interval_95"]["L_e_m"][0] == 0.0
            for p in report["profiles"] if "interval_95" in p]
    assert len(held) >= 60 and np.mean(held) >= 0.95
    assert report["interval_95"]["d_e_max_m"][0] == 0.0 and report["interval_95"]["L_e_max_m"][0] == 0.0


def _profiles_near_the_hole(flume, stage: str, out: Path):
    """Each profile of `out`'s damage.json within 25 mm of the hole's centre (truth frame) with the same profile's
    figures on the true 1 mm surfaces of stages I and `stage` (the same damage definitions: the profiler's foot,
    the active zone, the sweep): a list of (y in the truth frame, the report's profile, the true `ProfileDamage`)."""
    from jaxstereo import DEM, stretch_damage

    _, truth, rig = flume
    bw = truth["breakwater"]
    g = np.load(DATA / "breakwater_gt.npz")
    surfaces = [DEM(g["x"], g["y"], g[k].astype(float), float(g["x"][1] - g["x"][0])) for k in ("I", stage)]
    yc = bw["hole_centre_xy"][1]
    true = stretch_damage(*surfaces, bw["dn50"], bw["slope"], truth["scenes"]["bw_I_wet"]["water_level"],
                          (bw["toe"], 0.0), 0.001, stretch=(yc - 0.03, yc + 0.03))
    true_y = np.array([y for y, _ in true.profiles])
    to_truth = _to_truth(rig, truth)
    near = []
    for p in json.loads((out / "damage.json").read_text())["profiles"]:
        y = to_truth(np.array([[bw["hole_centre_xy"][0], p["y_m"], 0.1]]))[0, 1]
        if abs(y - yc) <= 0.025:
            near.append((y, p, true.profiles[int(np.argmin(np.abs(true_y - y)))][1]))
    return near


def test_profiles_through_the_hole_have_error_bars_that_cover_the_truth(flume):
    """Stage III against stage I, both wet: each profile within 25 mm of the hole's centre has A_e and d_e within
    2 sigma of the same figures on the true 1 mm surfaces, and L_e within its 95 % interval. The survey reads the
    hole's floor beside its landward wall high (a window straddling the wall, the band the right camera cannot
    see), so d_e errs by up to 15 mm (1.4 sigma): the error bar must say so. The profile's sigma and interval are
    in the JSON and the CSV alike."""
    import csv

    out = _damage(flume, "bw_I_wet", "bw_III_wet", "damage_stage_III")
    with open(out / "profiles.csv", newline="") as f:
        csv_rows = {row["y_m"]: row for row in csv.DictReader(f)}
    checked = []
    for y, p, reference in _profiles_near_the_hole(flume, "III", out):
        sigma = p["sigma"]
        assert float(csv_rows[f"{p['y_m']:.4f}"]["d_e_sigma_m"]) == pytest.approx(sigma["d_e_m"], rel=5e-3)  # 3 digits
        low, high = p["interval_95"]["L_e_m"]
        assert float(csv_rows[f"{p['y_m']:.4f}"]["L_e_low_m"]) == pytest.approx(low, rel=5e-3)
        # at least the 2 sigma band, less what lies below zero (a zone's length is not negative)
        assert low <= max(p["L_e_m"] - 2 * sigma["L_e_m"], 0.0) + 1e-12
        assert high >= p["L_e_m"] + 2 * sigma["L_e_m"] - 1e-12
        assert low <= reference.L_e <= high, (y, p["L_e_m"], reference.L_e, low, high)  # L_e reads long, by 1-32 mm
        checked.append(((p["d_e_m"] - reference.d_e) / sigma["d_e_m"], (p["A_e_m2"] - reference.A_e) / sigma["A_e_m2"]))
    z = np.abs(np.array(checked))
    assert len(checked) >= 9
    # Measured: d_e within 0.22 sigma (the central profile 99.5 +- 27.3 mm against 98.5), A_e within 0.60 sigma
    # (before round 68: 0.30 and 0.52; 31 px patch: 1.39 and 0.71).
    assert z.max() <= 2.0, checked


def test_a_zone_the_surveys_join_across_an_unmoved_rock_has_an_interval_that_holds_the_truth(flume):
    """Stage II against stage I, both wet. Two pits with an unmoved rock between them: the truth is at zero over
    about 20 mm there and keeps the pits apart (the central profile's L_e 70 mm), the surveys read that rock 3-7 mm
    lower after than before and join them (144 mm, 1.5 sigma away). Some draws of the surveys' errors split the
    zone: of the 95 % intervals of the profiles within 25 mm of the hole's centre (A_e, L_e and d_e each) all but
    two hold the truth, at most one of them an A_e's or an L_e's.

    The two lie 1-4 mm (in y) from a step of the true d_e (48 -> 67 mm at y 0.274 m, 59 -> 41 mm at 0.298 m). With
    the profiler's foot closed on the cells themselves both were d_e's, 60 and 41 mm against 68 and 59 ([53, 66] and
    [33, 55] mm); closed on the DEM's bilinear surface, the first (60 against 68 mm, [53, 66]) and the A_e at 0.295 m,
    28.9 cm2 against 34.5 ([22.8, 33.4]). Their intervals held the truth while the faces' edges, placed apart by the
    two surveys, read as slivers as deep as the faces: the draws then ranged from 18 to 76 mm and from 6 to 144 mm,
    intervals that said nothing."""
    out = _damage(flume, "bw_I_wet", "bw_II_wet", "damage_stage_II")
    near = _profiles_near_the_hole(flume, "II", out)
    outside = []
    for y, p, reference in near:
        true = profile_figures(reference)
        for key in ("A_e_m2", "L_e_m", "d_e_m"):
            low, high = p["interval_95"][key]
            if not low <= true[key] <= high:
                outside.append((round(y, 4), key, p[key], true[key], low, high))
    assert len(near) >= 9
    # Measured: 30 of 30 held (28 with the 31 px patch); the central profile's L_e 199.6 +- 73.2 mm against 69.7
    # (122.8 +- 63.5 before round 68)
    # (31 px: 143.5 +- 50.2; 174.4 +- 52.6 with the patches judged about their mean, not their plane: outside
    # 2 sigma). With the 47 px patch and the correlation width left at 31 px, the A_e intervals at y 0.295 and
    # 0.305 m missed ([27.1, 34.1] cm2 against 34.5, [14.1, 23.2] against 23.7).
    assert len([o for o in outside if o[1] != "d_e_m"]) <= 1, outside
    assert len(outside) <= 2, outside


@pytest.mark.parametrize("swl_offset", [0.055, -0.065])
def test_the_hole_counts_whole_with_the_swl_given_higher_or_lower(flume, swl_offset):
    """Stage III against stage I, both wet, with the SWL given 5.5 cm higher or 6.5 cm lower than the water's:
    the hole (from 3.1 Dn50 under the SWL to 0.4 Dn50 over it) still reaches into the active zone, and the
    profile through its centre reads the same A_e, L_e and d_e as at the true SWL. (While the active zone was a
    cut, the central profile's A_e fell by 35 % and by 5 %.)"""
    _, truth, rig = flume
    bw = truth["breakwater"]
    yc = _to_ours(rig, truth)(np.array([[bw["hole_centre_xy"][0], bw["hole_centre_xy"][1], 0.1]]))[0, 1]

    def central(out):
        return min(json.loads((out / "damage.json").read_text())["profiles"], key=lambda p: abs(p["y_m"] - yc))

    at_level = central(_damage(flume, "bw_I_wet", "bw_III_wet", "damage_stage_III"))
    moved = central(_damage(flume, "bw_I_wet", "bw_III_wet", f"damage_stage_III_swl{swl_offset:+.3f}", swl_offset))
    assert moved["y_m"] == at_level["y_m"] and at_level["A_e_m2"] > 0.007  # the truth: 0.0076 m2
    for key in ("A_e_m2", "L_e_m", "d_e_m"):
        assert moved[key] == pytest.approx(at_level[key], rel=1e-9), key


def test_damage_of_the_true_surfaces_is_the_same_in_a_frame_running_down_the_slope():
    """A rig whose cameras are turned 180 degrees about their axes sees the origin board the other way round: its
    world frame's x runs down the slope (the development flume's oblique rig's frame is turned so). The stage III
    damage of the true surfaces (5 mm cells), measured in that frame (x and y negated), is the same, profile by
    profile, and so is the slope's direction, found from the initial surface: with the frame's x down the slope the
    command refused ("no cross-section of the initial survey follows the design slope")."""
    from jaxstereo import DEM, stretch_damage

    truth = json.loads((DATA / "truth.json").read_text())
    bw, level = truth["breakwater"], truth["scenes"]["bw_I_wet"]["water_level"]
    g = np.load(DATA / "breakwater_gt.npz")
    x, y = g["x"][::5], g["y"][::5]
    surfaces = [DEM(x, y, g[k][::5, ::5].astype(float), float(x[1] - x[0])) for k in ("I", "III")]
    turned = [DEM(-x[::-1], -y[::-1], s.z[::-1, ::-1], s.spacing) for s in surfaces]
    found = stretch_damage(*surfaces, bw["dn50"], bw["slope"], level, (bw["toe"], 0.0), 0.005)
    other = stretch_damage(*turned, bw["dn50"], bw["slope"], level, (-bw["toe"], 0.0), 0.005)
    assert (found.rises_toward, other.rises_toward) == ("+x", "-x")
    by_y = {round(-yy, 4): p for yy, p in other.profiles}
    pairs = [(p, by_y[round(yy, 4)]) for yy, p in found.profiles if round(yy, 4) in by_y]
    assert len(pairs) >= 0.9 * len(found.profiles) and max(p.S for p, _ in pairs) > 5
    assert [q.A_e for _, q in pairs] == pytest.approx([p.A_e for p, _ in pairs], rel=1e-9, abs=1e-12)
    assert [q.d_e for _, q in pairs] == pytest.approx([p.d_e for p, _ in pairs], rel=1e-9, abs=1e-12)
    assert other.volumes.E3D == pytest.approx(found.volumes.E3D, rel=1e-9)
    assert np.allclose(other.volumes.E3D_xy, np.negative(found.volumes.E3D_xy))
