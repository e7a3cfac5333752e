"""Dense reconstruction against the synthetic flume's exact ground truth."""

import dataclasses

import numpy as np
import pytest

import jaxstereo as js
from jaxstereo._calibration.rig import Rig
from jaxstereo._geometry.pose import Pose
from jaxstereo._stereo.evaluation import layer_errors, layer_table_markdown
from jaxstereo._stereo.reconstruct import ReconstructOptions, reconstruct
from jaxstereo._surface.grid import grid_median
from jaxstereo._synthetic.flume_rig import flume_rig, jpeg, realistic_rig_spec
from jaxstereo._synthetic.render import render_view
from jaxstereo._synthetic.scenes import Breakwater, SlopingBoard, build_scene

# The paper's rig as mounted: cameras tilted and turned by fractions of a degree, a 35 mm lens's distortion,
# images saved as JPEG (quality 95). A parallel, distortion-free rig would hide whole code paths.
PAPER = dict(image_size=(1728, 1152), water_level_m=0.18, camera_height_m=2.0, baseline_m=0.16, focal_mm=35.0)


def _board_pair(tilt_deg=0.0):
    spec = SlopingBoard()
    scene = build_scene(spec)
    offset = -2.18 * np.tan(np.deg2rad(tilt_deg))  # keep the board in view of a tilted rig
    left, right = flume_rig(realistic_rig_spec(**PAPER, tilt_deg=tilt_deg, center_xy_m=(0.0, offset)))
    water = js.Interface(0.18)
    views = [render_view(cam, scene.heightfield, water) for cam in (left, right)]
    views = [dataclasses.replace(v, image=jpeg(v.image)) for v in views]
    return spec, Rig(left, right), views


def _survey_errors(spec, rig, views, model):
    survey, summary = reconstruct(views[0].image, views[1].image, rig, 0.18,
                                  ReconstructOptions(model=model, z_range_m=(-0.05, 0.4)))
    return survey, summary, layer_errors(survey.points, spec.height(survey.points[:, 0]), 0.18)


@pytest.fixture(scope="module")
def board():
    return _board_pair()


def test_board_exact_model_meets_paper_accuracy(board, capsys):
    spec, rig, views = board
    results = {}
    for model in ("exact", "first-order", "none"):
        survey, summary, rows = _survey_errors(spec, rig, views, model)
        results[model] = rows
        if model == "exact":
            exact_survey = survey
    with capsys.disabled():
        print("\nsloping board, 1728x1152, water 0.18 m: median vertical error per layer\n"
              + layer_table_markdown(results))
    submerged_layers = [r for r in results["exact"] if r["depth_from_m"] >= 0]
    assert len(submerged_layers) >= 3
    # The flat floor (the deepest layer, one disparity everywhere) is where SGBM's own sub-pixel values lean
    # towards whole pixels (2.9 mm here); the patch refinement from whole-pixel bases removes that (0.04 mm).
    for r in results["exact"]:
        assert abs(r["median_mm"]) <= 0.5, r
    every = exact_survey.points[:, 2] - spec.height(exact_survey.points[:, 0])
    assert np.mean(np.abs(every) > 0.02) <= 0.005  # one consistent match per pixel: no refracted mismatches
    sub = exact_survey.submerged
    err = exact_survey.points[sub, 2] - spec.height(exact_survey.points[sub, 0])
    assert np.sqrt(np.mean(err**2)) <= 1.0e-3
    # Ignoring refraction puts the deep points centimetres off; the first-order model millimetres.
    deepest = lambda m: max(results[m], key=lambda r: r["depth_from_m"])  # noqa: E731
    assert deepest("none")["median_mm"] > 20 * abs(deepest("exact")["median_mm"]) + 10
    assert abs(deepest("first-order")["median_mm"]) > abs(deepest("exact")["median_mm"])


def test_tilted_rig_30_degrees_exact_holds_first_order_grows(capsys):
    spec, rig, views = _board_pair(tilt_deg=18.0)
    # The rig sees the submerged board at up to 30 degrees of incidence.
    P = views[0].points[views[0].submerged][::500]
    o, _, _ = js.backproject_refracted(rig.left, js.Interface(0.18), js.project_refracted(rig.left, js.Interface(0.18), P)[0])
    v = np.asarray(o) - np.asarray(rig.left.center)
    incidence = np.degrees(np.arccos(np.abs(v[:, 2]) / np.linalg.norm(v, axis=1)))
    assert np.percentile(incidence, 95) >= 29.0
    results = {m: _survey_errors(spec, rig, views, m)[2] for m in ("exact", "first-order")}
    with capsys.disabled():
        print("\nsloping board, rig tilted 18 deg (incidence to 30 deg): median vertical error per layer\n"
              + layer_table_markdown(results))
    for r in results["exact"]:
        assert abs(r["median_mm"]) <= 1.0, r
    fo = [r["median_mm"] for r in results["first-order"] if r["depth_from_m"] >= 0]
    assert fo[-1] > 3.0 and fo[-1] > fo[0]  # grows with depth


