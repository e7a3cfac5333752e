import numpy as np
import pytest

import jaxstereo as js
from jaxstereo._damage import damage_level, dem_damage, parse_slope, profile_damage, to_slope_frame
from jaxstereo._grid import DEM, grid_median
from jaxstereo._profiles import moving_average, profile_from_dem

COT = 2.0
DN50 = 0.036


def _slope_profile(Xp, Zp, cot=COT, origin=(0.1, 0.05)):
    """Map slope-frame points (X' along, Z' normal) back to world (x, z)."""
    norm = np.hypot(cot, 1.0)
    t = np.array([cot, 1.0]) / norm
    n = np.array([-1.0, cot]) / norm
    x = origin[0] + Xp * t[0] + Zp * n[0]
    z = origin[1] + Xp * t[1] + Zp * n[1]
    return x, z


def _notch(X, centre, top_len, bottom_len, depth):
    """Z' of a trapezoidal notch (triangle when bottom_len = 0) cut into the slope line Z' = 0."""
    a = np.abs(X - centre)
    half_top, half_bot = top_len / 2, bottom_len / 2
    ramp = np.clip((half_top - a) / (half_top - half_bot), 0.0, 1.0) if half_top > half_bot else (a <= half_top) * 1.0
    return -depth * ramp


@pytest.mark.parametrize("bottom", [0.0, 0.04])
def test_analytic_notch(bottom):
    X = np.linspace(-0.5, 0.5, 1001)  # initial profile sampled on its own abscissae
    Xf = np.linspace(-0.5, 0.5, 777) + 1e-4  # final profile on others: merging is exercised
    top, depth, centre = 0.12, 0.05, 0.031
    # Make sure the notch's corners are vertices of the final polyline.
    Xf = np.unique(np.concatenate([Xf, [centre - top / 2, centre + top / 2, centre - bottom / 2, centre + bottom / 2]]))
    initial = _slope_profile(X, np.zeros_like(X))
    final = _slope_profile(Xf, _notch(Xf, centre, top, bottom, depth))
    dmg = profile_damage(initial, final, DN50, COT, origin=(0.1, 0.05))
    area = (top + bottom) / 2 * depth
    assert abs(dmg.A_e - area) < 1e-9
    assert abs(dmg.L_e - top) < 1e-9
    assert abs(dmg.d_e - depth) < 1e-9
    assert abs(dmg.S - area / DN50**2) < 1e-6
    assert abs(dmg.E2D - depth / DN50) < 1e-6
    assert dmg.accretion == []


def test_several_holes_are_all_found_and_the_largest_chosen():
    X = np.unique(np.concatenate([np.linspace(-0.6, 0.6, 1201), [-0.35, -0.3, -0.25, 0.0, 0.05, 0.1, 0.3, 0.32, 0.34]]))
    Z = (_notch(X, -0.3, 0.1, 0.0, 0.02) + _notch(X, 0.05, 0.1, 0.0, 0.06) + _notch(X, 0.32, 0.04, 0.0, 0.01))
    dmg = profile_damage(_slope_profile(X, 0 * X), _slope_profile(X, Z), DN50, COT, origin=(0.1, 0.05))
    assert len(dmg.erosion) == 3
    areas = sorted(z.area for z in dmg.erosion)
    np.testing.assert_allclose(areas, [0.04 * 0.01 / 2, 0.1 * 0.02 / 2, 0.1 * 0.06 / 2], atol=1e-12)
    assert abs(dmg.A_e - 0.003) < 1e-12 and abs(dmg.d_e - 0.06) < 1e-12 and abs(dmg.L_e - 0.1) < 1e-12


def test_pure_accretion_gives_zero_damage():
    X = np.unique(np.concatenate([np.linspace(-0.5, 0.5, 501), [-0.1, -0.025, 0.025, 0.1]]))
    Z = -_notch(X, 0.0, 0.2, 0.05, 0.03)  # a mound
    dmg = profile_damage(_slope_profile(X, 0 * X), _slope_profile(X, Z), DN50, COT, origin=(0.1, 0.05))
    assert dmg.S == 0 and dmg.A_e == 0 and dmg.erosion == []
    assert len(dmg.accretion) == 1 and abs(dmg.accretion[0].area - 0.125 * 0.03) < 1e-9


