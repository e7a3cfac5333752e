"""Error bars of the damage figures: the sampled noise's own statistics, shared errors that cancel between two
surveys of one rig, a clear refusal without sigma layers, and the DEM's sigma layers from a survey."""

import dataclasses
import json

import numpy as np
import pytest

from jaxstereo import DEM, JaxStereoError, Survey, grid_survey, stretch_damage
from jaxstereo._surface.damage_uncertainty import correlated_noise, damage_sigma, hollow_depth

DN50, COT, SWL, ORIGIN = 0.036, 2.0, 0.16, (0.0, 0.0)


def test_correlated_noise_has_unit_variance_and_the_box_correlation():
    rng = np.random.default_rng(0)
    field = correlated_noise((400, 400), 6, rng)
    assert np.std(field) == pytest.approx(1.0, abs=0.05)
    lag = [np.corrcoef(field[:, :-k].ravel(), field[:, k:].ravel())[0, 1] for k in (3, 6)]
    assert lag[0] == pytest.approx(0.5, abs=0.08)  # a box of 6: triangle correlation 1 - k / 6
    assert abs(lag[1]) < 0.08


def _slope(bump_m=0.0, **layers):
    x = np.arange(0.0, 0.8, 0.005)
    y = np.arange(-0.1, 0.1, 0.005)
    z = np.broadcast_to(x / COT, (y.size, x.size)).copy()
    hole = (np.abs(x - 0.32) < 0.06)[None, :] & (np.abs(y) < 0.06)[:, None]
    z[hole] -= bump_m
    full = {key: np.full(z.shape, value) for key, value in layers.items()}
    return DEM(x, y, z, 0.005, **full, correlation_m=0.02)


def _compute(before, after):
    return stretch_damage(before, after, DN50, COT, SWL, ORIGIN, foot_radius_m=0.0)


def test_a_shared_calibration_cancels_and_an_independent_one_does_not():
    """The same draws (one seed) with and without a 2 mm calibration error: shared by both surveys it changes no
    figure; independent it moves A_e."""
    layers = {"sigma_match": 0.0, "sigma_calibration": 0.002, "sigma_level": 0.0}
    none = {**layers, "sigma_calibration": 0.0}
    without = damage_sigma(_slope(**none), _slope(0.03, **none), _compute, True, False, draws=16)
    shared = damage_sigma(_slope(**layers), _slope(0.03, **layers), _compute, True, False, draws=16)
    independent = damage_sigma(_slope(**layers), _slope(0.03, **layers), _compute, False, False, draws=16)
    assert shared.sigma["S"] == pytest.approx(without.sigma["S"], abs=1e-9)  # the same offset in both surveys
    assert independent.sigma["S"] > without.sigma["S"] + 0.05  # a 2 mm offset of one survey against the other


def test_a_hollow_narrower_than_the_window_footprint_counts_as_possibly_read_high():
    """The hollow term: zero on a plane, the hollow's depth below the footprint's mean at its corners, zero on the
    crest's side (a window reads hollows high, not crests low); it alone gives the S of a hole a sigma."""
    plane, hole = _slope(sigma_match=0.0), _slope(0.03, sigma_match=0.0)
    assert np.abs(hollow_depth(plane)).max() < 1e-12
    depth = hollow_depth(hole)
    assert depth.min() >= 0.0 and depth.max() == pytest.approx(0.03 * 16 / 25, rel=1e-6)  # a 5x5 box at a corner
    crest = _slope(-0.03, sigma_match=0.0)  # the same box raised
    top = crest.z > crest.x[None, :] / COT + 0.01
    assert hollow_depth(crest)[top].max() == 0.0 and hollow_depth(crest)[~top].max() > 0.01  # its foot is a hollow
    zero = {"sigma_match": 0.0, "sigma_calibration": 0.0, "sigma_level": 0.0}
    assert damage_sigma(_slope(**zero), _slope(0.03, **zero), _compute, True, True, draws=16).sigma["S"] > 0.02
    assert damage_sigma(_slope(**zero), _slope(**zero), _compute, True, True, draws=16).sigma["S"] < 1e-9


