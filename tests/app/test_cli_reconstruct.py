import json

import numpy as np
import pytest

import jaxstereo as js
from jaxstereo._app.cli import main
from jaxstereo._app.images import write_image
from jaxstereo._calibration.rig import Rig, load_rig, save_rig
from jaxstereo._stereo.survey import load_survey
from jaxstereo._synthetic.flume_rig import RigSpec, flume_rig
from jaxstereo._synthetic.render import RenderOptions, render_view
from jaxstereo._synthetic.scenes import Extent, SlopingBoard, build_scene


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    root = tmp_path_factory.mktemp("pair")
    spec = SlopingBoard(extent=Extent(spacing=2e-3))
    left, right = flume_rig(RigSpec(image_size=(432, 288), water_level_m=0.18))
    water = js.Interface(0.18)
    scene = build_scene(spec)
    for name, cam in (("left.png", left), ("right.png", right)):
        write_image(root / name, render_view(cam, scene.heightfield, water, RenderOptions(fine_step_m=2e-3)).image)
    save_rig(Rig(left, right), root / "rig.json")
    return root, spec


def _run(root, tmp_path, *extra, left="left.png", right="right.png", rig="rig.json"):
    return main(["reconstruct", str(root / left), str(root / right), "--rig", str(root / rig),
                 "-o", str(tmp_path / "out" / "survey.npz"), *extra])


def test_reconstruct_command_writes_survey_ply_preview_summary(pair, tmp_path, capsys):
    root, spec = pair
    assert _run(root, tmp_path, "--water-level", "0.18", "--ply", str(tmp_path / "out" / "survey.ply")) == 0
    out = capsys.readouterr().out
    assert "submerged fraction" in out and "triangulate (s)" in out
    survey = load_survey(tmp_path / "out" / "survey.npz")
    assert len(survey) > 50000 and 0.3 < survey.submerged.mean() < 0.8
    err = survey.points[:, 2] - spec.height(survey.points[:, 0])
    assert abs(np.median(err[survey.submerged])) < 6e-3  # 432 px wide: 1 px of disparity is 44 mm here (0.1 px: 4.4 mm)
    assert json.loads(survey.rig_json)["interface"]["level"] == 0.18
    ply = (tmp_path / "out" / "survey.ply").read_bytes()
    assert ply.startswith(b"ply\nformat binary_little_endian 1.0") and f"element vertex {len(survey)}".encode() in ply
    assert (tmp_path / "out" / "survey_preview.png").read_bytes()[:4] == b"\x89PNG"
    summary = json.loads((tmp_path / "out" / "survey_summary.json").read_text())
    assert summary["points"] == len(survey)
    assert summary["warnings"] == [] and "WARNING" not in out


def test_reconstruct_command_warns_when_the_scene_rises_past_the_height_range(pair, tmp_path, capsys):
    root, _ = pair
    assert _run(root, tmp_path, "--water-level", "0.18", "--z-range", "-0.05", "0.2") == 0  # the board rises to 0.31 m
    out = capsys.readouterr().out
    summary = json.loads((tmp_path / "out" / "survey_summary.json").read_text())
    assert summary["dropped_above_height_range"] > 0.02 * summary["matches"]
    assert f"WARNING: {summary['dropped_above_height_range']} matches" in out
    assert "above the height range's top, z = 0.200 m" in out and "--z-range" in out
    assert load_survey(tmp_path / "out" / "survey.npz").points[:, 2].max() <= 0.2


