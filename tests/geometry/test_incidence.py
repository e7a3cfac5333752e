import numpy as np
import pytest

import jaxstereo as js
from jaxstereo._app.cli import main


def test_incidence_report_command_prints_table_and_writes_figure(tmp_path, capsys):
    png = tmp_path / "incidence.png"
    md = tmp_path / "incidence.md"
    assert main(["incidence-report", "-o", str(png), "--markdown", str(md)]) == 0
    out = capsys.readouterr().out
    row20 = next(line for line in out.splitlines() if line.startswith("| 20.0 "))
    row30 = next(line for line in out.splitlines() if line.startswith("| 30.0 "))
    assert row20.split("|")[4].strip() == "0.405"
    assert row30.split("|")[4].strip() == "1.388"
    assert "angle_error_deg > 0.5 deg: first exceeded at 25 deg" in out
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "| 40.0 |" in md.read_text()
    assert not list(tmp_path.glob(".*"))  # no temporary files left behind


def test_incidence_report_bad_input_is_one_line_error(tmp_path, capsys):
    assert main(["incidence-report", "--height", "-2", "-o", str(tmp_path / "x.png")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == "jaxstereo incidence-report: error: height_m must be positive, got -2.0"
    assert not (tmp_path / "x.png").exists()
    with pytest.raises(js.JaxStereoError, match="incidence_deg"):
        js.incidence_report([95.0])


def test_three_d_error_vanishes_for_a_shallow_point():
    # The first-order model's 3-D error scales with the depth under water.
    deep = js.incidence_report([20.0], js.IncidenceRig(depth_m=0.3))
    shallow = js.incidence_report([20.0], js.IncidenceRig(depth_m=0.003))
    assert shallow.error_3d_mm[0] < 0.02 * deep.error_3d_mm[0]
    assert np.all(np.isfinite(deep.error_3d_mm))


def test_predicted_sigma_z_matches_the_paraxial_formula_straight_down():
    """Straight down, a point at depth D appears at D / n (paraxial), at Z = H + D / n from the cameras, so a
    disparity error s moves it by n Z^2 / (f B) s vertically; off-axis the prediction grows."""
    rig = js.IncidenceRig(disparity_noise_px=0.2)
    report = js.incidence_report([0.0, 30.0], rig, sigma_depths_m=[0.1, 0.3])
    n = rig.n_water / rig.n_air
    for k, depth in enumerate((0.1, 0.3)):
        z = rig.height_m + depth / n
        expected = 1e3 * n * z**2 / (rig.focal_px * rig.baseline_m) * 0.2
        assert report.sigma_z_mm[k, 0] == pytest.approx(expected, rel=0.01)
        assert report.sigma_z_mm[k, 1] > 1.05 * report.sigma_z_mm[k, 0]
    assert "sigma_z at 0.3 m (mm)" in report.to_markdown()