def _basin(depth_m=0.0, **layers):
    """The slope of `_slope` with a smooth basin (a cosine arch, 0.16 m long) in place of the sharp hole, and no
    matching footprint: every cell's matching error independent, no hollow term."""
    x = np.arange(0.0, 0.8, 0.005)
    y = np.arange(-0.1, 0.1, 0.005)
    arch = np.clip(np.cos(np.pi * (x - 0.32) / 0.16), 0.0, None) * (np.abs(x - 0.32) < 0.08)
    z = x / COT - depth_m * arch[None, :] * (np.abs(y) < 0.06)[:, None]
    return DEM(x, y, z, 0.005, **{key: np.full(z.shape, value) for key, value in layers.items()})


def test_matching_noise_gives_a_sigma_that_grows_with_it():
    """On a smooth basin, where no zone's end jumps, S's error bar is proportional to the matching noise."""
    sigmas, profile_sigmas = [], []
    for noise in (0.0005, 0.002):
        layers = {"sigma_match": noise, "sigma_calibration": 0.0, "sigma_level": 0.0}
        result = damage_sigma(_basin(**layers), _basin(0.03, **layers), _compute, False, False, draws=24)
        sigmas.append(result.sigma["S"])
        assert set(result.profile_S) and all(v >= 0 for v in result.profile_S.values())
        inside = [figures for y, figures in result.profile_sigma.items() if abs(y) < 0.04]  # through the basin
        assert len(inside) >= 2 and all(set(f) == {"A_e_m2", "L_e_m", "d_e_m", "S", "E2D"} for f in inside)
        profile_sigmas.append(np.median([[f["A_e_m2"], f["d_e_m"]] for f in inside], axis=0))
    assert 0 < sigmas[0] and 3.0 < sigmas[1] / sigmas[0] < 5.0  # four times the noise
    # One profile's A_e and d_e follow the noise too (measured: 4.0 and 3.5 times; the deepest point is the largest
    # of several cells' draws, which does not scale exactly), and a profile's depth carries its own cells' noise,
    # not the stretch's average (0.35 mm for 0.5 mm per cell; the averaged profile's d_e: 0.09 mm).
    ratio = profile_sigmas[1] / profile_sigmas[0]
    assert 3.0 < ratio[0] < 5.0 and 3.0 < ratio[1] < 5.0, ratio
    assert profile_sigmas[0][1] > 0.0005 / 2


def _two_pits(band_m=None, noise=0.001):
    """The slope of `_slope` with two 20 mm pits (x 0.22-0.28 and 0.30-0.40 m) and, between them, a 20 mm band read
    `band_m` low (an unmoved rock the two surveys read differently); independent matching noise `noise` per cell."""
    x = np.arange(0.0, 0.8, 0.005)
    y = np.arange(-0.1, 0.1, 0.005)
    drop = np.zeros_like(x) if band_m is None else (0.02 * ((x > 0.22) & (x < 0.28)) + 0.02 * ((x > 0.30) & (x < 0.40))
                                                    + band_m * ((x >= 0.28) & (x <= 0.30)))
    z = x / COT - drop[None, :] * (np.abs(y) < 0.06)[:, None]
    layers = {"sigma_match": noise, "sigma_calibration": 0.0, "sigma_level": 0.0}
    return DEM(x, y, z, 0.005, **{key: np.full(z.shape, value) for key, value in layers.items()})