def _error(capsys, code, text, tmp_path):
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and text in err, err
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_reconstruct_command_bad_input(pair, tmp_path, capsys):
    root, _ = pair
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "empty.png").write_bytes(b"")
    (bad / "truncated.png").write_bytes((root / "left.png").read_bytes()[:300])
    write_image(bad / "small.png", np.zeros((100, 150, 3), np.uint8))
    data = json.loads((root / "rig.json").read_text())
    del data["right"]["t"]
    (bad / "rig_missing.json").write_text(json.dumps(data))
    data = json.loads((root / "rig.json").read_text())
    data["left"]["fx"] = float("nan")
    (bad / "rig_nan.json").write_text(json.dumps(data))
    cases = [
        (dict(left=str(bad / "empty.png")), "is empty (0 bytes)"),
        (dict(left=str(bad / "truncated.png")), "cannot be read"),
        (dict(right=str(bad / "small.png")), "small.png' is 150x100 but the rig's cameras are 432x288"),
        (dict(rig=str(bad / "rig_missing.json")), "field right.t is missing"),
        (dict(rig=str(bad / "rig_nan.json")), "field left.fx must be a finite number"),
        (dict(rig=str(bad / "nothing.json")), "does not exist"),
    ]
    for kwargs, text in cases:
        _error(capsys, _run(root, tmp_path, "--water-level", "0.18", **kwargs), text, tmp_path)
    _error(capsys, _run(root, tmp_path, "--water-level", "5.0"), "below the water plane", tmp_path)
    _error(capsys, _run(root, tmp_path, "--water-level", "-1.0"), "below the whole scene", tmp_path)
    # An empty match set (the command itself refuses uniform images earlier; see test_robustness.py).
    black = np.zeros((288, 432, 3), np.uint8)
    with pytest.raises(js.JaxStereoError, match="no matches survived"):
        js.reconstruct(black, black, load_rig(root / "rig.json"), 0.18)


def test_one_way_flag_keeps_every_match_the_second_run_would_drop(pair, tmp_path):
    """`--one-way` skips matching the right image against the left: a superset of the two-way survey's pixels,
    with the same points where both have one."""
    root, _ = pair
    surveys = {}
    for flag in ((), ("--one-way",)):
        out = tmp_path / ("one" if flag else "two")
        assert main(["reconstruct", str(root / "left.png"), str(root / "right.png"), "--rig", str(root / "rig.json"),
                     "--water-level", "0.18", "-o", str(out / "survey.npz"), *flag]) == 0
        surveys[bool(flag)] = load_survey(out / "survey.npz")
    one, two = surveys[True], surveys[False]

    def key(s):
        return np.rint(s.pixels * 4).astype(np.int64) @ np.array([1, 1 << 20])

    common, i_one, i_two = np.intersect1d(key(one), key(two), return_indices=True)
    assert len(one) > len(two) and common.size > 0.97 * len(two)
    assert np.median(np.abs(one.points[i_one, 2] - two.points[i_two, 2])) < 1e-4


def test_the_rig_tables_kept_between_commands_give_the_same_survey(pair, tmp_path, monkeypatch):
    root, _ = pair
    monkeypatch.setenv("JAXSTEREO_CACHE_DIR", "off")
    assert _run(root, tmp_path / "off", "--water-level", "0.18") == 0
    assert not (tmp_path / "off" / "tables").exists()
    monkeypatch.setenv("JAXSTEREO_CACHE_DIR", str(tmp_path / "cache"))
    tables = tmp_path / "cache" / "tables"
    assert _run(root, tmp_path / "first", "--water-level", "0.18") == 0
    kept = sorted(p.name.split("-")[0] for p in tables.glob("*.npz"))
    # the rectification, its two map grids, the search range, the exact row offsets, the shared covariance, and
    # the match plan (the remap tables and the search range, for the next command's head start: match_ahead.py)
    assert kept == ["disparity", "exact", "match", "rectification", "rectification", "rectification", "shared"]
    written = {p: p.stat().st_mtime_ns for p in tables.glob("*.npz")}
    assert _run(root, tmp_path / "second", "--water-level", "0.18") == 0
    assert {p: p.stat().st_mtime_ns for p in tables.glob("*.npz")}.keys() == written.keys()  # read, none added
    ahead = [json.loads((tmp_path / name / "out" / "survey_summary.json").read_text())["matched_ahead"]
             for name in ("off", "first", "second")]
    assert ahead == [False, False, True]
    surveys = [load_survey(tmp_path / name / "out" / "survey.npz") for name in ("off", "first", "second")]
    for other in surveys[1:]:
        for field in ("points", "cov", "pixels", "submerged"):
            assert np.array_equal(getattr(other, field), getattr(surveys[0], field)), field
    # Another water level is another rectification: its tables are computed and kept beside the first ones.
    assert _run(root, tmp_path / "third", "--water-level", "0.17") == 0
    assert len(list(tables.glob("*.npz"))) == 2 * len(written)
