"""The command line's head start on matching: a kept plan gives the same match, and nothing else does."""

import subprocess
import sys
from concurrent.futures import Future

import numpy as np
import pytest

from jaxstereo._stereo.match_ahead import MatchAhead, MatchPlan, match_rectifying, plan_path
from jaxstereo._stereo.matching import MatchOptions

SIZE = (320, 200)  # w, h


def _done(value) -> Future:
    future = Future()
    future.set_result(value)
    return future


def _failed(error) -> Future:
    future = Future()
    future.set_exception(error)
    return future


@pytest.fixture
def pair():
    """A textured pair 12 px apart, and remap tables that move each image by a fraction of a pixel (an
    interpolating rectification, not the identity)."""
    rng = np.random.default_rng(5)
    w, h = SIZE
    texture = rng.integers(0, 256, (h, w + 12, 3)).astype(np.uint8)
    left, right = np.ascontiguousarray(texture[:, :-12]), np.ascontiguousarray(texture[:, 12:])
    u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    maps = ((u + 0.3, v - 0.2), (u + 0.25, v - 0.2))
    plan = MatchPlan("k1", maps, (4, 16), MatchOptions(), True)
    return left, right, plan


def test_a_kept_plan_is_matched_ahead_and_equals_the_match_made_after_rectifying(pair, tmp_path):
    left, right, plan = pair
    path = tmp_path / "plan.npz"
    images = (_done(left), _done(right))
    first = MatchAhead(path, images)
    assert first.take("k1", SIZE) is None  # no plan kept yet
    first.keep(plan)
    assert path.is_file() and not list(tmp_path.glob("*.partial"))
    direct = match_rectifying(left, right, plan.maps, plan.search, plan.options, plan.colour)
    assert 0.8 * SIZE[0] * SIZE[1] < np.isfinite(direct.disparity).sum()
    assert abs(np.nanmedian(direct.disparity) - 12.0) < 0.1
    ahead = MatchAhead(path, images).take("k1", SIZE)
    assert ahead is not None
    for name in ("left", "right", "disparity"):
        assert np.array_equal(getattr(ahead, name), getattr(direct, name), equal_nan=True), name
    assert all(np.array_equal(a, b) for a, b in zip(ahead.left_map, plan.maps[0]))
    # Another plan's key, or images of another size, take nothing.
    assert MatchAhead(path, images).take("k2", SIZE) is None
    assert MatchAhead(path, images).take("k1", (SIZE[0] + 1, SIZE[1])) is None
    cropped = (_done(left), _done(np.ascontiguousarray(right[:, 1:])))  # a right image not the rig's size
    assert MatchAhead(path, cropped).take("k1", SIZE) is None


def test_grey_images_or_colour_off_match_on_grey(pair, tmp_path):
    left, right, plan = pair
    grey = MatchPlan("k1", plan.maps, plan.search, plan.options, False)
    on_colour = match_rectifying(left, right, plan.maps, plan.search, plan.options, True)
    on_grey = match_rectifying(left, right, grey.maps, grey.search, grey.options, False)
    assert on_grey.left.ndim == 3  # the rectified images stay in colour for the survey's colours
    assert not np.array_equal(on_grey.disparity, on_colour.disparity, equal_nan=True)
    single = match_rectifying(left[..., 0], right[..., 0], plan.maps, plan.search, plan.options, True)
    assert single.left.ndim == 2 and abs(np.nanmedian(single.disparity) - 12.0) < 0.1


def test_an_unreadable_plan_or_image_gives_no_match_ahead(pair, tmp_path):
    left, right, plan = pair
    path = tmp_path / "plan.npz"
    MatchAhead(path, (_done(left), _done(right))).keep(plan)
    assert MatchAhead(path, (_failed(OSError("no such image")), _done(right))).take("k1", SIZE) is None
    path.write_bytes(b"PK\x03\x04 half a zip")
    assert MatchAhead(path, (_done(left), _done(right))).take("k1", SIZE) is None
    # A plan that cannot be kept (its folder is a file) leaves the command as it was.
    blocked = tmp_path / "file"
    blocked.write_text("")
    MatchAhead(blocked / "plan.npz", (_done(left), _done(right))).keep(plan)
    assert not (blocked / "plan.npz").exists()


def test_the_plan_file_follows_the_rig_file_and_the_arguments(tmp_path):
    rig = tmp_path / "rig.json"
    rig.write_text('{"a": 1}')

    def digest():
        return b"source"

    args = {"water_level": 0.16, "z_range": None}
    path = plan_path(tmp_path, digest, rig, args)
    assert path.parent == tmp_path and path.name.startswith("match-plan-")
    assert plan_path(tmp_path, digest, rig, dict(args)) == path
    assert plan_path(tmp_path, digest, rig, {**args, "water_level": 0.17}) != path
    assert plan_path(tmp_path, lambda: b"other source", rig, args) != path
    rig.write_text('{"a": 2}')
    assert plan_path(tmp_path, digest, rig, args) != path
    assert plan_path(tmp_path, digest, tmp_path / "missing.json", args) is None


def test_the_head_start_imports_no_jax():
    code = ("import sys\nimport jaxstereo._stereo.match_ahead, jaxstereo._stereo.table_cache\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('jax', 'jaxlib', 'equinox')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "[]"
