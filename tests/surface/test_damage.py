import numpy as np
import pytest

import jaxstereo as js
from jaxstereo._surface.damage import (
    damage_level,
    damage_thresholds,
    dem_damage,
    parse_slope,
    profile_damage,
    slope_abscissa,
    to_slope_frame,
)
from jaxstereo._surface.grid import DEM, grid_median
from jaxstereo._surface.profiles import moving_average, profile_from_dem

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


def test_two_pits_that_touch_at_one_point_are_one_zone_and_a_stretch_between_splits_them():
    """The paper's sweep: where the final profile only touches the initial one (an unmoved rock's top between two
    removed ones) the erosion zone goes on; a stretch of the slope left as it was ends it."""
    for gap in (0.0, 0.03):
        X = np.unique(np.concatenate([np.linspace(-0.5, 0.5, 1001), [-0.1, 0.0, gap, gap + 0.1]]))
        Z = _notch(X, -0.05, 0.1, 0.0, 0.04) + _notch(X, gap + 0.05, 0.1, 0.0, 0.02)
        dmg = profile_damage(_slope_profile(X, 0 * X), _slope_profile(X, Z), DN50, COT, origin=(0.1, 0.05))
        if gap == 0.0:
            assert len(dmg.erosion) == 1
            assert dmg.A_e == pytest.approx(0.1 * 0.04 / 2 + 0.1 * 0.02 / 2, abs=1e-12)
            assert dmg.L_e == pytest.approx(0.2, abs=1e-12) and dmg.d_e == pytest.approx(0.04, abs=1e-12)
        else:
            assert len(dmg.erosion) == 2
            assert dmg.A_e == pytest.approx(0.1 * 0.04 / 2, abs=1e-12) and dmg.L_e == pytest.approx(0.1, abs=1e-12)


def _zones_one_piece_at_a_time(X, D, sign):
    """The sweep of `damage._zones` written as a loop over the pieces (a reference): (start, end, area, depth)."""
    zones, current = [], None
    for x0, x1, v0, v1 in zip(X[:-1], X[1:], sign * D[:-1], sign * D[1:]):
        pieces = [(x0, x1, v0, v1)]
        if v0 * v1 < 0:
            xc = x0 + (x1 - x0) * v0 / (v0 - v1)
            pieces = [(x0, xc, v0, 0.0), (xc, x1, 0.0, v1)]
        for a, b, va, vb in pieces:
            if va > 0 or vb > 0:
                current = current or [a, a, 0.0, 0.0]
                current[1:] = [b, current[2] + 0.5 * (max(va, 0) + max(vb, 0)) * (b - a), max(current[3], va, vb)]
            elif current is not None and b > a:
                zones.append(tuple(current))
                current = None
    return zones + ([tuple(current)] if current is not None else [])


def test_zones_match_a_loop_over_the_pieces_on_random_differences():
    """Repeated abscissae (an envelope's jump), zeros (profiles that touch) and crossings, in any mix."""
    from jaxstereo._surface.damage import _zones

    rng = np.random.default_rng(5)
    for trial in range(400):
        X = np.sort(rng.uniform(0.0, 1.0, rng.integers(2, 40)))
        X = np.repeat(X, rng.integers(1, 3, X.size))
        D = np.where(rng.uniform(size=X.size) < 0.3, 0.0, rng.normal(size=X.size))
        for sign, zones in zip((-1.0, 1.0), _zones(X, D)):
            expected = _zones_one_piece_at_a_time(X, D, sign)
            got = [(z.start, z.end, z.area, z.depth) for z in zones]
            assert len(got) == len(expected), trial
            np.testing.assert_allclose(np.reshape(got, (-1, 4)), np.reshape(expected, (-1, 4)), rtol=1e-12, atol=1e-15)


def test_pure_accretion_gives_zero_damage():
    X = np.unique(np.concatenate([np.linspace(-0.5, 0.5, 501), [-0.1, -0.025, 0.025, 0.1]]))
    Z = -_notch(X, 0.0, 0.2, 0.05, 0.03)  # a mound
    dmg = profile_damage(_slope_profile(X, 0 * X), _slope_profile(X, Z), DN50, COT, origin=(0.1, 0.05))
    assert dmg.S == 0 and dmg.A_e == 0 and dmg.erosion == []
    assert len(dmg.accretion) == 1 and abs(dmg.accretion[0].area - 0.125 * 0.03) < 1e-9


