import glob
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

import jaxstereo as js
from jaxstereo._app.images import read_images_same_size
from jaxstereo._calibration.boards import BoardSpec
from jaxstereo._calibration.calibration import align_chessboard_order, calibrate_stereo, detect_all, world_frame_rig
from jaxstereo._synthetic.board_render import board_poses, render_board
from jaxstereo._synthetic.flume_rig import RigSpec, flume_rig

DATA = Path(__file__).parents[1] / "data" / "opencv-stereo-chessboard"


@pytest.fixture(scope="module")
def real_calibration():
    board = BoardSpec.parse("chessboard:9x6:0.025")
    left, size = read_images_same_size(sorted(glob.glob(str(DATA / "left*.jpg"))))
    right, _ = read_images_same_size(sorted(glob.glob(str(DATA / "right*.jpg"))))
    dl, dr = detect_all(left, board), detect_all(right, board)
    return board, dl, dr, calibrate_stereo(dl, dr, board, size)


def test_detection_on_threads_equals_one_image_at_a_time_in_order():
    """`detect_all` searches on threads; its detections are the serial ones, in the images' order, with None
    where no board is found, and `on_each` sees them in that order."""
    board = BoardSpec.parse("chessboard:9x6:0.025")
    images, _ = read_images_same_size(sorted(glob.glob(str(DATA / "left*.jpg")))[:5])
    images.insert(2, np.full_like(images[0], 128))  # a blank view: no board
    seen = []
    threaded = detect_all(images, board, on_each=lambda k, found: seen.append((k, found)), workers=3)
    serial = [js.detect_board(image, board) for image in images]
    assert [k for k, _ in seen] == list(range(len(images))) and [f for _, f in seen] == threaded
    assert threaded[2] is None and serial[2] is None
    for a, b in zip(threaded, serial):
        if b is not None:
            np.testing.assert_array_equal(a.ids, b.ids)
            np.testing.assert_array_equal(a.pixels, b.pixels)


def test_real_photographs_stereo_rms(real_calibration):
    _, _, _, stereo = real_calibration
    assert len(stereo.pairs) >= 12
    assert stereo.rms_px <= 0.5
    assert stereo.left.rms_px <= 0.5 and stereo.right.rms_px <= 0.5


def test_real_photographs_triangulated_squares_are_25mm(real_calibration):
    board, dl, dr, stereo = real_calibration
    rig, _ = world_frame_rig(stereo, board, dl[0], dr[0], refine=False)
    gaps = []
    for i in stereo.pairs:
        a = dl[i]
        b = align_chessboard_order(a, dr[i])
        o1, d1 = rig.left.backproject(jnp.asarray(a.pixels))
        o2, d2 = rig.right.backproject(jnp.asarray(b.pixels))
        pts, _ = js.triangulate_rays(o1, d1, o2, d2)
        grid = np.asarray(pts).reshape(board.rows, board.cols, 3)
        gaps.append(np.linalg.norm(np.diff(grid, axis=1), axis=-1).ravel())
        gaps.append(np.linalg.norm(np.diff(grid, axis=0), axis=-1).ravel())
    gaps = np.concatenate(gaps)
    assert abs(np.median(gaps) - 0.025) <= 0.0002, np.median(gaps)


def _synthetic(board_text, n_views=12, size=(864, 576), seed=3):
    spec = RigSpec(image_size=size, water_level_m=0.18)
    left, right = flume_rig(spec)
    board = BoardSpec.parse(board_text)
    poses = board_poses((left, right), board, n_views, seed=seed, max_tilt_deg=45.0)
    dl = detect_all([render_board(left, board, p, seed=2 * k) for k, p in enumerate(poses)], board)
    dr = detect_all([render_board(right, board, p, seed=2 * k + 1) for k, p in enumerate(poses)], board)
    stereo = calibrate_stereo(dl, dr, board, size)
    # The origin board lies flat on the flume floor (z = 0), printed side up, under the rig.
    x0, x1, y0, y1 = board.outline
    origin = js.Pose(jnp.diag(jnp.array([1.0, -1.0, -1.0])), jnp.array([-0.5 * (x0 + x1), 0.5 * (y0 + y1), 0.0]))
    ol = js.detect_board(render_board(left, board, origin, seed=99), board)
    orr = js.detect_board(render_board(right, board, origin, seed=98), board)
    rig, report = world_frame_rig(stereo, board, ol, orr)
    return spec, (left, right), origin, stereo, rig, report


