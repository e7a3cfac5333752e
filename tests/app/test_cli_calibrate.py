import shutil
from pathlib import Path

import numpy as np

from jaxstereo._app.cli import main
from jaxstereo._calibration.rig import load_rig

DATA = Path(__file__).parents[1] / "data" / "opencv-stereo-chessboard"


def _args(tmp_path, left=None, right=None, board="chessboard:9x6:0.025", origin_left=None, origin_right=None):
    return ["calibrate", "--left", left or str(DATA / "left*.jpg"), "--right", right or str(DATA / "right*.jpg"),
            "--board", board, "--origin-left", origin_left or str(DATA / "left01.jpg"),
            "--origin-right", origin_right or str(DATA / "right01.jpg"), "-o", str(tmp_path / "out" / "rig.json")]


def test_calibrate_command_writes_rig_and_figure(tmp_path, capsys):
    assert main(_args(tmp_path)) == 0
    out = capsys.readouterr().out
    assert "RMS left / right / stereo (px)" in out and "baseline (m)" in out
    rig = load_rig(tmp_path / "out" / "rig.json")
    assert rig.calibration["rms_stereo_px"] <= 0.5
    assert abs(rig.baseline_m - rig.calibration["baseline_m"]) < 1e-6
    # Z up: both cameras above the origin board.
    assert float(rig.left.center[2]) > 0.2 and float(rig.right.center[2]) > 0.2
    assert (tmp_path / "out" / "rig_errors.png").read_bytes()[:4] == b"\x89PNG"


def _one_line_error(capsys, code, pattern, tmp_path):
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert len(err.splitlines()) == 1, err
    assert pattern in err, err
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_calibrate_bad_input(tmp_path, capsys):
    code = main(_args(tmp_path, left=str(tmp_path / "nothing*.png")))
    _one_line_error(capsys, code, "no left images match", tmp_path)

    code = main(_args(tmp_path, board="chessboard:9x6"))
    _one_line_error(capsys, code, "does not parse", tmp_path)

    broken = tmp_path / "broken"
    broken.mkdir()
    for p in sorted(DATA.glob("left*.jpg"))[:4]:
        shutil.copy(p, broken / p.name)
    (broken / "left99.jpg").write_bytes(b"")
    code = main(_args(tmp_path, left=str(broken / "left*.jpg"), right=str(DATA / "right0[1-5].jpg")))
    _one_line_error(capsys, code, "is empty (0 bytes)", tmp_path)

    (broken / "left99.jpg").write_bytes((DATA / "left02.jpg").read_bytes()[:500])
    code = main(_args(tmp_path, left=str(broken / "left*.jpg"), right=str(DATA / "right0[1-5].jpg")))
    _one_line_error(capsys, code, "cannot be read", tmp_path)

    import cv2

    small = tmp_path / "small"
    small.mkdir()
    for p in sorted(DATA.glob("left0[1-4].jpg")):
        shutil.copy(p, small / p.name)
    img = cv2.imread(str(DATA / "left05.jpg"))
    cv2.imwrite(str(small / "left05.jpg"), cv2.resize(img, (320, 240)))
    code = main(_args(tmp_path, left=str(small / "left*.jpg"), right=str(DATA / "right0[1-5].jpg")))
    _one_line_error(capsys, code, "must have the same size", tmp_path)

    code = main(_args(tmp_path, right=str(DATA / "right0[1-3].jpg")))
    _one_line_error(capsys, code, "pairs must match", tmp_path)

    blank = tmp_path / "blank"
    blank.mkdir()
    for side in ("left", "right"):
        for k in range(4):
            cv2.imwrite(str(blank / f"{side}{k}.png"), np.full((480, 640), 128, np.uint8))
    code = main(_args(tmp_path, left=str(blank / "left*.png"), right=str(blank / "right*.png")))
    _one_line_error(capsys, code, "was found in only 0 of", tmp_path)

    code = main(_args(tmp_path, origin_left=str(blank / "left0.png")))
    _one_line_error(capsys, code, "no board chessboard:9x6:0.025 found in origin image", tmp_path)


def test_a_pair_left_out_is_named_by_the_image_without_a_board(tmp_path, capsys):
    import cv2

    folder = tmp_path / "views"
    folder.mkdir()
    for p in DATA.glob("*.jpg"):
        shutil.copy(p, folder / p.name)
    cv2.imwrite(str(folder / "right03.jpg"), np.full((480, 640, 3), 128, np.uint8))
    assert main(_args(tmp_path, left=str(folder / "left*.jpg"), right=str(folder / "right*.jpg"))) == 0
    assert "pairs left out: right03.jpg (no board)" in capsys.readouterr().out
    assert load_rig(tmp_path / "out" / "rig.json").calibration["pairs_left_out"] == ["right03.jpg (no board)"]