def _dense_envelope_damage(initial, final, cot, origin, step=2e-5):
    """Reference for a folded profile: both polylines cut into pieces shorter than a bin, their outer envelope
    taken as the highest piece in each 20-micrometre bin along the slope, the difference summed."""
    envelopes = []
    for x, z in (initial, final):
        t = np.linspace(0.0, 1.0, 4000)[:, None]  # a 1 mm step rising 3 cm spans 15 mm of slope
        xs = (x[:-1] + t * np.diff(x)).ravel()
        zs = (z[:-1] + t * np.diff(z)).ravel()
        X, Z = to_slope_frame(xs, zs, cot, origin)
        envelopes.append((X, Z))
    lo = max(X.min() for X, _ in envelopes)
    hi = min(X.max() for X, _ in envelopes)
    edges = np.arange(lo, hi, step)
    tops = []
    for X, Z in envelopes:
        top = np.full(edges.size, -np.inf)
        k = np.clip(((X - lo) / step).astype(int), 0, edges.size - 1)
        np.maximum.at(top, k, Z)
        tops.append(top)
    D = tops[1] - tops[0]
    return step * np.sum(np.clip(-D, 0.0, None)), float(np.max(-D))


def test_a_face_steeper_than_the_slope_folds_the_profile_and_its_outer_envelope_is_swept():
    # A 1:2 slope with a block on it: its landward face drops vertically, so the profile turns back along
    # the slope there. The final profile has lost the block and 1 cm more over a stretch around it.
    origin = (0.1, 0.05)
    x = np.round(np.arange(0.0, 0.6, 0.001), 6)
    slope = origin[1] + (x - origin[0]) / COT
    block = (x >= 0.25) & (x < 0.30)
    z_initial = slope + 0.03 * block
    lowered = (x >= 0.20) & (x <= 0.36)
    z_final = slope - 0.01 * lowered
    dmg = profile_damage((x, z_initial), (x, z_final), DN50, COT, origin=origin)
    area, depth = _dense_envelope_damage((x, z_initial), (x, z_final), COT, origin)
    big = [zone for zone in dmg.erosion if zone.area > 1e-7]
    assert len(big) == 1  # one hole, not split where the block's face folds the profile
    assert abs(dmg.A_e - area) < 0.002 * area
    assert abs(dmg.d_e - depth) < 1e-5
    # The zone runs along the slope over the whole lowered stretch (x 0.20 to 0.36), the block inside it.
    assert abs(dmg.L_e - (0.36 - 0.20) * np.hypot(COT, 1.0) / COT) < 0.003


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
    # A 1:4 slope has its own thresholds (start 3, intermediate 8-12, failure 17), not 1:3's.
    assert damage_level(7.0, 3.0) == "intermediate damage" and damage_level(7.0, 4.0) == "start of damage"
    assert damage_level(16.0, 4.0) == "advanced damage" and damage_level(17.0, 6.0) == "failure"
    start, (lo, hi), failure = damage_thresholds(2.5)  # between 1:2 and 1:3: linear in the cotangent
    assert (start, lo, hi, failure) == (2.0, 5.0, 7.5, 10.0)
    with pytest.raises(js.JaxStereoError, match="outside"):
        damage_level(3.0, 8.0)


def test_erosion_zones_reaching_into_the_active_zone_count_whole():
    X = np.unique(np.concatenate([np.linspace(-0.6, 0.6, 1201), [-0.266, -0.216, -0.166, -0.1, -0.05, 0.0, 0.35, 0.4,
                                                                   0.45]]))
    origin = (0.1, 0.05)
    swl = origin[1]  # the slope line meets the SWL at the origin: X' = 0
    zone = (slope_abscissa(swl, COT, origin) - 6 * DN50, slope_abscissa(swl, COT, origin) + 4 * DN50)
    # A small hole at the still water level, a larger one 0.4 m up the slope (the crest) and one across the
    # active zone's lower end (X' = -0.216 m), half of it outside the zone.
    Z = _notch(X, -0.05, 0.1, 0.0, 0.02) + _notch(X, 0.4, 0.1, 0.0, 0.05) + _notch(X, zone[0], 0.1, 0.0, 0.03)
    everywhere = profile_damage(_slope_profile(X, 0 * X), _slope_profile(X, Z), DN50, COT, origin)
    assert abs(everywhere.A_e - 0.1 * 0.05 / 2) < 1e-12 and len(everywhere.erosion) == 3  # the crest's, without a zone
    active = profile_damage(_slope_profile(X, 0 * X), _slope_profile(X, Z), DN50, COT, origin, zone)
    # The crest's hole is not counted; the one across the zone's end is, whole (not the half inside the zone).
    assert len(active.erosion) == 2 and all(zn.end < 0.3 for zn in active.erosion)
    assert abs(active.A_e - 0.1 * 0.03 / 2) < 1e-12 and active.d_e == pytest.approx(0.03)
    assert active.erosion[0].start == pytest.approx(zone[0] - 0.05) and active.swept == everywhere.swept


