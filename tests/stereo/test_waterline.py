"""The water plane's own disparity in a water rectification: exact against the exact triangulation."""

import jax.numpy as jnp
import numpy as np

from jaxstereo._geometry.interface import Interface, tilt_normal
from jaxstereo._stereo.reconstruct import _triangulate_model
from jaxstereo._stereo.rectify import rectify_checked, waterline_disparity
from jaxstereo._synthetic.flume_rig import flume_rig, realistic_rig_spec


def test_the_waterline_disparity_triangulates_onto_the_water_and_splits_above_from_below(x64):
    """A realistic rig (cameras tilted and turned, lens distortion) over a water plane tilted by a tenth of a degree:
    a match at the waterline disparity (same row) lands on the plane, one a pixel more above it, one less below."""
    left, right = flume_rig(realistic_rig_spec(water_level_m=0.12, image_size=(960, 640)))
    water = Interface(0.12, tilt_normal(0.0015, -0.001))
    rect = rectify_checked(left, right, water, "water")
    d = waterline_disparity(rect)
    assert d.shape == (640, 960) and waterline_disparity(rectify_checked(left, right, None, "air")) is None
    rng = np.random.default_rng(0)
    u, v = rng.integers(0, 960, 300).astype(np.float64), rng.integers(0, 640, 300).astype(np.float64)
    at = d[v.astype(int), u.astype(int)].astype(np.float64)
    normal = np.asarray(water.normal)
    for step, side in ((0.0, 0), (1.0, 1), (-1.0, -1)):
        points, _, submerged, ok = _triangulate_model(rect, left, right, water, "exact",
                                                      jnp.asarray(np.stack([u, v], -1)),
                                                      jnp.asarray(np.stack([u - at - step, v], -1)))
        height = np.asarray(points) @ normal - 0.12
        assert np.all(np.asarray(ok))
        if side == 0:
            assert np.abs(height).max() < 2e-6  # float32 disparities: 1e-5 px
        else:
            assert np.all(np.sign(height) == side) and np.all(np.asarray(submerged) == (side < 0))
