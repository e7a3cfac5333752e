"""Every command fed broken input: one line on stderr naming the problem, a non-zero exit, nothing written.

Broken inputs: truncated and zero-byte images, a wrong-size pair, a rig JSON with a missing or NaN field,
a water level above the cameras, an all-black image, manifests pointing to missing files, corrupt or
NaN-holding surveys. Errors are read at the file-descriptor level (capfd), so messages C libraries
print (libpng) would be caught too.
"""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import jaxstereo as js
from jaxstereo._app.cli import build_parser, main
from jaxstereo._app.images import write_image
from jaxstereo._calibration.rig import Rig, save_rig
from jaxstereo._stereo.survey import Survey, save_survey
from jaxstereo._synthetic.flume_rig import RigSpec, flume_rig
from jaxstereo._synthetic.render import RenderOptions, render_view
from jaxstereo._synthetic.scenes import Extent, SlopingBoard, build_scene

SIZE = (432, 288)
LEVEL = 0.18


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """Good inputs (a rendered wet pair, its rig, surveys) and every kind of broken one, in one folder."""
    root = tmp_path_factory.mktemp("robustness")
    left, right = flume_rig(RigSpec(image_size=SIZE, water_level_m=LEVEL))
    scene = build_scene(SlopingBoard(extent=Extent(spacing=2e-3)))
    for name, cam in (("left.png", left), ("right.png", right)):
        image = render_view(cam, scene.heightfield, js.Interface(LEVEL), RenderOptions(fine_step_m=2e-3)).image
        write_image(root / name, image)
    save_rig(Rig(left, right), root / "rig.json")
    (root / "empty.png").write_bytes(b"")
    (root / "truncated.png").write_bytes((root / "left.png").read_bytes()[:400])
    write_image(root / "small.png", np.full((200, 300, 3), 128, np.uint8))
    write_image(root / "black.png", np.zeros((SIZE[1], SIZE[0], 3), np.uint8))
    data = json.loads((root / "rig.json").read_text())
    del data["right"]["t"]
    (root / "rig_missing.json").write_text(json.dumps(data))
    data = json.loads((root / "rig.json").read_text())
    data["left"]["fx"] = float("nan")
    (root / "rig_nan.json").write_text(json.dumps(data))
    rng = np.random.default_rng(0)
    xy = rng.uniform([-0.3, -0.15], [0.5, 0.15], (20000, 2))
    points = np.column_stack([xy, np.clip((xy[:, 0] + 0.3) / 2, 0, 0.31)])
    for name, pts in (("survey.npz", points), ("elsewhere.npz", points + [5.0, 0, 0])):
        n = pts.shape[0]
        save_survey(Survey(pts, np.zeros((n, 3), np.uint8), np.zeros((n, 2)), np.zeros(n, bool), "{}", "exact", LEVEL),
                    root / name)
    nan_points = points.copy()
    nan_points[::100, 2] = np.nan
    np.savez(root / "survey_nan.npz", points=nan_points, colors=np.zeros((20000, 3), np.uint8),
             pixels=np.zeros((20000, 2)), submerged=np.zeros(20000, bool))
    (root / "survey_zero.npz").write_bytes(b"")
    (root / "survey_truncated.npz").write_bytes((root / "survey.npz").read_bytes()[:500])
    return root


def _check(capfd, code, text, out):
    """One stderr line containing `text`, a non-zero exit, and `out` not written (absent or empty)."""
    err = capfd.readouterr().err.strip()
    assert code != 0, err
    assert len(err.splitlines()) == 1 and text in err, err
    assert err.startswith("jaxstereo ") and "Traceback" not in err
    assert not out.exists() or (out.is_dir() and not any(out.iterdir())), sorted(out.rglob("*"))


def _image_cases(f):
    """(left, right, rig, expected text) with the good pair otherwise."""
    good = (f / "left.png", f / "right.png", f / "rig.json")
    return [
        ((f / "truncated.png", *good[1:]), "cannot be read (corrupt, truncated or not an image)"),
        ((f / "empty.png", *good[1:]), "is empty (0 bytes)"),
        ((good[0], f / "small.png", good[2]), "small.png' is 300x200 but the rig's cameras are 432x288"),
        ((good[0], f / "black.png", good[2]), "is uniform (every pixel 0): no texture to match"),
        ((f / "nothing.png", *good[1:]), "does not exist"),
        ((*good[:2], f / "rig_missing.json"), "field right.t is missing"),
        ((*good[:2], f / "rig_nan.json"), "field left.fx must be a finite number"),
    ]