def _dems(rows_with_hole, depth=0.03, cot=COT, spacing=0.004):
    """DEMs of a 1:cot slope through (0, 0); the after one with a square-sided hole 8 cm long, centred on z = 0,
    on the given rows (a boolean per y)."""
    x = np.arange(-0.4, 0.6 + 1e-9, spacing)
    y = np.arange(-0.3, 0.3 + 1e-9, spacing)
    X, Y = np.meshgrid(x, y)
    z = X / cot
    hole = (np.abs(X) <= 0.04 * cot / np.hypot(cot, 1)) & rows_with_hole(Y)
    return DEM(x, y, z, spacing), DEM(x, y, z - depth * hole, spacing)


def test_stretch_is_the_average_of_its_profiles():
    from jaxstereo._surface.damage_report import stretch_damage

    # A hole on |y| < 0.1, and a deeper one for y > 0.2, outside the tested stretch.
    before, after = _dems(lambda Y: (np.abs(Y) < 0.1) | (Y > 0.2))
    result = stretch_damage(before, after, DN50, COT, 0.0, (0.0, 0.0), profile_spacing_m=0.004,
                            stretch=(-0.15, 0.15), foot_radius_m=0.0)
    rows = (before.y >= -0.15) & (before.y <= 0.15)
    by_hand = profile_damage((before.x, before.z[rows].mean(axis=0)), (after.x, after.z[rows].mean(axis=0)),
                             DN50, COT, (0.0, 0.0), result.averaged.swept)
    assert result.averaged.A_e == pytest.approx(by_hand.A_e, rel=1e-12) and by_hand.A_e > 0
    assert result.averaged.d_e == pytest.approx(by_hand.d_e, rel=1e-12)
    inside = [p for y, p in result.profiles]
    assert all(-0.15 <= y <= 0.15 for y, _ in result.profiles) and not result.whole_width
    # Profiles through the hole see its full depth; the stretch's characteristic S is their width average.
    assert max(p.d_e for p in inside) == pytest.approx(0.03 * COT / np.hypot(COT, 1), rel=1e-6)
    assert result.level == damage_level(result.averaged.S, COT)
    whole = stretch_damage(before, after, DN50, COT, 0.0, (0.0, 0.0), foot_radius_m=0.0)
    assert whole.whole_width and any(y > 0.2 and p.A_e > 0 for y, p in whole.profiles)
    assert whole.stretch[0] > before.y[0] and whole.stretch[1] < before.y[-1]  # Dn50 off the model's sides


def test_no_silent_zeros():
    from jaxstereo._surface.damage_report import stretch_damage

    before, after = _dems(lambda Y: np.abs(Y) < 0.1)
    nan_after = DEM(after.x, after.y, np.full_like(after.z, np.nan), after.spacing)
    with pytest.raises(js.JaxStereoError, match="do not overlap"):
        stretch_damage(before, nan_after, DN50, COT, 0.0, (0.0, 0.0))
    with pytest.raises(js.JaxStereoError, match="outside the surveys"):
        stretch_damage(before, after, DN50, COT, 0.0, (0.0, 0.0), stretch=(2.0, 3.0))
    # A narrow strip of data: no Dn50 circle is covered, so E3D is not measurable (None), not 0.
    strip = np.full_like(after.z, np.nan)
    strip[:, :3] = after.z[:, :3]
    assert dem_damage(before, DEM(after.x, after.y, strip, after.spacing), DN50).E3D is None
    # Sections off the design slope are named with their reason, not silently dropped.
    off = before.z.copy()
    off[before.y > 0.25] = -0.2
    result = stretch_damage(DEM(before.x, before.y, off, before.spacing), after, DN50, COT, 0.0, (0.0, 0.0),
                            stretch=(-0.3, 0.3))
    assert any("under the design slope: not a cross-section" in why for _, why in result.skipped)
    assert all(y <= 0.25 for y, _ in result.profiles)