def test_slope_frame_rotation_keeps_lengths():
    x = np.array([0.0, 2.0, 3.0])
    z = np.array([0.0, 1.0, 0.5])
    X, Z = to_slope_frame(x, z, 2.0)
    np.testing.assert_allclose(np.hypot(np.diff(X), np.diff(Z)), np.hypot(np.diff(x), np.diff(z)), atol=1e-15)
    np.testing.assert_allclose(Z[:2], 0.0, atol=1e-15)  # points on the slope line


def test_dem_volumes_and_e3d_of_a_cylindrical_hole():
    spacing = 0.002
    x = np.arange(-0.3, 0.3 + 1e-9, spacing)
    y = np.arange(-0.2, 0.2 + 1e-9, spacing)
    X, Y = np.meshgrid(x, y)
    before = DEM(x, y, 0.5 * X, spacing)
    hole = (X - 0.05) ** 2 + (Y + 0.02) ** 2 <= 0.04**2
    mound = (X + 0.2) ** 2 + Y**2 <= 0.02**2
    after_z = before.z - 0.03 * hole + 0.01 * mound
    dmg = dem_damage(before, DEM(x, y, after_z, spacing), DN50)
    assert abs(dmg.eroded_m3 - 0.03 * hole.sum() * spacing**2) < 1e-12
    assert abs(dmg.accreted_m3 - 0.01 * mound.sum() * spacing**2) < 1e-12
    assert abs(dmg.E3D - 0.03 / DN50) < 1e-9  # the Dn50 circle fits inside the 80 mm hole
    # Anywhere the Dn50 circle fits in the hole (centre within 40 - 18 mm of its axis) is a maximum.
    assert np.hypot(dmg.E3D_xy[0] - 0.05, dmg.E3D_xy[1] + 0.02) <= 0.022 + spacing


def test_gridding_median_and_profiles():
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(0, 1, 200000), rng.uniform(0, 0.5, 200000), np.zeros(200000)])
    pts[:, 2] = 0.3 * pts[:, 0] + 0.1
    dem = grid_median(pts, 0.01)
    X, _ = np.meshgrid(dem.x, dem.y)
    interior = np.isfinite(dem.z)
    assert interior.mean() > 0.9
    assert np.nanmax(np.abs(dem.z - (0.3 * X + 0.1))) < 0.3 * 0.006  # within a cell of the plane
    s, z = profile_from_dem(dem, (0.1, 0.25), (0.9, 0.25))
    np.testing.assert_allclose(z, 0.3 * (0.1 + s) + 0.1, atol=2e-3)
    np.testing.assert_allclose(moving_average(np.arange(10.0), 5)[2:-2], np.arange(10.0)[2:-2])


def test_bad_damage_input():
    for text in ["steep", "-2", "1:0", "0"]:
        with pytest.raises(js.JaxStereoError, match="slope"):
            parse_slope(text)
    assert parse_slope("1:2") == 2.0 and parse_slope("2") == 2.0 and parse_slope("2:3") == 1.5
    X = np.linspace(0, 1, 10)
    with pytest.raises(js.JaxStereoError, match="Dn50 must be positive"):
        profile_damage((X, X), (X, X), 0.0, 2.0)
    with pytest.raises(js.JaxStereoError, match="do not overlap"):
        profile_damage((X, 0 * X), (X + 5, 0 * X), 0.036, 2.0)
    a = DEM(np.arange(3.0), np.arange(2.0), np.zeros((2, 3)), 1.0)
    b = DEM(np.arange(4.0), np.arange(2.0), np.zeros((2, 4)), 1.0)
    with pytest.raises(js.JaxStereoError, match="same grid"):
        dem_damage(a, b, 0.036)
    nan = DEM(a.x, a.y, np.full((2, 3), np.nan), 1.0)
    with pytest.raises(js.JaxStereoError, match="do not overlap"):
        dem_damage(a, nan, 0.036)


def test_damage_levels():
    assert damage_level(1.0, 2.0) == "no damage"
    assert damage_level(2.5, 2.0) == "start of damage"
    assert damage_level(5.0, 2.0) == "intermediate damage"
    assert damage_level(9.0, 2.0) == "failure"
    assert damage_level(10.0, 3.0) == "advanced damage"
