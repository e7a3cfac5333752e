import json

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

import jaxstereo as js
from jaxstereo._calibration.rig import Rig, load_rig, rig_to_dict, save_rig

finite = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False)


def _rig(rvec, t, f, dist, level):
    pose = js.Pose.from_rvec(np.asarray(rvec), np.asarray(t))
    left = js.Camera(f, f * 1.01, 320.5, 240.25, dist, pose, (640, 480))
    right = js.Camera(f * 0.99, f, 319.0, 241.0, dist[::-1], js.Pose.from_rvec(np.asarray(rvec) * 0.5, np.asarray(t) + 0.1),
                      (640, 480))
    return Rig(left, right, js.Interface.from_tilt(level, 0.01, -0.02), {"note": "test", "rms": 0.25})


@settings(max_examples=25, deadline=None)
@given(st.lists(st.floats(-3, 3), min_size=3, max_size=3), st.lists(finite, min_size=3, max_size=3),
       st.floats(10, 1e4), st.lists(st.floats(-1, 1), min_size=5, max_size=5), finite)
def test_rig_json_round_trips_bit_for_bit(tmp_path_factory, rvec, t, f, dist, level):
    rig = _rig(rvec, t, f, np.asarray(dist), level)
    path = tmp_path_factory.mktemp("rig") / "rig.json"
    save_rig(rig, path)
    back = load_rig(path)
    a, b = rig_to_dict(rig), rig_to_dict(back)
    assert a == b  # floats compared exactly
    np.testing.assert_array_equal(np.asarray(back.left.pose.R), np.asarray(rig.left.pose.R))
    assert back.interface is not None and float(back.interface.level) == float(rig.interface.level)


def _write(tmp_path, data):
    path = tmp_path / "rig.json"
    path.write_text(json.dumps(data))
    return path


def test_rig_bad_fields_are_named(tmp_path):
    good = rig_to_dict(_rig([0.1, 0.2, 0.3], [0.0, 0.0, 2.0], 800.0, np.zeros(5), 0.15))
    cases = [
        (lambda d: d["left"].pop("fx"), "field left.fx is missing"),
        (lambda d: d["right"].__setitem__("cy", float("nan")), "field right.cy must be a finite number"),
        (lambda d: d["left"].__setitem__("R", [[1, 0], [0, 1]]), r"field left.R must have shape \(3, 3\)"),
        (lambda d: d["interface"].__setitem__("normal", [0, 0, 2]), "normal must be a unit vector"),
        (lambda d: d.pop("image_size"), "field rig.image_size is missing"),
        (lambda d: d.__setitem__("format", "other"), "field format must be"),
        (lambda d: d["left"].__setitem__("R", [[2, 0, 0], [0, 1, 0], [0, 0, 1]]), "not a rotation matrix"),
    ]
    for mutate, message in cases:
        data = json.loads(json.dumps(good))
        mutate(data)
        with pytest.raises(js.JaxStereoError, match=message):
            load_rig(_write(tmp_path, data))
    (tmp_path / "broken.json").write_text("{not json")
    with pytest.raises(js.JaxStereoError, match="not valid JSON"):
        load_rig(tmp_path / "broken.json")
    with pytest.raises(js.JaxStereoError, match="does not exist"):
        load_rig(tmp_path / "missing.json")