def test_a_section_along_one_rock_is_kept_and_the_underlayer_beside_the_armour_is_not():
    from jaxstereo._surface.damage_report import stretch_damage

    before, _ = _dems(lambda Y: np.zeros_like(Y, bool))
    to_vertical = np.hypot(COT, 1) / COT  # a normal offset of the slope plane, as a height
    z = before.z.copy()
    z[np.abs(before.y) < 0.002] += 1.5 * DN50 * to_vertical  # one 4 mm section along the top of a row of rocks
    z[np.abs(before.y) > 0.2] -= 1.8 * DN50 * to_vertical  # the underlayer, beside the armour (|y| < 0.2 m)
    surface = DEM(before.x, before.y, z, before.spacing)
    result = stretch_damage(surface, surface, DN50, COT, 0.0, (0.0, 0.0), profile_spacing_m=0.004, stretch=(-0.3, 0.3))
    ys = np.array([y for y, _ in result.profiles])
    assert np.any(np.abs(ys) < 0.002)  # the rock's section is one of the armour's
    assert np.all(np.abs(ys) <= 0.2 - DN50 + 1e-9) and ys.min() < -0.15 and ys.max() > 0.15
    assert any("under the design slope" in why for y, why in result.skipped if abs(y) > 0.2)
    assert result.S_max == 0.0


def test_profiler_foot_bridges_crevices_and_keeps_holes():
    from jaxstereo._surface.damage_report import profiler_foot

    spacing = 0.002
    x = np.arange(0, 0.2, spacing)
    X, Y = np.meshgrid(x, x)
    z = np.zeros_like(X)
    z[(np.abs(X - 0.05) < 0.003)] = -0.02  # a crevice 6 mm wide: the 9 mm ball does not reach its bottom
    z[(np.abs(X - 0.15) < 0.03) & (np.abs(Y - 0.1) < 0.03)] = -0.02  # a hole 6 cm across: it does
    z[50, 20] = 0.05  # a single-cell spike
    seen = profiler_foot(DEM(x, x, z, spacing), 0.009).z
    assert seen[:, 25].min() > -0.005  # bridged (the ball sags at most r - sqrt(r^2 - 3^2) mm)
    assert seen[50, 75] == pytest.approx(-0.02)  # the hole's middle
    assert abs(seen[50, 20]) < 1e-12  # the spike removed


