import itertools
import json

import numpy as np
import pytest

from jaxstereo._app.cli import main
from jaxstereo._stereo.survey import Survey, save_survey
from jaxstereo._surface.grid import load_dem


def _survey(path, points):
    n = points.shape[0]
    save_survey(Survey(points, np.zeros((n, 3), np.uint8), np.zeros((n, 2)), np.zeros(n, bool), "{}", "exact", 0.158),
                path)


def _slope_cloud(rng, n=300000, hole=False, shift=0.0):
    xy = rng.uniform([-0.3, -0.15], [0.5, 0.15], (n, 2))
    z = np.clip((xy[:, 0] + 0.3) / 2.0, 0, 0.31)
    if hole:  # a 3 cm deep pit around the still water level, 12 cm across
        r = np.hypot(xy[:, 0] - 0.016, xy[:, 1])
        z = z - 0.03 * np.clip(1 - r / 0.06, 0, 1)
    return np.column_stack([xy[:, 0] + shift, xy[:, 1], z])


@pytest.fixture(scope="module")
def surveys(tmp_path_factory):
    root = tmp_path_factory.mktemp("surveys")
    rng = np.random.default_rng(1)
    _survey(root / "before.npz", _slope_cloud(rng))
    _survey(root / "after.npz", _slope_cloud(rng, hole=True))
    _survey(root / "elsewhere.npz", _slope_cloud(rng, shift=5.0))
    return root


def test_grid_and_damage_commands(surveys, tmp_path, capsys):
    assert main(["grid", str(surveys / "before.npz"), "--spacing", "0.005", "-o", str(tmp_path / "before_dem.npz")]) == 0
    dem = load_dem(tmp_path / "before_dem.npz")
    X, _ = np.meshgrid(dem.x, dem.y)
    assert np.nanmedian(np.abs(dem.z - np.clip((X + 0.3) / 2, 0, 0.31))) < 1e-3
    code = main(["damage", str(tmp_path / "before_dem.npz"), str(surveys / "after.npz"), "--dn50", "0.036",
                 "--slope", "1:2", "--swl", "0.158", "--slope-origin", "-0.3", "0.0", "-o", str(tmp_path / "report")])
    assert code == 0
    out = capsys.readouterr().out
    assert "averaged profile" in out and "E3D" in out
    report = json.loads((tmp_path / "report" / "damage.json").read_text())
    # The pit's volume is pi r^2 h / 3 (a cone, 12 cm across, 3 cm deep) measured vertically. Gridding
    # noise (about 0.2 mm per cell here) adds to both the eroded and the accreted sums; the net is the pit.
    cone = np.pi * 0.06**2 * 0.03 / 3
    assert abs(report["eroded_volume_m3"] - report["accreted_volume_m3"] - cone) < 0.05 * cone
    assert report["accreted_volume_m3"] < 0.3 * cone
    # E3D: the cone's depth averaged over the Dn50 circle at its axis, 0.03 (1 - (2/3) 0.018 / 0.06), over Dn50.
    assert abs(report["E3D"] - 0.03 * (1 - 2 / 3 * 0.018 / 0.06) / 0.036) < 0.03 * report["E3D"]
    assert report["S_max"] > report["averaged_profile"]["S"] > 0
    # surveys without error bars have no coverage layer: every cell counts as seen, none takes another's change
    assert report["change_carried_from_seen_cells"] == {"share_of_cells": 0.0, "coverage_tolerance_m": 0.0}
    worst = next(p for p in report["profiles"] if p["y_m"] == report["S_max_at_y_m"])
    assert worst["S"] == report["S_max"] and abs(worst["y_m"]) < 0.06  # a profile through the pit
    assert f"(y {report['S_max_at_y_m']:+.3f} m)" in out
    for profile in report["profiles"]:  # each profile's zones, the largest giving its A_e and d_e
        zones = profile["erosion"]
        assert len(zones) == profile["erosion_zones"]
        assert all(z["start_m"] < z["end_m"] and z["A_e_m2"] > 0 for z in zones)
        assert all(a["end_m"] <= b["start_m"] for a, b in itertools.pairwise(zones))
        if zones:
            largest = max(zones, key=lambda z: z["A_e_m2"])
            assert (largest["A_e_m2"], largest["d_e_m"]) == (profile["A_e_m2"], profile["d_e_m"])
            assert largest["end_m"] - largest["start_m"] == pytest.approx(profile["L_e_m"], abs=1e-12)
    assert max(p["A_e_m2"] for p in report["profiles"]) > 0
    for name in ("profiles.csv", "profile.png", "difference.png"):
        assert (tmp_path / "report" / name).stat().st_size > 0