def test_reconstruct_broken_input(files, tmp_path, capfd):
    out = tmp_path / "out"
    for (left, right, rig), text in _image_cases(files):
        code = main(["reconstruct", str(left), str(right), "--rig", str(rig), "--water-level", str(LEVEL),
                     "-o", str(out / "s.npz")])
        _check(capfd, code, text, out)
    code = main(["reconstruct", str(files / "left.png"), str(files / "right.png"), "--rig", str(files / "rig.json"),
                 "--water-level", "3.0", "-o", str(out / "s.npz")])
    _check(capfd, code, "below the water plane", out)
    code = main(["reconstruct", str(files / "left.png"), str(files / "right.png"), "--rig", str(files / "rig.json"),
                 "--water-level", str(LEVEL), "--water-level-std", "-1", "-o", str(out / "s.npz")])
    _check(capfd, code, "water_level_std_m must be a finite number >= 0", out)
    code = main(["reconstruct", str(files / "left.png"), str(files / "right.png"), "--rig", str(files / "rig.json"),
                 "--water-level", str(LEVEL), "--photometric-ratio", "-2", "-o", str(out / "s.npz")])
    _check(capfd, code, "--photometric-ratio must be >= 0", out)


def test_reconstruct_failing_after_its_points_were_written_leaves_nothing(files, tmp_path, capfd, monkeypatch):
    """The command writes the survey's points while their errors are propagated (`SurveyWriter`); a failure
    there leaves neither the survey nor its temporary file, nor a preview."""
    from jaxstereo._stereo import reconstruct

    def fail(*args, **kwargs):
        raise js.JaxStereoError("the errors could not be propagated")

    monkeypatch.setattr(reconstruct, "_point_errors", fail)
    out = tmp_path / "out"
    code = main(["reconstruct", str(files / "left.png"), str(files / "right.png"), "--rig", str(files / "rig.json"),
                 "--water-level", str(LEVEL), "-o", str(out / "s.npz")])
    _check(capfd, code, "the errors could not be propagated", out)


def test_refine_broken_input(files, tmp_path, capfd):
    out = tmp_path / "out"
    for (left, right, rig), text in _image_cases(files):
        code = main(["refine", str(left), str(right), "--rig", str(rig), "--water-level-guess", "0.17",
                     "-o", str(out / "rig.json")])
        _check(capfd, code, text, out)
    code = main(["refine", str(files / "left.png"), str(files / "right.png"), "--rig", str(files / "rig.json"),
                 "--water-level-guess", "3.0", "-o", str(out / "rig.json")])
    _check(capfd, code, "below the water plane", out)
    code = main(["refine", str(files / "left.png"), str(files / "right.png"), "--rig", str(files / "rig.json"),
                 "--water-level-guess", "0.17", "--control", "floor", "--floor-x", "4", "5", "-o", str(out / "rig.json")])
    _check(capfd, code, "no correspondence lies in the floor region x 4.000 to 5.000 m", out)  # out of view
    for tolerance in ("0", "-0.001", "nan"):
        code = main(["refine", str(files / "left.png"), str(files / "right.png"), "--rig", str(files / "rig.json"),
                     "--water-level-guess", "0.17", "--level-tolerance", tolerance, "-o", str(out / "rig.json")])
        _check(capfd, code, "--level-tolerance must be a positive number of metres, got " + tolerance, out)
    for count in ("0", "-5"):
        code = main(["refine", str(files / "left.png"), str(files / "right.png"), "--rig", str(files / "rig.json"),
                     "--water-level-guess", "0.17", "--max-points", count, "-o", str(out / "rig.json")])
        _check(capfd, code, "--max-points must be a positive number of correspondences, got " + count, out)


