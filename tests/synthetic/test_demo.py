"""The README's first command, run as a test: the demo's numbers against the synthetic truth."""

import json

from jaxstereo._app.cli import main
from jaxstereo._surface.damage import damage_level


def test_demo_runs_end_to_end(tmp_path, capsys):
    assert main(["demo", "-o", str(tmp_path / "demo")]) == 0
    summary = json.loads((tmp_path / "demo" / "summary.json").read_text())
    c = summary["calibration"]
    assert abs(c["baseline_m"] - c["baseline_true_m"]) < 2e-4
    assert abs(c["camera_height_m"] - c["camera_height_true_m"]) < 2e-3
    assert abs(summary["refine"]["water_level_m"] - summary["refine"]["true_m"]) < 3e-3
    s2 = summary["damage"]["II"]["averaged_profile"]["S"]
    s3 = summary["damage"]["III"]["averaged_profile"]["S"]
    assert 0 < s2 < s3
    sigma, (low, high) = summary["damage"]["III"]["sigma"]["S"], summary["damage"]["III"]["interval_95"]["S"]
    assert 0 <= low <= s3 - 2 * sigma + 1e-12 and high >= s3 + 2 * sigma - 1e-12  # the 95 % interval holds +- 2 sigma
    report = (tmp_path / "demo" / "report.md").read_text()
    assert f"[{low:.2f}, {high:.2f}]" in report
    # The report shows the tested stretch, the active zone and a level that is the one of the S it prints.
    d3 = summary["damage"]["III"]
    assert d3["damage_level"] == damage_level(s3, 2.0) and f"| {d3['damage_level']} |" in report
    assert not d3["whole_surveyed_width"] and d3["stretch_y_m"][0] < d3["stretch_y_m"][1]
    z0, z1 = d3["active_zone_z_m"]
    assert "Tested stretch y" in report and f"active zone z {z0:.3f} to {z1:.3f} m" in report
    for name in ("report.md", "calibration_errors.png", "damage_vs_stage.png", "damage_stageIII/profile.png",
                 "surveys/stageIII.npz", "rig_wet.json"):
        assert (tmp_path / "demo" / name).stat().st_size > 0
    assert "done:" in capsys.readouterr().out