def test_slope_points_set_the_direction_the_slope_rises(surveys, tmp_path, capsys):
    """--slope-points say which way the slope rises (the order of their heights): on the fixture's model mirrored
    in x (rising toward -x) the damage is the unmirrored model's; points that rise the other way than the initial
    survey are taken as given, with a warning."""
    rng = np.random.default_rng(1)
    mirrored = {}
    for name, hole in (("before", False), ("after", True)):
        cloud = _slope_cloud(rng, hole=hole)
        cloud[:, 0] *= -1.0
        mirrored[name] = tmp_path / f"{name}_mirrored.npz"
        _survey(mirrored[name], cloud)
    common = ["--dn50", "0.036", "--slope", "1:2", "--swl", "0.158", "--profile-spacing", "0.036"]

    def damage(before, after, line, name):
        assert main(["damage", str(before), str(after), *common, *line, "-o", str(tmp_path / name)]) == 0
        return json.loads((tmp_path / name / "damage.json").read_text()), capsys.readouterr().out

    straight, _ = damage(surveys / "before.npz", surveys / "after.npz", ["--slope-origin", "-0.3", "0.0"], "straight")
    down, out = damage(mirrored["before"], mirrored["after"], ["--slope-points", "0.3", "0.0", "-0.3", "0.3"], "down")
    assert "WARNING" not in out
    assert (straight["slope_rises_toward"], down["slope_rises_toward"]) == ("+x", "-x")
    a, b = straight["averaged_profile"], down["averaged_profile"]
    assert a["A_e_m2"] > 0 and abs(b["A_e_m2"] - a["A_e_m2"]) < 0.05 * a["A_e_m2"]
    assert abs(b["d_e_m"] - a["d_e_m"]) < 1e-3
    # the same points listed from the top: the same line, the same direction
    top_first, _ = damage(mirrored["before"], mirrored["after"], ["--slope-points", "-0.3", "0.3", "0.3", "0.0"],
                          "top_first")
    assert top_first["slope_rises_toward"] == "-x" and top_first["averaged_profile"] == pytest.approx(b, rel=1e-9)
    # points rising toward +x through the mirrored model: taken as given, said to contradict the survey, and the
    # line then lies on no cross-section of it: refused, nothing written
    code = main(["damage", str(mirrored["before"]), str(mirrored["after"]), *common,
                 "--slope-points", "0.3", "0.0", "0.9", "0.3", "-o", str(tmp_path / "against")])
    captured = capsys.readouterr()
    assert "WARNING: --slope-points rise toward +x, but the initial survey follows a slope rising toward -x" in captured.out
    assert code == 2 and "no cross-section of the initial survey follows the design slope" in captured.err
    assert not (tmp_path / "against").exists()


def _error(capsys, code, text):
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and text in err, err


def test_damage_bad_input(surveys, tmp_path, capsys):
    base = [str(surveys / "before.npz"), str(surveys / "after.npz"), "--swl", "0.158", "-o", str(tmp_path / "r")]
    _error(capsys, main(["damage", *base, "--dn50", "0", "--slope", "2"]), "--dn50 must be positive")
    _error(capsys, main(["damage", *base, "--dn50", "-0.03", "--slope", "2"]), "--dn50 must be positive")
    _error(capsys, main(["damage", *base, "--dn50", "0.036", "--slope", "steep"]), "slope 'steep' does not parse")
    _error(capsys, main(["damage", *base, "--dn50", "0.036", "--slope", "2", "--seen-tolerance", "-0.001"]),
           "--seen-tolerance must be 0 or more")
    _error(capsys, main(["damage", str(surveys / "before.npz"), str(surveys / "elsewhere.npz"), "--swl", "0.158",
                         "--dn50", "0.036", "--slope", "2", "-o", str(tmp_path / "r")]), "do not overlap")
    _error(capsys, main(["damage", str(surveys / "missing.npz"), str(surveys / "after.npz"), "--swl", "0.158",
                         "--dn50", "0.036", "--slope", "2", "-o", str(tmp_path / "r")]), "does not exist")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    _error(capsys, main(["grid", str(tmp_path / "junk.npz"), "-o", str(tmp_path / "d.npz")]), "cannot be read")
    assert not (tmp_path / "r").exists() and not (tmp_path / "d.npz").exists()
