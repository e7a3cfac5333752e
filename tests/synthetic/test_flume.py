import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

import jaxstereo as js
from jaxstereo._synthetic.flume_rig import RigSpec, flume_rig
from jaxstereo._synthetic.render import RenderOptions, render_view
from jaxstereo._synthetic.scenes import (
    Breakwater,
    Damage,
    Extent,
    FlatFloor,
    SlopingBoard,
    build_scene,
    scene_from_json,
    scene_to_json,
)

SMALL = Extent(-0.6, 0.6, -0.4, 0.4, 2e-3)


def _pixel_centres(view):
    h, w = view.hit.shape
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    return np.stack([u, v], axis=-1)


@pytest.mark.parametrize("tilt_deg, tilt_x, tilt_y", [(0.0, 0.0, 0.0), (18.0, 0.03, -0.04)])
def test_ground_truth_points_project_onto_their_pixel_centres(tilt_deg, tilt_x, tilt_y):
    scene = build_scene(Breakwater(extent=Extent(-0.6, 0.6, -0.35, 1.0, 2e-3), seed=4))
    left, _ = flume_rig(RigSpec(image_size=(288, 192), water_level_m=0.158, tilt_deg=tilt_deg,
                                dist=(-0.05, 0.02, 0.0, 0.0, 0.0)))
    water = js.Interface.from_tilt(0.158, tilt_x, tilt_y)
    view = render_view(left, scene.heightfield, water, RenderOptions(fine_step_m=2e-3))
    m = view.hit
    assert m.sum() > 20000
    assert 0.2 < view.submerged[m].mean() < 0.8  # both emerged and submerged pixels are checked
    pixels, valid = js.project_refracted(left, water, jnp.asarray(view.points[m]))
    err = np.abs(np.asarray(pixels) - _pixel_centres(view)[m]).max(axis=-1)
    assert bool(np.all(valid))
    assert err.max() < 0.02
    # And the points lie on the scene's surface.
    z, _ = scene.heightfield.height_at(jnp.asarray(view.points[m][:, :2]))
    assert np.abs(np.asarray(z) - view.points[m][:, 2]).max() < 1e-4


def test_finer_bounds_skip_empty_space_without_passing_the_surface():
    """The 4-node and single-cell bounds let a ray take long steps beside a rock; they find the surface where the
    16-node bound alone does, but for rays whose path through a rock's edge is shorter than the 1 mm fine step
    (either sampling may catch or miss such a graze: the surface behind is found instead)."""
    scene = build_scene(Breakwater(extent=Extent(-0.6, 0.6, -0.35, 1.0, 1e-3), seed=4))
    left, _ = flume_rig(RigSpec(image_size=(432, 288), water_level_m=0.158, tilt_deg=5.0))
    water = js.Interface(0.158)
    views = [render_view(left, scene.heightfield, water, RenderOptions(skip_levels=k)) for k in (1, 3)]
    np.testing.assert_array_equal(views[0].hit, views[1].hit)
    apart = np.linalg.norm(views[0].points - views[1].points, axis=-1)[views[0].hit]
    assert views[0].hit.sum() > 100000
    assert np.mean(apart > 1e-6) < 2e-4  # measured: 7 of 110,210 here (25 of 500,000 pixels at 864x576)
    assert np.median(apart) < 1e-9
    with pytest.raises(js.JaxStereoError, match="skip_levels must be 1, 2 or 3"):
        RenderOptions(skip_levels=4)


def test_sloping_board_heights_are_exact():
    spec = SlopingBoard(extent=SMALL)
    scene = build_scene(spec)
    left, _ = flume_rig(RigSpec(image_size=(216, 144), water_level_m=0.18))
    view = render_view(left, scene.heightfield, js.Interface(0.18), RenderOptions(fine_step_m=2e-3))
    p = view.points[view.hit]
    assert np.abs(p[:, 2] - spec.height(p[:, 0])).max() < 1e-7
    # Submerged exactly where the board is under 0.18 m.
    np.testing.assert_array_equal(view.submerged[view.hit], p[:, 2] < 0.18)


def test_scenes_are_deterministic_and_serialisable():
    spec = Breakwater(extent=SMALL, seed=11, damage=Damage(half_length_dn50=2.5, deep_fraction=0.5))
    again = scene_from_json(scene_to_json(spec))
    assert again == spec
    a, b = build_scene(spec), build_scene(again)
    np.testing.assert_array_equal(np.asarray(a.heightfield.z), np.asarray(b.heightfield.z))
    np.testing.assert_array_equal(np.asarray(a.heightfield.albedo), np.asarray(b.heightfield.albedo))
    other = build_scene(dataclasses.replace(spec, seed=12))
    assert not np.array_equal(np.asarray(other.heightfield.z), np.asarray(a.heightfield.z))
    for s in (FlatFloor(extent=SMALL), SlopingBoard(extent=SMALL)):
        assert scene_from_json(scene_to_json(s)) == s


def test_damage_removes_units_around_swl_and_lowers_the_surface():
    intact = build_scene(Breakwater(extent=SMALL, seed=5))
    stages = [build_scene(Breakwater(extent=SMALL, seed=5, damage=Damage(half_length_dn50=k, deep_fraction=f)))
              for k, f in ((1.5, 0.0), (2.5, 0.3), (3.5, 0.6))]
    removed = [int(s.rocks["removed"].sum() + s.rocks["deposited"].sum()) for s in stages]
    assert removed[0] < removed[1] < removed[2]
    z0 = np.asarray(intact.heightfield.z)
    x = intact.heightfield.x
    swl_zone = np.abs(x - (-0.45 + 2.0 * 0.158)) < 0.05
    losses = [float(np.mean(np.clip(z0 - np.asarray(s.heightfield.z), 0, None)[:, swl_zone])) for s in stages]
    assert 0 < losses[0] < losses[1] < losses[2]