def test_a_zone_the_errors_may_split_gets_an_interval_that_holds_the_split_reading():
    """Two pits joined by a band read 3 mm low: the measured zone runs over both (0.18 m of x, 0.201 m along the
    slope), but 1 mm of noise per cell lifts the band to zero in some draws (6 of 48), which then read the larger
    pit alone (0.112 m). The standard deviation, shrunk by the draws that do not split, leaves that reading out
    at 2 sigma; the 95 % interval, the wider of +- 2 sigma and the middle 95 % of the draws, holds it. With the band
    read 6 mm low no draw splits, and the interval does not reach the split reading."""
    along = np.hypot(COT, 1.0) / COT  # metres along the slope per metre of x
    merged, split = 0.18 * along, 0.10 * along
    for band, splits in ((0.003, True), (0.006, False)):
        before, after = _two_pits(), _two_pits(band)
        y, p = min(_compute(before, after).profiles, key=lambda t: abs(t[0]))
        assert p.L_e == pytest.approx(merged, abs=0.006)  # the measured zone runs over both pits
        result = damage_sigma(before, after, _compute, True, True)
        low, high = result.interval("L_e_m", p.L_e, y)
        sigma = result.profile_sigma[round(y, 6)]["L_e_m"]
        assert low <= p.L_e - 2 * sigma and high >= p.L_e + 2 * sigma and low >= 0
        if splits:
            assert p.L_e - 2 * sigma > split + 0.02  # measured 0.141 against 0.112
            assert low <= split + 0.005  # measured 0.113
        else:
            assert low > split + 0.05  # measured 0.183
    assert result.interval("L_e_m", None, y) is None and result.interval("L_e_m", p.L_e, 1.0) is None


def test_a_zone_the_data_cannot_tell_from_noise_has_length_and_depth_intervals_down_to_zero():
    """Two surveys of one slope, the second read with 1 mm of noise per cell: every zone the sweep finds is the
    noise's (true A_e, L_e and d_e all 0). The length's and depth's intervals reach zero wherever the size's does
    (each profile's A_e; the stretch's largest S for its largest L_e and d_e). The draws alone keep them off zero,
    as every draw's noise makes some zone. Through a 30 mm hole the size's interval is clear of zero and the
    length's is the draws' own."""
    from jaxstereo._surface.damage_uncertainty import stretch_damage_with_sigma

    layers = {"sigma_match": 0.001, "sigma_calibration": 0.0, "sigma_level": 0.0}
    before = _slope(**layers)
    rng = np.random.default_rng(5)
    noisy = dataclasses.replace(before, z=before.z + rng.normal(0.0, 0.001, before.z.shape))
    result, sigma = stretch_damage_with_sigma(before, noisy, DN50, COT, SWL, ORIGIN, draws=16, foot_radius_m=0.0)
    draws_only = dataclasses.replace(sigma, values={}, profile_values={})
    assert result.L_e_max > 0.02 and sigma.interval("S_max", result.S_max)[0] == 0.0
    assert draws_only.interval("L_e_max_m", result.L_e_max)[0] > 0.0
    assert sigma.interval("L_e_max_m", result.L_e_max)[0] == 0.0
    assert sigma.interval("d_e_max_m", result.d_e_max)[0] == 0.0
    noise_only = [(y, p) for y, p in result.profiles if sigma.interval("A_e_m2", p.A_e, y)[0] == 0.0]
    assert len(noise_only) >= 0.9 * len(result.profiles)
    for y, p in noise_only:
        assert sigma.interval("L_e_m", p.L_e, y)[0] == 0.0 and sigma.interval("d_e_m", p.d_e, y)[0] == 0.0
    assert any(draws_only.interval("L_e_m", p.L_e, y)[0] > 0.0 for y, p in noise_only)

    result, sigma = stretch_damage_with_sigma(before, _slope(0.03, **layers), DN50, COT, SWL, ORIGIN, draws=16,
                                              foot_radius_m=0.0)
    y, p = min(result.profiles, key=lambda t: abs(t[0]))
    assert sigma.interval("A_e_m2", p.A_e, y)[0] > 0.5 * p.A_e
    draws_only = dataclasses.replace(sigma, values={}, profile_values={})
    assert sigma.interval("L_e_m", p.L_e, y) == draws_only.interval("L_e_m", p.L_e, y)
    assert sigma.interval("L_e_m", p.L_e, y)[0] > 0.5 * p.L_e