def test_calibrate_broken_input(files, tmp_path, capfd):
    out = tmp_path / "out"
    board = "chessboard:9x6:0.03"

    def run(left_dir, right_dir):
        return main(["calibrate", "--left", str(left_dir / "*.png"), "--right", str(right_dir / "*.png"),
                     "--board", board, "--origin-left", str(left_dir / "a.png"),
                     "--origin-right", str(right_dir / "a.png"), "-o", str(out / "rig.json")])

    def folder(name, images):
        path = tmp_path / name
        path.mkdir()
        for i, source in enumerate(images):
            shutil.copyfile(source, path / f"{'abc'[i]}.png")
        return path

    f = files
    blacks = folder("blacks", [f / "black.png"] * 3)
    cases = [
        (folder("trunc", [f / "black.png", f / "truncated.png", f / "black.png"]), blacks, "cannot be read"),
        (folder("zero", [f / "black.png", f / "black.png", f / "empty.png"]), blacks, "is empty (0 bytes)"),
        (blacks, folder("small", [f / "small.png"] * 3), "left images are 432x288 but right images are 300x200"),
        (blacks, blacks, "board chessboard:9x6:0.03"),  # all black: no board anywhere
    ]
    for left_dir, right_dir, text in cases:
        _check(capfd, run(left_dir, right_dir), text, out)
    _check(capfd, run(tmp_path / "nowhere", blacks), "no left images match", out)


def test_grid_and_damage_broken_input(files, tmp_path, capfd):
    out = tmp_path / "out"
    for name, text in (("survey_zero.npz", "cannot be read"), ("survey_truncated.npz", "cannot be read"),
                       ("survey_nan.npz", "holds 200 point(s) with NaN"), ("nothing.npz", "does not exist"),
                       ("left.png", "cannot be read")):
        _check(capfd, main(["grid", str(files / name), "-o", str(out / "dem.npz")]), text, out)
        code = main(["damage", str(files / "survey.npz"), str(files / name), "--dn50", "0.036", "--slope", "1:2",
                     "--swl", str(LEVEL), "--slope-origin", "-0.45", "0", "-o", str(out / "report")])
        _check(capfd, code, text, out)
    code = main(["damage", str(files / "survey.npz"), str(files / "elsewhere.npz"), "--dn50", "0.036", "--slope", "2",
                 "--swl", str(LEVEL), "--slope-origin", "-0.45", "0", "-o", str(out / "report")])
    _check(capfd, code, "do not overlap", out)
    code = main(["grid", str(files / "survey.npz"), "--spacing", "-1", "-o", str(out / "dem.npz")])
    _check(capfd, code, "--spacing must be positive", out)


def test_demo_and_incidence_report_broken_input(tmp_path, capfd):
    out = tmp_path / "out"
    (tmp_path / "a_file").write_text("x")
    _check(capfd, main(["demo", "-o", str(tmp_path / "a_file")]), "is a file, not a folder", out)
    for option, value, text in (("--height", "-2", "height_m must be positive"), ("--n-water", "0.9", "n_water"),
                                ("--step-deg", "0", "--step-deg must be positive"),
                                ("--disparity-noise", "0", "disparity_noise_px must be positive"),
                                ("--sigma-depths", "-0.1", "sigma_depths_m must be positive depths")):
        code = main(["incidence-report", option, value, "-o", str(out / "inc.png")])
        _check(capfd, code, text, out)


def _manifest(path, rig, pairs, extra=""):
    lines = [f'rig = "{rig}"', f"water_level = {LEVEL}", extra,
             "[damage]", "dn50 = 0.036", 'slope = "1:2"', f"swl = {LEVEL}", "slope_origin = [-0.45, 0.0]"]
    for i, (left, right) in enumerate(pairs):
        lines += ["[[pair]]", 'test = "T1"', f'stage = "S{i}"', f'left = "{left}"', f'right = "{right}"']
    path.write_text("\n".join(lines) + "\n")
    return path