def test_cameras_at_unequal_heights_over_deep_water(capsys):
    # A camera bar rolled by 10 degrees puts the right camera 3 cm above the left: the virtual cameras then differ
    # in height and the water rectification is exact for neither medium, so every match leans on its exact curve's
    # row offset. Deep water (0.25 m, 70 % of the board under it) makes those offsets large.
    spec = SlopingBoard()
    scene = build_scene(spec)
    level = 0.25
    left, right = flume_rig(realistic_rig_spec(**{**PAPER, "water_level_m": level}))
    raised = Pose.from_center(np.asarray(right.pose.R), np.asarray(right.center) + np.array([0.0, 0.0, 0.03]))
    right = dataclasses.replace(right, pose=raised)
    views = [jpeg(render_view(cam, scene.heightfield, js.Interface(level)).image) for cam in (left, right)]
    survey, summary = reconstruct(views[0], views[1], Rig(left, right), level,
                                  ReconstructOptions(z_range_m=(-0.05, 0.4)))
    rows = layer_errors(survey.points, spec.height(survey.points[:, 0]), level)
    with capsys.disabled():
        print("\nsloping board, right camera 3 cm higher, water 0.25 m: median vertical error per layer\n"
              + layer_table_markdown({"exact": rows}))
    assert summary["vertical_parallax_px_max"] > 0.3  # the curves leave the rectified rows
    assert survey.submerged.mean() > 0.6
    assert len(rows) == 8  # from 0.10 m above the water to 0.30 m below it
    for r in rows:
        assert abs(r["median_mm"]) <= 0.5, r
    error = survey.points[:, 2] - spec.height(survey.points[:, 0])
    assert np.sqrt(np.mean(error[survey.submerged] ** 2)) <= 1.0e-3
    assert np.mean(np.abs(error) > 0.02) <= 0.005


def test_breakwater_wet_and_dry_surveys_agree():
    spec = Breakwater(seed=2)
    scene = build_scene(spec)
    left, right = flume_rig(realistic_rig_spec(image_size=(1728, 1152), water_level_m=0.158))
    rig = Rig(left, right)
    water = js.Interface(0.158)
    wet = [jpeg(render_view(c, scene.heightfield, water).image) for c in (left, right)]
    dry = [jpeg(render_view(c, scene.heightfield, None).image) for c in (left, right)]
    options = ReconstructOptions(z_range_m=(-0.05, 0.45))
    s_wet, _ = reconstruct(wet[0], wet[1], rig, 0.158, options)
    s_dry, _ = reconstruct(dry[0], dry[1], rig, None, options)
    assert np.mean(s_wet.points[:, 2] < -0.02) <= 5e-4  # nothing refracted below the floor
    dem_wet = grid_median(s_wet.points, 0.01)
    dem_dry = grid_median(s_dry.points, 0.01, dem_wet.x, dem_wet.y)
    X, _ = np.meshgrid(dem_wet.x, dem_wet.y)
    slope = (X > spec.toe_x_m + 0.05) & (X < spec.toe_x_m + spec.slope * spec.crest_height_m - 0.05)
    diff = np.abs(dem_wet.z - dem_dry.z)[slope]
    diff = diff[np.isfinite(diff)]
    assert diff.size > 1000
    assert np.median(diff) <= 2e-3, np.median(diff)
    # Both agree with the truth too.
    truth = grid_median(np.stack([*np.meshgrid(scene.heightfield.x, scene.heightfield.y), np.asarray(scene.heightfield.z)],
                                 axis=-1).reshape(-1, 3), 0.01, dem_wet.x, dem_wet.y)
    err = np.abs(dem_wet.z - truth.z)[slope]
    assert np.nanmedian(err) <= 3e-3


def test_a_floor_a_metre_under_water_is_surveyed_on_its_exact_curves():
    """A wide rig (0.3 m baseline, 1.3 m above the water) over a floor 1 m deep: the exact epipolar curves leave the
    rectified rows by up to 1.5 px, and a third of the matches by more than half a pixel, so the right image is
    sampled on other rows than the left pixel's."""
    spec = realistic_rig_spec(image_size=(864, 576), water_level_m=0.0, camera_height_m=1.3, baseline_m=0.3)
    left, right = flume_rig(spec)
    water = js.Interface(0.0)
    scene = build_scene(js.FlatFloor(z_m=-1.0, extent=js.Extent(-2.0, 2.0, -1.4, 1.4, 2e-3), seed=1))
    images = [jpeg(render_view(c, scene.heightfield, water).image) for c in (left, right)]
    survey, summary = reconstruct(images[0], images[1], Rig(left, right), 0.0, ReconstructOptions(z_range_m=(-1.3, 0.2)))
    assert summary["vertical_parallax_px_max"] > 1.0  # the curves leave the rows (1.54 px; 0.77 read at half size)
    # Each match moved wholly onto its curve: the two rays meet (the median gap was 0.17 px with the curves' offsets
    # read at half their size)
    assert summary["median_ray_gap_px"] < 0.01
    error = np.abs(survey.points[:, 2] + 1.0)
    assert np.median(error) <= 0.8e-3  # 0.51 mm measured
    # 5.15 mm measured (4.33 mm with a 15 px small sub-pixel patch, the default before round 50); 5.85 mm with the
    # curves' offsets at half their size
    assert np.percentile(error, 99) <= 5.5e-3