@pytest.mark.parametrize(("cell_mm", "rms_mm", "p95_mm"), [(5, 0.9, 2.0), (10, 1.6, 4.0)])
def test_profiler_foot_on_a_coarse_dem_matches_the_ball_on_the_fine_surface(cell_mm, rms_mm, p95_mm):
    # Rubble of ellipsoidal rocks (Dn about 36 mm) on a 1 mm grid, closed there with the 9 mm ball (the reference),
    # and its DEM of cell medians closed by `profiler_foot`: the two agree per cell (the reference's cell medians)
    # to 0.75 mm RMS on 5 mm cells. On the DEM's own cells the ball is three heights (9, 7.5, 5.6 mm) and sinks
    # between them: 1.20 mm RMS, 2.37 mm p95. On 10 mm cells, coarser than the ball's radius, it was not closed at
    # all (3.3 mm RMS off); now 1.3 mm.
    from scipy import ndimage

    from jaxstereo._surface.damage_report import profiler_foot

    rng = np.random.default_rng(3)
    n, k, radius = 300, cell_mm, 0.009
    x = np.arange(n) * 0.001
    X, Y = np.meshgrid(x, x)
    z = np.zeros((n, n))
    for _ in range(120):
        (cx, cy), (a, b), turn = rng.uniform(0, 0.3, 2), rng.uniform(0.012, 0.022, 2), rng.uniform(0, np.pi)
        u = ((X - cx) * np.cos(turn) + (Y - cy) * np.sin(turn)) / a
        v = (-(X - cx) * np.sin(turn) + (Y - cy) * np.cos(turn)) / b
        dome = np.sqrt(np.clip(1 - u**2 - v**2, 0, None))
        z = np.maximum(z, rng.uniform(0.01, 0.025) * dome + rng.uniform(0, 0.01) * (u**2 + v**2 < 1))
    r = 9
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1] * 0.001
    inside = xx**2 + yy**2 <= radius**2
    ball = np.where(inside, np.sqrt(np.clip(radius**2 - xx**2 - yy**2, 0, None)), 0)
    reference = ndimage.grey_closing(z, footprint=inside, structure=ball)

    def cells(a):
        return np.median(a.reshape(n // k, k, n // k, k).transpose(0, 2, 1, 3).reshape(n // k, n // k, -1), axis=-1)

    centres = x.reshape(-1, k).mean(axis=1)
    inner = slice(20 // k, -20 // k)  # away from the borders
    seen = profiler_foot(DEM(centres, centres, cells(z), k / 1000), radius).z[inner, inner]
    error = seen - cells(reference)[inner, inner]
    assert np.sqrt(np.mean(error**2)) < rms_mm / 1000
    assert np.percentile(np.abs(error), 95) < p95_mm / 1000


def test_a_face_edge_one_survey_places_lower_reads_as_that_cells_change_not_the_faces_height():
    # A block on a 1:2 slope whose landward face drops 40 mm between two 5 mm cells (steeper than 2:1, so the
    # profile folds back along the slope and its envelope jumps at the block's edge). The second survey reads
    # the edge cell `delta` lower. Its envelope's edge moves 0.45 * delta along the slope, and between the two
    # edges one envelope is on the block's top and the other at its foot: unpaired, that sliver reads as deep as
    # the face is high. Paired, the change is the edge cell's own: delta * cos(slope) normal to the slope, over
    # the one segment of the block's top that ends there (the face itself lies under the envelope).
    origin = (0.1, 0.05)
    x = np.round(np.arange(0.0, 0.6, 0.005), 6)
    block = (x >= 0.25) & (x < 0.30)
    initial = origin[1] + (x - origin[0]) / COT + 0.04 * block
    cos_slope = COT / np.hypot(COT, 1.0)
    for delta in (0.001, 0.004, 0.008):
        final = initial.copy()
        final[np.flatnonzero(block)[-1]] -= delta
        paired = profile_damage((x, initial), (x, final), DN50, COT, origin=origin)
        assert len(paired.erosion) == 1
        assert paired.d_e == pytest.approx(delta * cos_slope, abs=1e-12)
        assert paired.A_e == pytest.approx(delta * 0.005 / 2, rel=1e-9)
        assert paired.L_e == pytest.approx(0.005 / cos_slope, rel=1e-9)  # the top's last segment along the slope
        unpaired = profile_damage((x, initial), (x, final), DN50, COT, origin=origin, edge_tolerance_m=0.0)
        assert unpaired.d_e == pytest.approx(0.04 * cos_slope, rel=1e-9)  # the face's height: the sliver


def test_a_face_edge_moved_further_than_a_sample_is_measured_whole():
    # The same block, its last 15 mm of top gone in the second survey: the edges lie three samples apart, are
    # not one edge, and the eroded corner is measured in full (40 mm deep normal to the slope at the old edge).
    origin = (0.1, 0.05)
    x = np.round(np.arange(0.0, 0.6, 0.005), 6)
    slope = origin[1] + (x - origin[0]) / COT
    initial = slope + 0.04 * ((x >= 0.25) & (x < 0.30))
    final = slope + 0.04 * ((x >= 0.25) & (x < 0.285))
    cos_slope = COT / np.hypot(COT, 1.0)
    for tolerance in (None, 0.0):
        dmg = profile_damage((x, initial), (x, final), DN50, COT, origin=origin, edge_tolerance_m=tolerance)
        assert dmg.d_e == pytest.approx(0.04 * cos_slope, rel=1e-9)


def test_a_face_short_of_the_slopes_normal_in_one_survey_and_overhanging_in_the_other_leaves_no_sliver():
    # A rock on a 1:2 slope whose landward face falls in two steps, each within a few degrees of the slope's normal
    # (it advances 0.13 and 0.45 mm along the slope while falling 9-10 mm). The second survey reads the rock
    # `delta` lower, which tips the first step past the normal: its envelope jumps there and the first survey's
    # does not. Until round 67 only jumps were edges, and the sliver between the two surveys' faces read as deep
    # as the step (7.5-15 mm); the change is delta normal to the slope, a few times that on the faces' ends.
    origin = (0.0, 0.0)
    x = np.round(np.arange(0.0, 0.3, 0.005), 6)
    initial = x / COT
    initial[30:37] += [0.020, 0.024, 0.0245, 0.0195, 0.0073, 0.0045, -0.0040]
    cos_slope = COT / np.hypot(COT, 1.0)
    for delta in (0.0005, 0.001, 0.002, 0.003):
        final = initial.copy()
        final[30:37] -= delta
        unpaired = profile_damage((x, initial), (x, final), DN50, COT, origin=origin, edge_tolerance_m=0.0)
        assert unpaired.d_e > 0.011  # the sliver
        paired = profile_damage((x, initial), (x, final), DN50, COT, origin=origin)
        assert delta * cos_slope < paired.d_e < 3.5 * delta * cos_slope


def test_a_face_stepping_down_twice_within_a_sample_in_both_surveys_leaves_no_sliver():
    # A rock's landward face folds back along the slope twice (two jumps in each envelope, their tops 0.1 mm apart
    # along it). The second survey reads the upper step `upper` lower and the lower step `lower` lower, which puts
    # its two edges 0.45 * (upper - lower) - 0.1 mm apart the other way round: each of its edges lies nearest the
    # same edge of the first survey. Until round 67 the second pair, overlapping the first, was left out, and the
    # first survey's other edge bounded a sliver as deep as the step (22.6-23.8 mm); the change lies between the
    # cells' own changes normal to the slope.
    origin = (0.0, 0.0)
    x = np.round(np.arange(0.0, 0.3, 0.005), 6)
    initial = x / COT
    initial[30:38] += [0.020, 0.024, 0.0245, 0.00685, -0.00073, -0.01726, -0.0100, -0.005]
    X, _ = to_slope_frame(x, initial, COT, origin)
    assert np.allclose(np.diff(X[32:37]), [-0.0023, 0.0022, -0.0018, 0.00884], atol=5e-5)  # fold, advance, fold
    cos_slope = COT / np.hypot(COT, 1.0)
    for upper, lower in ((0.0018, 0.001), (0.0015, 0.0005), (0.001, 0.0), (0.002, 0.0015)):
        final = initial.copy()
        final[30:34] -= upper
        final[34:38] -= lower
        unpaired = profile_damage((x, initial), (x, final), DN50, COT, origin=origin, edge_tolerance_m=0.0)
        assert unpaired.d_e > 0.035  # the sliver
        paired = profile_damage((x, initial), (x, final), DN50, COT, origin=origin)
        assert lower * cos_slope <= paired.d_e <= upper * cos_slope


def test_overhanging_faces_sampled_apart_add_no_false_erosion():
    # Rubble seen twice: the same blocks (faces 14 to 50 mm high), each with a vertical landward face (which
    # folds the profile back along the slope), in two surveys whose 5 mm cells fall 2 mm apart. The outer
    # envelopes jump at the faces' edges in slightly different places. The area between them is a few small
    # slivers, not a trapezoid bridged from each jump to the next vertex (which gave a per-profile S of 1.56 on
    # a true rubble surface against itself with 1 mm of noise, and 0.84 on the POV-Ray flume's undamaged
    # model); and each pair of edges is one edge, so no sliver reads as deep as its face.
    origin = (0.1, 0.05)
    rng = np.random.default_rng(3)
    heights = rng.uniform(0.01, 0.06, 12)

    def surface(x):
        slope = origin[1] + (x - origin[0]) / COT
        block = np.floor((x - 0.1) / 0.04).astype(int)
        inside = (block >= 0) & (block < heights.size) & ((x - 0.1) % 0.04 < 0.03)
        return slope + np.where(inside, heights[np.clip(block, 0, heights.size - 1)], 0.0)

    x_initial = np.arange(0.0, 0.7, 0.005)
    x_final = x_initial + 0.002
    initial, final = (x_initial, surface(x_initial)), (x_final, surface(x_final))
    unpaired = profile_damage(initial, final, DN50, COT, origin=origin, edge_tolerance_m=0.0)
    area, _ = _dense_envelope_damage(initial, final, COT, origin)
    eroded = sum(zone.area for zone in unpaired.erosion)
    assert abs(eroded - area) < 0.01 * area + 1e-7
    assert unpaired.S < 0.1  # the largest sliver
    assert max(zone.depth for zone in unpaired.erosion) > 0.014  # a sliver as deep as the lowest face
    paired = profile_damage(initial, final, DN50, COT, origin=origin)
    assert sum(zone.area for zone in paired.erosion) < 0.6 * eroded
    assert paired.S < 0.1
    # What is left is the faces' sampled segments, 2 mm apart: 3.3 mm at most, against faces 14-50 mm high.
    assert max(zone.depth for zone in paired.erosion) < 0.004


def test_despike_replaces_cells_beyond_all_eight_neighbours_as_a_stack_of_shifts_finds_them():
    from jaxstereo._surface.damage_report import despike

    rng = np.random.default_rng(8)
    z = np.cumsum(rng.normal(0.0, 0.002, (40, 50)), axis=1)
    spikes = rng.uniform(size=z.shape) < 0.05
    z[spikes] += rng.choice([-0.05, 0.05], size=spikes.sum())
    z[rng.uniform(size=z.shape) < 0.15] = np.nan
    shifts = np.stack([np.pad(z, 1, constant_values=np.nan)[i : i + 40, j : j + 50]
                       for i in range(3) for j in range(3) if (i, j) != (1, 1)])
    finite = np.isfinite(shifts)
    high, low = np.where(finite, shifts, -np.inf).max(axis=0), np.where(finite, shifts, np.inf).min(axis=0)
    enough = finite.sum(axis=0) >= 5
    with np.errstate(invalid="ignore"):
        peak, pit = enough & (z - high > 0.01), enough & (low - z > 0.01)
    assert peak.sum() > 5 and pit.sum() > 5
    got = despike(DEM(np.arange(50.0), np.arange(40.0), z, 1.0), 0.01).z
    np.testing.assert_array_equal(got, np.where(peak, high, np.where(pit, low, z)))


def test_a_slope_rising_toward_minus_x_is_found_and_measured_as_its_mirror_image():
    """The world frame may run down the slope (a rig turned 180 degrees sees the origin board the other way
    round): the initial DEM says which way the slope rises, and the damage is that of the mirrored DEMs, with the
    E3D place given back in the DEMs' own frame. The design line fitted to a profile finds its direction too."""
    from jaxstereo._surface.damage_report import fit_design_slope, stretch_damage
    from jaxstereo._surface.slope_direction import mirrored_in_x, slope_direction

    before, after = _dems(lambda Y: np.abs(Y) < 0.1)
    toe = (-0.3, -0.3 / COT)  # a point of the line z = x / cot
    mirrored = [mirrored_in_x(d) for d in (before, after)]
    assert np.array_equal(mirrored[0].x, -before.x[::-1]) and np.array_equal(mirrored[1].z, after.z[:, ::-1])
    assert slope_direction(before, COT, 0.0, toe, DN50) == "+x"
    assert slope_direction(mirrored[0], COT, 0.0, (0.3, toe[1]), DN50) == "-x"
    assert slope_direction(before, COT, 0.0, (5.0, 0.0), DN50) == "+x"  # no line meets the DEM: the default
    reference = stretch_damage(before, after, DN50, COT, 0.0, toe, foot_radius_m=0.0)
    result = stretch_damage(*mirrored, DN50, COT, 0.0, (0.3, toe[1]), foot_radius_m=0.0)
    assert reference.rises_toward == "+x" and result.rises_toward == "-x"
    assert result.to_dict()["slope_rises_toward"] == "-x" and result.origin == (0.3, toe[1])
    assert [p.A_e for _, p in result.profiles] == pytest.approx([p.A_e for _, p in reference.profiles], rel=1e-9)
    assert [p.d_e for _, p in result.profiles] == pytest.approx([p.d_e for _, p in reference.profiles], rel=1e-9)
    assert result.averaged.S == pytest.approx(reference.averaged.S, rel=1e-9) and reference.d_e_max > 0.02
    assert result.volumes.E3D_xy == pytest.approx((-reference.volumes.E3D_xy[0], reference.volumes.E3D_xy[1]))
    # Told the wrong way, the slope is not found: said, not measured.
    with pytest.raises(js.JaxStereoError, match="design slope"):
        stretch_damage(*mirrored, DN50, COT, 0.0, (0.3, toe[1]), foot_radius_m=0.0, rises_toward="+x")
    with pytest.raises(js.JaxStereoError, match="rises_toward"):
        stretch_damage(before, after, DN50, COT, 0.0, toe, rises_toward="up")
    for dem, x0 in ((before, 0.0), (mirrored[0], 0.0)):
        (x_fit, _), rms = fit_design_slope(dem.x, dem.z[0], COT, 0.0, DN50)
        assert x_fit == pytest.approx(x0, abs=1e-9) and rms < 1e-9


def test_a_design_line_that_runs_off_the_survey_at_once_does_not_win_on_its_first_centimetres():
    """A survey that reaches only 6 cm in front of the toe, where a row of toe rocks stands Dn50 high, and an armour
    whose surface lies 2.5 cm above the design line through the toe (on the POV-Ray flume's rig J, water 7 cm deep,
    the slope's direction was read the wrong way so, and the central profile's d_e came out 10.7 mm short). Drawn
    toward -x the line leaves the DEM after its first 7 of 33 heights, and over those it passes within 1-3 cm of
    the toe rocks, nearer than the armour is to the line drawn up the slope: judged by those heights alone it wins.
    A height at which a line has left the survey, or crosses an empty cell, counts against it."""
    from jaxstereo._surface.slope_direction import slope_direction

    spacing = 0.005
    x = np.round(np.arange(-0.06, 0.6, spacing), 6)
    y = np.round(np.arange(-0.2, 0.2, spacing), 6)
    X, Y = np.meshgrid(x, y)
    rng = np.random.default_rng(3)
    z = np.where(X < 0.0, DN50, X / COT + 0.025) + rng.normal(0.0, 0.003, X.shape)
    dem = DEM(x, y, z, spacing)
    swl = 2 * DN50
    assert slope_direction(dem, COT, swl, (0.0, 0.0), DN50) == "+x"
    mirrored = DEM(-x[::-1], y, z[:, ::-1], spacing)
    assert slope_direction(mirrored, COT, swl, (0.0, 0.0), DN50) == "-x"
    # The same on a grid that runs on past the survey, its cells there empty (a DEM's box is wider than its data).
    x_box = np.round(np.arange(-0.4, 0.6, spacing), 6)
    z_box = np.full((y.size, x_box.size), np.nan)
    z_box[:, x_box >= -0.06 - 1e-9] = z
    assert slope_direction(DEM(x_box, y, z_box, spacing), COT, swl, (0.0, 0.0), DN50) == "+x"
    # Where the survey runs on in front of the toe (floor at z = 0 beyond the toe rocks), the same holds.
    x_long = np.round(np.arange(-0.4, 0.6, spacing), 6)
    X, Y = np.meshgrid(x_long, y)
    z_long = np.where(X < -0.1, 0.0, np.where(X < 0.0, DN50, X / COT + 0.025))
    assert slope_direction(DEM(x_long, y, z_long, spacing), COT, swl, (0.0, 0.0), DN50) == "+x"


def test_a_cell_only_one_survey_saw_is_not_compared_with_the_other_bridged_across_it():
    """An unchanged rubble slope surveyed twice: the first survey missed the floor cell at the foot of each block's
    seaward face (a crevice it did not see), the second saw it. Compared as they were, the first survey's profile
    bridges the missing cell from the crevice's floor up to the block's top, the second drops to the floor, and
    the difference reads as erosion (on the POV-Ray flume seen by its rig turned 180 degrees, such a cell gave
    the undamaged model a profile S of 0.31). The damage compares the cells both surveys have: none here."""
    from jaxstereo._surface.damage_report import stretch_damage

    spacing = 0.005
    x = np.round(np.arange(-0.3, 0.5, spacing), 6)
    y = np.round(np.arange(-0.2, 0.2, spacing), 6)
    X, _ = np.meshgrid(x, y)
    heights = np.random.default_rng(5).uniform(0.02, 0.06, 40)
    block = np.floor((X + 0.3) / 0.04).astype(int)
    on_block = (X + 0.3) % 0.04 < 0.03 - 1e-9
    z = X / COT + np.where(on_block, heights[block], 0.0)
    foot = ~on_block & np.roll(on_block, -1, axis=1)  # the last floor cell before each block
    seen_once = DEM(x, y, np.where(foot, np.nan, z), spacing)
    seen_twice = DEM(x, y, z, spacing)
    result = stretch_damage(seen_once, seen_twice, DN50, COT, 0.0, (0.0, 0.0), profile_spacing_m=spacing)
    assert len(result.profiles) > 50 and result.S_max == 0.0 and result.averaged.S == 0.0
    assert result.volumes.eroded_m3 == 0.0 and result.volumes.accreted_m3 == 0.0
    # Each profile alone, its missing cells bridged, reads the crevices as erosion.
    row = int(np.argmin(np.abs(y)))
    alone = profile_damage((x, seen_once.z[row]), (x, z[row]), DN50, COT, (0.0, 0.0))
    assert alone.S > 0.1 and alone.d_e > 0.005