def test_surfaces_without_sigma_layers_are_refused_with_a_clear_error():
    with pytest.raises(JaxStereoError, match="no sigma layers"):
        damage_sigma(_slope(), _slope(0.03), _compute, True, True)


def test_grid_survey_keeps_the_sources_apart():
    """Two points per cell: the shared parts are cell means, the matching part averages only over independent
    matches (here none: two neighbouring pixels share their window)."""
    rng = np.random.default_rng(1)
    n = 400
    points = np.column_stack([rng.uniform(0, 0.1, n), rng.uniform(0, 0.1, n), np.zeros(n)])
    cov = np.zeros((n, 6), np.float32)
    cov[:, 2] = 0.002**2 + 0.001**2 + 0.0005**2
    rig = {"left": {"R": np.eye(3).tolist(), "t": [0.0, 0.0, -2.0], "fx": 2000.0}, "right": {}}
    survey = Survey(points, np.zeros((n, 3), np.uint8), np.zeros((n, 2)), np.zeros(n, bool), json.dumps(rig),
                    "exact", 0.16, cov, np.full(n, 0.002, np.float32), np.full(n, 0.0005, np.float32),
                    np.zeros(n, np.float32))
    dem = grid_survey(survey, 0.02)
    ok = np.isfinite(dem.z)
    np.testing.assert_allclose(dem.sigma_match[ok], 0.002, rtol=1e-6)
    np.testing.assert_allclose(dem.sigma_level[ok], 0.0005, rtol=1e-6)
    np.testing.assert_allclose(dem.sigma_calibration[ok], 0.001, rtol=1e-4)
    assert dem.correlation_m == pytest.approx(47 * 2.0 / 2000.0, rel=1e-3)  # the large sub-pixel patch at 2 m
    assert dataclasses.replace(dem).has_sigma


def test_the_errors_correlation_width_is_the_large_sub_pixel_patch():
    """The grid's and the damage's correlation width (`MATCH_CORRELATION_PX`) is the large sub-pixel patch: on the
    POV-Ray flume's board the height errors' correlation falls to zero at the patch's width (32 px with 31, about
    45 px with 47). In round 53 the patch grew to 47 px while the width stayed 31 px, and two profiles' A_e intervals
    at the development flume's stage II missed the truth."""
    from jaxstereo import ReconstructOptions
    from jaxstereo._stereo.uncertainty import MATCH_CORRELATION_PX

    assert MATCH_CORRELATION_PX == ReconstructOptions().subpixel_window


def test_true_S_lies_within_two_sigma_on_a_synthetic_trial():
    """One of the uncertainty experiment's trials (864x576, a realistic rig with calibration errors drawn from the
    covariance it records, water levels known to 0.5 mm, JPEG): the true S of stages I (a repeat survey), II and
    III within 2 sigma of the measured S. The coverage over many trials is the experiment's to measure (20 trials,
    `python -m experiments uncertainty`); one trial here keeps the suite within its time (a second cost 35 s)."""
    import sys
    from pathlib import Path

    import jax

    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
    from experiments.uncertainty import trial

    with jax.enable_x64(True):
        rows = trial(0, log=lambda _: None)
    for r in rows:
        assert abs(r["S"] - r["S_true"]) <= 2 * r["sigma"], r  # |S - S_true| / sigma measured 0.0-1.9 (seeds 0-9)
        assert r["sigma"] > 0
    assert [r["stage"] for r in rows[:3]] == ["I", "II", "III"] and rows[0]["S"] < rows[1]["S"] < rows[2]["S"]


def test_surveys_share_the_rig_and_the_level_they_were_made_with():
    from jaxstereo._surface.damage_uncertainty import shares_errors

    a = dataclasses.replace(_slope(), calibration_id="abc", water_level=0.158)
    assert shares_errors(a, dataclasses.replace(a)) == (True, True)
    assert shares_errors(a, dataclasses.replace(a, water_level=0.16)) == (True, False)
    assert shares_errors(a, dataclasses.replace(a, calibration_id="xyz", water_level=float("nan"))) == (False, False)