def test_batch_broken_manifest_is_fatal_before_any_output(files, tmp_path, capfd):
    out = tmp_path / "out"
    good = (files / "left.png", files / "right.png")
    cases = [
        (_manifest(tmp_path / "m1.toml", files / "rig.json", [good, (files / "gone_L.png", files / "gone_R.png")]),
         "points to 2 missing image file(s)"),
        (_manifest(tmp_path / "m2.toml", files / "rig_missing.json", [good]), "field right.t is missing"),
        (_manifest(tmp_path / "m3.toml", files / "rig_nan.json", [good]), "field left.fx must be a finite number"),
        (_manifest(tmp_path / "m4.toml", files / "rig.json", [good], "model = \"magic\""), "model must be exact"),
        (_manifest(tmp_path / "m5.toml", files / "nothing.json", [good]), "rig file"),
        (_manifest(tmp_path / "m6.toml", files / "rig.json", [good]).with_name("absent.toml"), "does not exist"),
    ]
    (tmp_path / "m8.toml").write_text("rig = [unclosed\n")
    cases += [(tmp_path / "m8.toml", "not valid TOML")]
    for manifest, text in cases:
        _check(capfd, main(["batch", str(manifest), "-o", str(out)]), text, out)
    above = _manifest(tmp_path / "m9.toml", files / "rig.json", [good])
    above.write_text(above.read_text().replace(f"water_level = {LEVEL}", "water_level = 3.0"))
    _check(capfd, main(["batch", str(above), "-o", str(out)]), "pair T1/S0: left camera centre", out)


def test_batch_broken_pairs_are_logged_and_leave_no_output(files, tmp_path, capfd):
    """Broken pairs inside a campaign do not stop it: each is logged, nothing is written for it, exit 1."""
    out = tmp_path / "out"
    f = files
    pairs = [(f / "left.png", f / "right.png"), (f / "truncated.png", f / "right.png"),
             (f / "empty.png", f / "right.png"), (f / "left.png", f / "small.png"), (f / "black.png", f / "right.png")]
    manifest = _manifest(tmp_path / "m.toml", f / "rig.json", pairs)
    code = main(["batch", str(manifest), "-o", str(out)])
    err = capfd.readouterr().err
    assert code == 1
    errors = [line for line in err.splitlines() if "error" in line]
    assert len(errors) == 1 and errors[0].startswith("jaxstereo batch: error: 4 of 5 pairs failed"), err
    for text in ("T1/S1: image", "cannot be read", "T1/S2: image", "is empty (0 bytes)",
                 "small.png' is 300x200 but the rig's cameras are 432x288", "T1/S4: left image", "is uniform"):
        assert text in errors[0], (text, errors[0])
    assert (out / "T1" / "S0" / "result.json").is_file()
    for stage in ("S1", "S2", "S3", "S4"):
        assert not (out / "T1" / stage).exists() or not any((out / "T1" / stage).iterdir())


def test_every_command_is_covered():
    """The suite above exercises every command the parser knows."""
    commands = set(build_parser()._subparsers._group_actions[0].choices)
    source = Path(__file__).read_text()
    assert commands == {"demo", "incidence-report", "calibrate", "reconstruct", "refine", "grid", "damage", "batch"}
    for command in commands:
        assert f'main(["{command}"' in source, command


def test_entry_point_prints_one_line_for_a_truncated_image(files, tmp_path):
    """The real executable (a fresh process): libpng's own complaint must not reach the user either."""
    proc = subprocess.run([sys.executable, "-m", "jaxstereo", "reconstruct", str(files / "truncated.png"),
                           str(files / "right.png"), "--rig", str(files / "rig.json"), "-o", str(tmp_path / "s.npz")],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        f"jaxstereo reconstruct: error: image {str(files / 'truncated.png')!r} cannot be read "
        "(corrupt, truncated or not an image)"]
    assert not (tmp_path / "s.npz").exists()


def test_entry_point_finishes_its_files_when_the_reader_of_its_output_goes_away(tmp_path):
    """`jaxstereo incidence-report | head -1`: the report's table is printed before the figure is drawn; with the
    pipe's reader gone the command still writes the figure and ends as it would have, without a word."""
    figure = tmp_path / "incidence.png"
    proc = subprocess.Popen([sys.executable, "-m", "jaxstereo", "incidence-report", "-o", str(figure)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()  # the reader goes away before the command prints anything
    with proc.stderr:
        stderr = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 0, stderr
    assert stderr == ""
    assert figure.read_bytes()[:4] == b"\x89PNG"
