"""Damage of synthetic breakwater stages: reconstructed surveys against the exact heightfields."""

import numpy as np
import pytest

import jaxstereo as js
from jaxstereo._calibration.rig import Rig
from jaxstereo._stereo.reconstruct import ReconstructOptions, reconstruct
from jaxstereo._surface.damage_report import stretch_damage
from jaxstereo._surface.grid import DEM, fill_holes, grid_median
from jaxstereo._synthetic.flume_rig import RigSpec, flume_rig
from jaxstereo._synthetic.render import render_view
from jaxstereo._synthetic.scenes import Breakwater, Damage, build_scene

SWL = 0.158
BAND = 0.09  # the damaged band: |y| < 9 cm (the hole is 3 Dn50 = 10.8 cm wide each side of y = 0)


def _band(dem: DEM) -> DEM:
    rows = np.abs(dem.y) <= BAND
    return DEM(dem.x, dem.y[rows], dem.z[rows], dem.spacing)


def _truth_dem(scene, spacing, x, y):
    hf = scene.heightfield
    X, Y = np.meshgrid(hf.x, hf.y)
    nodes = np.stack([X.ravel(), Y.ravel(), np.asarray(hf.z).ravel()], axis=-1)
    return grid_median(nodes, spacing, x, y)


@pytest.fixture(scope="module")
def stages():
    left, right = flume_rig(RigSpec(image_size=(1728, 1152), water_level_m=SWL))
    rig = Rig(left, right)
    water = js.Interface(SWL)
    damages = [None, Damage(half_length_dn50=2.0, half_width_dn50=3.0, deep_fraction=0.0, swl_m=SWL),
               Damage(half_length_dn50=3.0, half_width_dn50=3.0, deep_fraction=0.6, swl_m=SWL)]
    out = []
    for damage in damages:
        spec = Breakwater(seed=7, damage=damage)
        scene = build_scene(spec)
        views = [render_view(c, scene.heightfield, water) for c in (left, right)]
        survey, _ = reconstruct(views[0].image, views[1].image, rig, SWL, ReconstructOptions(z_range_m=(-0.05, 0.45)))
        out.append((spec, scene, survey))
    return out


def _damage(before, after, spec):
    return stretch_damage(_band(before), _band(after), spec.dn50_m, spec.slope, SWL, origin=(spec.toe_x_m, 0.0))


def test_reconstructed_damage_matches_ground_truth_and_grows_with_stage(stages, capsys):
    spacing = 0.005
    spec0, scene0, survey0 = stages[0]
    base = fill_holes(grid_median(survey0.points, spacing), 0.01)
    truth0 = _truth_dem(scene0, spacing, base.x, base.y)
    rows = []
    for spec, scene, survey in stages[1:]:
        measured = _damage(base, fill_holes(grid_median(survey.points, spacing, base.x, base.y), 0.01), spec)
        truth = _damage(truth0, _truth_dem(scene, spacing, base.x, base.y), spec)
        rows.append((truth.averaged, measured.averaged))
    with capsys.disabled():
        print("\nbreakwater stages (wet surveys, 1728x1152, water 0.158 m), damaged band |y| < 9 cm, averaged profile")
        print("| stage | A_e truth (m2) | A_e survey (m2) | S truth | S survey | d_e truth (m) | d_e survey (m) |")
        print("|---|---:|---:|---:|---:|---:|---:|")
        for k, (t, m) in enumerate(rows, start=2):
            print(f"| {'I' * k} | {t.A_e:.5f} | {m.A_e:.5f} | {t.S:.2f} | {m.S:.2f} | {t.d_e:.4f} | {m.d_e:.4f} |")
    for truth, measured in rows:
        assert truth.A_e > 0
        assert abs(measured.A_e - truth.A_e) <= 0.10 * truth.A_e
    assert rows[1][1].S > rows[0][1].S > 0


def test_damage_does_not_depend_on_grid_spacing(stages):
    spec0, _, survey0 = stages[0]
    spec, _, survey = stages[2]
    values = []
    for spacing in (0.002, 0.005, 0.010):
        base = fill_holes(grid_median(survey0.points, spacing), 2 * spacing)
        after = fill_holes(grid_median(survey.points, spacing, base.x, base.y), 2 * spacing)
        values.append(_damage(base, after, spec).averaged.A_e)
    values = np.array(values)
    assert np.ptp(values) <= 0.05 * values.mean(), values