def test_a_scene_rising_past_the_height_range_is_reported(board):
    _, rig, views = board
    options = ReconstructOptions(z_range_m=(-0.05, 0.25))
    survey, summary = reconstruct(views[0].image, views[1].image, rig, 0.18, options)
    assert survey.points[:, 2].max() <= 0.25
    # The board rises to 0.31 m: its top fifth lies above the range. Its matches either land in the search's
    # margin (triangulated above 0.25 m, dropped and counted; measured: 29.5 % of all matches) or are lost.
    above = summary["dropped_above_height_range"]
    assert above > 0.02 * summary["matches"], above
    assert summary["height_range_m"] == [-0.05, 0.25]
    assert len(summary["warnings"]) == 1
    assert f"{above} matches" in summary["warnings"][0]
    assert "above the height range's top, z = 0.250 m" in summary["warnings"][0]
    # The whole board inside the range: no match above it, no warning.
    stages = []
    _, summary = reconstruct(views[0].image, views[1].image, rig, 0.18, ReconstructOptions(z_range_m=(-0.05, 0.4)),
                             on_stage=stages.append)
    assert summary["dropped_above_height_range"] == 0 and summary["warnings"] == []
    # Each stage was announced as it started, in order: the ones the summary times.
    assert stages == ["rectify+match", "sub-pixel", "triangulate", "uncertainty"]
    assert stages == [key.removesuffix(" (s)") for key in summary["seconds"]]


def test_matches_dropped_beside_the_triangulation_leave_the_points_and_counts_of_a_disparity_without_them(x64):
    """`reconstruct` runs the photometric check beside the triangulation and drops its matches from the points
    after (`_triangulate_matches`'s `dropped`): the points, pixels and every count must be those of triangulating
    the disparity without those matches. Disparities across the whole search range put some points below the
    height range and some above it."""
    from jaxstereo._stereo.reconstruct import _search_range, _triangulate_matches
    from jaxstereo._stereo.rectify import rectify_checked

    rig = Rig(*flume_rig(realistic_rig_spec(**PAPER)))
    water, z_range = js.Interface(0.18), (-0.05, 0.3)
    rect = rectify_checked(rig.left, rig.right, water, "water")
    first, count = _search_range(rect, rig, water, z_range, ReconstructOptions())
    rng = np.random.default_rng(7)
    shape = (288, 432)  # the rectified image's top left corner
    disparity = (first + count * rng.random(shape)).astype(np.float32)
    disparity[rng.random(shape) < 0.1] = np.nan
    marked = rng.random(shape) < 0.2
    dropped = _triangulate_matches(rect, rig, water, "exact", disparity, None, z_range, 1.0, dropped=lambda: marked)
    without = _triangulate_matches(rect, rig, water, "exact", np.where(marked, np.nan, disparity), None, z_range, 1.0)
    for name in ("v", "u", "points", "submerged"):
        np.testing.assert_array_equal(getattr(dropped, name), getattr(without, name))
    assert dropped.counts == without.counts and dropped.median_gap_px == without.median_gap_px
    assert without.counts["dropped_above_height_range"] > 0 and without.counts["dropped_outside_height_range"] > (
        without.counts["dropped_above_height_range"])  # some below the range too
    assert without.counts["matches"] == np.count_nonzero(np.isfinite(disparity) & ~marked)


def test_reconstruct_bad_input(board):
    spec, rig, views = board
    left, right = views[0].image, views[1].image
    with pytest.raises(js.JaxStereoError, match="right image is 864x576 but the rig's cameras are 1728x1152"):
        reconstruct(left, right[::2, ::2], rig, 0.18)
    with pytest.raises(js.JaxStereoError, match="left camera centre is .* below the water plane"):
        reconstruct(left, right, rig, 3.0)
    with pytest.raises(js.JaxStereoError, match="below the whole scene"):
        reconstruct(left, right, rig, -0.5)
    blank = np.zeros_like(left)
    with pytest.raises(js.JaxStereoError, match="no matches survived"):
        reconstruct(blank, blank, rig, 0.18)
    with pytest.raises(js.JaxStereoError, match="model must be one of"):
        ReconstructOptions(model="magic")