# ChArUco corners are located less precisely than chessboard corners (about 0.08 px against 0.03 px
# here): the ChArUco case uses more views.
@pytest.mark.parametrize("board_text, n_views", [("chessboard:9x6:0.06", 12), ("charuco:8x6:0.075:0.035:4X4_50", 18)])
def test_synthetic_calibration_recovers_the_rig(board_text, n_views):
    spec, truth, origin, stereo, rig, report = _synthetic(board_text, n_views)
    f = spec.focal_px
    for cal, cam in ((stereo.left, truth[0]), (stereo.right, truth[1])):
        assert abs(cal.K[0, 0] / f - 1) < 1e-3 and abs(cal.K[1, 1] / f - 1) < 1e-3
        assert abs(cal.K[0, 2] - float(cam.cx)) < 3 and abs(cal.K[1, 2] - float(cam.cy)) < 3
    assert abs(stereo.baseline_m - spec.baseline_m) < 2e-4
    assert abs(rig.baseline_m - spec.baseline_m) < 2e-4
    # World frame: origin at the board frame's origin, Z up; heights of the cameras above z = 0.
    corner0 = np.asarray(origin.t)
    for cam, true_cam in zip((rig.left, rig.right), truth):
        c = np.asarray(cam.center)
        true_c = np.asarray(true_cam.center) - corner0
        assert c[2] > 0  # Z up: cameras above the board
        assert abs(c[2] - true_c[2]) < 2e-3
        # One planar origin board fixes the lateral position and the frame's tilt less well than the
        # height (a lateral shift trades against a rotation): within 1 cm and 5 mrad.
        np.testing.assert_allclose(c[:2], true_c[:2], atol=1e-2)
        angle = np.linalg.norm(np.asarray(js.so3_log(np.asarray(cam.pose.R) @ np.asarray(true_cam.pose.R).T)))
        assert angle < 5e-3
    assert report["origin_rms_px_after"] <= report["origin_rms_px_before"] + 1e-9
    # The frame's recorded tilt uncertainty covers its tilt error: the angle between the calibrated and the
    # true vertical, seen from the left camera.
    z_cal = np.asarray(rig.left.pose.R)[:, 2]
    z_true = np.asarray(truth[0].pose.R)[:, 2]
    tilt_error = float(np.arccos(np.clip(z_cal @ z_true, -1.0, 1.0)))
    tilt_std = 1e-3 * float(np.hypot(*report["frame_tilt_std_mrad"]))
    print(f"frame tilt error {1e3 * tilt_error:.3f} mrad, recorded std {1e3 * tilt_std:.3f} mrad")
    assert tilt_error <= 3 * tilt_std


def test_board_spec_parse_errors():
    for text in ["chessboard", "chess:9x6:0.025", "chessboard:9by6:0.025", "chessboard:9x6:-1",
                 "chessboard:9x6:abc", "charuco:7x5:0.04:0.05:4X4_50", "charuco:7x5:0.04:0.03:NOPE",
                 "charuco:7x5:0.04"]:
        with pytest.raises(js.JaxStereoError, match="board spec"):
            BoardSpec.parse(text)
    assert str(BoardSpec.parse("charuco:7x5:0.04:0.03:dict_4x4_50")) == "charuco:7x5:0.04:0.03:4X4_50"
