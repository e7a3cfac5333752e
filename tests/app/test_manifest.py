"""Campaign manifests: pair tables, folders named by convention, ordering, and clear errors."""

import json

import pytest

import jaxstereo as js
from jaxstereo._app.manifest import load_manifest


@pytest.fixture
def folder(tmp_path):
    (tmp_path / "rig.json").write_text(json.dumps({}))
    pairs = tmp_path / "pairs"
    pairs.mkdir()
    for test in ("A2", "A10"):
        for stage in ("after", "before", "mid"):
            for side in "LR":
                (pairs / f"{test}_{stage}_{side}.png").write_bytes(b"x")
    (pairs / "notes.txt").write_text("ignored")
    return tmp_path


def _write(folder, text):
    path = folder / "m.toml"
    path.write_text('rig = "rig.json"\n' + text)
    return path


def test_folder_by_convention_with_stage_order(folder):
    m = load_manifest(_write(folder, 'pairs = "pairs"\nstages = ["before", "mid", "after"]\nwater_level = 0.2\n'))
    assert [(p.test, p.stage, p.reference) for p in m.pairs] == [
        ("A2", "before", True), ("A2", "mid", False), ("A2", "after", False),
        ("A10", "before", True), ("A10", "mid", False), ("A10", "after", False)]  # tests in natural order
    assert m.pairs[0].left == (folder / "pairs" / "A2_before_L.png").resolve()
    assert all(p.water_level == 0.2 for p in m.pairs)
    assert m.output == (folder / "m-out").resolve() and m.spacing == 0.005 and m.damage is None


def test_pair_tables_reference_and_overrides(folder):
    text = "".join(f'[[pair]]\ntest = "T"\nstage = "{s}"\nleft = "pairs/A2_{s}_L.png"\nright = "pairs/A2_{s}_R.png"\n'
                   + ('reference = true\nwater_level = 0.25\n' if s == "mid" else "") for s in ("before", "mid", "after"))
    m = load_manifest(_write(folder, "[damage]\ndn50 = 0.036\nslope = 2\nswl = 0.158\nslope_origin = [0.1, 0.0]\n"
                                     "stretch = [-0.2, 0.2]\nactive_zone = [5, 3]\n" + text))
    assert [p.stage for p in m.pairs] == ["mid", "before", "after"]  # the reference first
    assert m.pairs[0].water_level == 0.25 and m.pairs[1].water_level is None
    assert m.damage.dn50 == 0.036 and m.damage.slope == "2" and m.damage.slope_origin == (0.1, 0.0)
    assert m.damage.stretch == (-0.2, 0.2) and m.damage.active_zone == (5.0, 3.0) and not m.damage.fit_slope


@pytest.mark.parametrize("text, message", [
    ('pairs = "nowhere"\n', "pairs folder"),
    ('pairs = "pairs"\nspacing = -1\n', "spacing must be positive"),
    ('pairs = "pairs"\ncolour = 1\n', "unknown key(s) colour"),
    ('pairs = "pairs"\n[damage]\ndn50 = 0.03\nslope = "steep"\nswl = 0.1\n', "[damage] slope 'steep' does not parse"),
    ('pairs = "pairs"\n[damage]\ndn50 = 0.03\n', "[damage] needs slope"),
    ('pairs = "pairs"\n[damage]\ndn50 = 0.03\nslope = 2\nswl = 0.1\n', "exactly one of slope_origin"),
    ('pairs = "pairs"\n[damage]\ndn50 = 0.03\nslope = 2\nswl = 0.1\nslope_origin = [0, 0]\nfit_slope = true\n',
     "exactly one of slope_origin"),
    ('pairs = "pairs"\n[damage]\ndn50 = 0.03\nslope = 2\nswl = 0.1\nfit_slope = true\nstretch = [1]\n',
     "stretch must be a list of two numbers"),
    ('[[pair]]\ntest = "T"\nstage = "I"\nleft = "a.png"\nright = "b.png"\n' * 2, "listed twice"),
    ('[[pair]]\ntest = "T/1"\nstage = "I"\nleft = "a.png"\nright = "b.png"\n', "may hold only letters"),
    ('[[pair]]\ntest = "T"\nstage = "I"\nleft = "a.png"\n', "needs right"),
    ("", "lists no pairs"),
    ('z_range = [0.4, 0.1]\npairs = "pairs"\n', "ZMIN < ZMAX"),
    ('water_level = nan\npairs = "pairs"\n', "water_level must be a finite number"),
])
def test_manifest_errors_name_the_problem(folder, text, message):
    with pytest.raises(js.JaxStereoError, match="manifest .*m.toml") as err:
        load_manifest(_write(folder, text))
    assert message in str(err.value)


def test_incomplete_pair_in_folder(folder):
    (folder / "pairs" / "A2_mid_R.png").unlink()
    with pytest.raises(js.JaxStereoError, match="A2_mid_R is missing"):
        load_manifest(_write(folder, 'pairs = "pairs"\n'))
