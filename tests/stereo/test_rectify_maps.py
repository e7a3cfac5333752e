"""The remap tables of a water rectification: exact mapping on a coarse grid, interpolated to every pixel.

References: the exact per-pixel mapping (`rectified_to_real`), and bilinear interpolation written as the dense
interpolation matrices' product (numpy), on a grid whose size is no multiple of the grid step.
"""

import jax.numpy as jnp
import numpy as np
import pytest

from jaxstereo._geometry.interface import Interface
from jaxstereo._stereo.rectify import (
    MAP_STEP,
    _all_weighed_ok,
    _coarse_axis,
    _upsampled,
    real_to_rectified,
    rectification_maps,
    rectified_to_real,
    rectify_checked,
)
from jaxstereo._synthetic.flume_rig import flume_rig, realistic_rig_spec


def _dense_weights(coarse: np.ndarray, n: int) -> np.ndarray:
    """(n, len(coarse)) linear interpolation weights from the `coarse` knots to 0..n-1."""
    x = np.arange(n, dtype=np.float64)
    k = np.minimum((x // MAP_STEP).astype(int), len(coarse) - 2)
    t = (x - coarse[k]) / MAP_STEP
    weights = np.zeros((n, len(coarse)))
    weights[np.arange(n), k] = 1.0 - t
    weights[np.arange(n), k + 1] = t
    return weights


@pytest.mark.parametrize("h, w", [(101, 203), (97, 201), (96, 200)])  # the last knot past, on, past the edge
def test_upsampling_is_bilinear_and_a_pixel_is_outside_where_any_knot_it_weighs_is(rng, h, w):
    vs, us = _coarse_axis(h), _coarse_axis(w)
    values = rng.normal(0.0, 300.0, (len(vs), len(us)))
    ok = rng.random((len(vs), len(us))) > 0.05
    A, B = _dense_weights(vs, h), _dense_weights(us, w)
    upsampled = _upsampled(values, h, w)
    assert upsampled.flags.c_contiguous  # cv2.remap takes it as it is
    np.testing.assert_allclose(upsampled, A @ values @ B.T, rtol=0, atol=1e-9)
    expected = (A @ ok.astype(np.float64) @ B.T) > 1.0 - 1e-9
    inside = _all_weighed_ok(ok, h, w)
    assert inside.shape == (h, w) and 0.5 < inside.mean() < 0.95  # holes do reach pixels: the check can fail
    np.testing.assert_array_equal(inside, expected)


def test_water_rectification_maps_follow_the_exact_mapping_on_a_tilted_distorted_rig(x64, rng):
    left, right = flume_rig(realistic_rig_spec(image_size=(960, 640), water_level_m=0.12))
    rect = rectify_checked(left, right, Interface(0.12), "water")
    for side, cam in enumerate((left, right)):
        map_x, map_y = rectification_maps(rect, cam, side)
        assert map_x.shape == map_y.shape == (640, 960) and map_x.dtype == np.float32
        u, v = rng.integers(0, 960, 4000), rng.integers(0, 640, 4000)
        real, valid = rectified_to_real(rect, cam, side, jnp.asarray(np.stack([u, v], axis=-1), dtype=jnp.float64))
        real, valid = np.asarray(real), np.asarray(valid)
        table = np.stack([map_x[v, u], map_y[v, u]], axis=-1)
        inside = table[:, 0] >= 0
        assert inside.mean() > 0.9 and np.all(valid[inside])
        assert np.abs(table[inside] - real[inside]).max() < 1e-3  # pixels


def _share_in_view(rect, camera) -> float:
    """The share of the left real image (a grid every 8 px) whose pixels land inside the rectified image."""
    w, h = camera.image_size
    u, v = np.meshgrid(np.arange(0, w, 8.0), np.arange(0, h, 8.0))
    px = np.asarray(real_to_rectified(rect, camera, 0, jnp.asarray(np.stack([u.ravel(), v.ravel()], axis=-1))))
    rw, rh = rect.size
    return float(np.mean((px[:, 0] >= 0) & (px[:, 0] <= rw - 1) & (px[:, 1] >= 0) & (px[:, 1] <= rh - 1)))


@pytest.mark.parametrize("mode", ["air", "water"])
@pytest.mark.parametrize("turn_deg", [0.0, 90.0, 180.0, 270.0])
def test_rectified_images_hold_the_whole_view_whichever_way_the_cameras_are_turned(x64, mode, turn_deg):
    """Cameras turned a quarter about their axes see the baseline (world X) run up or down the image, along its
    short side: the rectified rows run along the baseline, so the rectified images must be the real ones' height
    wide and their width high. Before they kept the real size, and the rectified view lost a third of the scene
    (the POV-Ray flume's quarter-turned pair: 693,000 points instead of 1.24 million)."""
    misalign = ((0.4, -0.3, 0.6 + turn_deg), (-0.5, 0.7, -0.35 + turn_deg))
    left, right = flume_rig(realistic_rig_spec(image_size=(960, 640), water_level_m=0.12, misalignment_deg=misalign))
    rect = rectify_checked(left, right, Interface(0.12), mode)
    assert rect.size == ((640, 960) if turn_deg % 180 else (960, 640))
    assert _share_in_view(rect, left) > 0.95  # 0.97 measured at every turn; 0.66 quarter-turned before
    for side, cam in enumerate((left, right)):
        map_x, _ = rectification_maps(rect, cam, side)
        assert map_x.shape == (rect.size[1], rect.size[0])
        assert np.mean(map_x >= 0) > 0.9  # the rectified image is filled from the real one, not left black