def test_bad_scene_input():
    with pytest.raises(js.JaxStereoError, match="dn50_m must be positive"):
        Breakwater(dn50_m=0.0)
    with pytest.raises(js.JaxStereoError, match="slope"):
        Breakwater(slope=0.5)
    with pytest.raises(js.JaxStereoError, match="supersample"):
        RenderOptions(supersample=2)
    with pytest.raises(js.JaxStereoError, match="unknown kind"):
        scene_from_json('{"kind": "volcano", "extent": {}}')


def test_scene_entirely_under_water_is_refracted_at_the_surface():
    # Regression: a flat floor 0.5 m under the water, nothing above it.
    scene = build_scene(FlatFloor(z_m=-0.5, extent=Extent(-1.0, 1.0, -0.8, 0.8, 4e-3)))
    left, _ = flume_rig(RigSpec(image_size=(216, 144), water_level_m=0.0, camera_height_m=1.3))
    water = js.Interface(0.0)
    view = render_view(left, scene.heightfield, water, RenderOptions(fine_step_m=4e-3))
    m = view.hit
    assert m.mean() > 0.9 and view.submerged[m].all()
    np.testing.assert_allclose(view.points[m][:, 2], -0.5, atol=1e-7)
    pixels, _ = js.project_refracted(left, water, jnp.asarray(view.points[m]))
    assert np.abs(np.asarray(pixels) - _pixel_centres(view)[m]).max() < 0.02


def _first_crossings_numpy(z, spacing, origin, direction, s_max, sample_m=2e-5):
    """Reference for rays (n, 3) over the bilinear surface z (grid origin at 0, 0): the first sample under it on a
    dense scan, then 50 halvings of the step before it; NaN where no sample is under it."""
    ny, nx = z.shape

    def below(s):
        p = origin + s[:, None] * direction
        gx, gy = p[:, 0] / spacing, p[:, 1] / spacing
        inside = (gx >= 0) & (gx <= nx - 1) & (gy >= 0) & (gy <= ny - 1)
        j = np.clip(np.floor(gx), 0, nx - 2).astype(int)
        i = np.clip(np.floor(gy), 0, ny - 2).astype(int)
        fx, fy = gx - j, gy - i
        h = (z[i, j] * (1 - fx) + z[i, j + 1] * fx) * (1 - fy) + (z[i + 1, j] * (1 - fx) + z[i + 1, j + 1] * fx) * fy
        return inside & (p[:, 2] <= h)

    steps = np.arange(0.0, s_max.max() + sample_m, sample_m)
    under = np.stack([below(np.minimum(s, s_max)) & (s_max > 0) for s in steps], axis=1)
    found = under.any(axis=1)
    k = np.argmax(under, axis=1)
    lo, hi = steps[np.maximum(k - 1, 0)], np.minimum(steps[k], s_max)
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        inside = below(mid)
        lo, hi = np.where(inside, lo, mid), np.where(inside, mid, hi)
    return np.where(found, 0.5 * (lo + hi), np.nan)


def test_first_hits_match_a_dense_numpy_scan_whatever_the_pool_size(rng):
    """The pooled march (slots handed to the next ray as rays finish) against a numpy scan at 20 um, on a
    rolling surface with slopes up to about 1: same hits, same distances within 10 nm, with the
    three bounds that skip empty space and with the coarse one alone; bit for bit the same for any pool size."""
    import jax

    from jaxstereo._synthetic.heightfield import Heightfield
    from jaxstereo._synthetic.render import _march

    spacing = 1e-3
    y, x = np.mgrid[0:80, 0:90] * spacing
    z = 0.02 + 0.01 * np.sin(x / 0.007) * np.cos(y / 0.009) + 0.004 * np.sin((x + 2 * y) / 0.003)
    n = 300
    origin = np.stack([rng.uniform(0.0, 0.09, n), rng.uniform(0.0, 0.08, n), np.full(n, 0.05)], axis=-1)
    tilt, turn = np.radians(rng.uniform(0.0, 35.0, n)), rng.uniform(0.0, 2 * np.pi, n)
    direction = np.stack([np.sin(tilt) * np.cos(turn), np.sin(tilt) * np.sin(turn), -np.cos(tilt)], axis=-1)
    s_max = np.where(rng.uniform(size=n) < 0.1, 0.0, 0.06 / np.cos(tilt))  # a tenth of the rays are empty
    with jax.enable_x64(True):
        hf64 = Heightfield(z, np.full(z.shape + (3,), 0.5), 0.0, 0.0, spacing, block=8)
        runs = [jax.tree.map(np.asarray, _march(hf64, jnp.asarray(origin), jnp.asarray(direction),
                                                 jnp.asarray(s_max), 1e-3, 2000, pool, levels))
                for levels in (3, 1) for pool in (7, n)]
    reference = _first_crossings_numpy(np.asarray(hf64.z), spacing, origin, direction, s_max)
    hit = np.isfinite(reference)
    assert 100 < hit.sum() < n - 30  # rays that hit, rays that leave the grid or are empty
    for i, (s, found) in enumerate(runs):
        np.testing.assert_array_equal(found, hit)
        assert np.abs(s[hit] - reference[hit]).max() < 1e-8
        # the pool size changes nothing; the bounds change the step sequence, so only round-off
        np.testing.assert_array_equal(s[hit], runs[i - i % 2][0][hit])
