"""Chessboard corners from the board's edge lines, against the exact corners: the project's own renderer on a
realistic rig (distortion, a tilted and turned camera, JPEG), and the POV-Ray flume's origin boards, whose
corners follow from its truth file. OpenCV's `findChessboardCornersSB` (accuracy mode) is the reference."""

import json
import os
from pathlib import Path

import cv2
import jax.numpy as jnp
import numpy as np
import pytest

import jaxstereo as js
from jaxstereo._calibration.boards import BoardSpec
from jaxstereo._calibration.corner_edges import edge_blur_px, refine_chessboard_corners
from jaxstereo._calibration.detect import _canonical_chessboard_order
from jaxstereo._synthetic.board_render import board_poses, render_board
from jaxstereo._synthetic.flume_rig import flume_rig, jpeg, realistic_rig_spec

POVRAY = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "povray-flume-dev"


def _opencv_corners(grey, board):
    found, corners = cv2.findChessboardCornersSB(grey, (board.cols, board.rows),
                                                 flags=cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY)
    assert found
    return _canonical_chessboard_order(corners.reshape(-1, 2).astype(float), board.cols, board.rows)


def _rms(error):
    return float(np.sqrt(np.mean(np.sum(error**2, axis=1))))


@pytest.fixture(scope="module")
def rendered_views():
    """Four views of a 9x6 board by a camera tilted and turned by fractions of a degree, with a 35 mm lens's
    distortion, saved as JPEG (quality 95); the exact corners are the camera's projection of the board's."""
    camera, _ = flume_rig(realistic_rig_spec(image_size=(864, 576)))
    board = BoardSpec.parse("chessboard:9x6:0.06")
    views = []
    for k, pose in enumerate(board_poses((camera,), board, 4, seed=5, max_tilt_deg=45.0)):
        grey = jpeg(render_board(camera, board, pose, seed=k))
        world = board.corners @ np.asarray(pose.R).T + np.asarray(pose.t)
        exact = np.asarray(camera.project(jnp.asarray(world)))
        found = _opencv_corners(grey, board)
        if np.linalg.norm(exact[0] - found[0]) > np.linalg.norm(exact[-1] - found[0]):
            exact = exact[::-1]  # the detector's order starts at the other end of the board
        views.append((grey, found, exact))
    return board, views


@pytest.mark.parametrize("blur_px", [0.0, 1.5])
def test_edge_corners_are_several_times_closer_to_the_truth_than_opencvs(rendered_views, blur_px):
    board, views = rendered_views
    ours, opencv = [], []
    for grey, _, exact in views:
        if blur_px:
            grey = cv2.GaussianBlur(grey, (0, 0), blur_px)  # a lens or a focus a little off
        found = _opencv_corners(grey, board)
        refined, mask = refine_chessboard_corners(grey, found, board.rows, board.cols)
        assert mask.all()
        ours.append(refined - exact)
        opencv.append(found - exact)
    ours, opencv = np.concatenate(ours), np.concatenate(opencv)
    print(f"blur {blur_px} px: edges {_rms(ours):.4f} px, findChessboardCornersSB {_rms(opencv):.4f} px")
    # measured: 0.0073 / 0.0072 px against OpenCV's 0.041 / 0.043 px
    assert _rms(ours) <= 0.015
    assert _rms(ours) <= 0.4 * _rms(opencv)


def test_detect_board_returns_the_edge_corners(rendered_views):
    board, views = rendered_views
    grey, found, exact = views[0]
    detection = js.detect_board(grey, board)
    expected, _ = refine_chessboard_corners(grey, found, board.rows, board.cols)
    np.testing.assert_allclose(detection.pixels, expected, atol=1e-9)
    assert _rms(detection.pixels - exact) <= 0.015


def test_edge_blur_follows_the_image_blur(rendered_views):
    board, views = rendered_views
    grey, found, _ = views[0]
    grid = found.reshape(board.rows, board.cols, 2)
    widths = [edge_blur_px(cv2.GaussianBlur(grey, (0, 0), s) if s else grey, grid) for s in (0.0, 1.0, 2.0, 3.0)]
    assert np.all(np.diff(widths) > 0), widths
    # Beyond the render's own blur, the measured width grows as the added one (the derivative of a Gaussian
    # edge has the blur's standard deviation; the part under a tenth of its peak is left out, hence 0.8-1).
    assert 0.8 * 2.0 <= widths[3] - widths[1] <= 1.05 * 2.0, widths


def test_a_corner_whose_edges_are_hidden_keeps_the_detectors_position(rendered_views):
    board, views = rendered_views
    grey, found, _ = views[0]
    hidden = grey.copy()
    x, y = np.round(found[20]).astype(int)
    side = int(np.ceil(np.max(np.linalg.norm(found[[11, 19, 21, 29]] - found[20], axis=1))))
    hidden[y - side:y + side + 1, x - side:x + side + 1] = 128  # a smudge over one corner and its four edges
    refined, mask = refine_chessboard_corners(hidden, found, board.rows, board.cols)
    assert not mask[20]
    np.testing.assert_array_equal(refined[20], found[20])
    # Its neighbours still have an edge on their other side; the corners away from the smudge are all refined.
    far = np.max(np.abs(found - found[20]), axis=1) > 2 * side
    assert mask[far].all() and far.sum() > 20


@pytest.mark.skipif(not POVRAY.is_dir() and os.environ.get("CI") != "true",
                    reason=f"the development flume is not at {POVRAY}")
@pytest.mark.parametrize("rig, name, shift", [("main", "origin", (0.0, 0.0)),
                                             ("oblique", "origin_oblique", (0.2, 0.04))])
def test_povray_origin_board_corners_against_its_truth(rig, name, shift):
    """The POV-Ray flume's origin boards lie on z = 0 at the truth file's `origin` (the oblique one moved by
    `shift`, metres, as its README says): their exact corners are the true cameras' projections."""
    truth = json.loads((POVRAY / "truth.json").read_text())
    board = BoardSpec.parse(f"chessboard:9x6:{truth['square']:g}")
    K = np.asarray(truth["K"], float)
    for side in "LR":
        grey = cv2.imread(str(POVRAY / f"{name}_{side}.jpg"), cv2.IMREAD_GRAYSCALE)
        found = _opencv_corners(grey, board)
        camera = truth["rigs"][rig][side]
        # The board's axes lie along the truth's x and y, each either way: the placement whose projection
        # meets the detected corners.
        candidates = []
        for axes in ([[1, 0], [0, 1]], [[0, 1], [1, 0]]):
            for signs in ([1, 1], [1, -1], [-1, 1], [-1, -1]):
                offset = board.corners[:, :2] @ (np.asarray(axes) * signs)
                world = np.c_[np.asarray(truth["origin"][:2]) + shift + offset, np.zeros(len(offset))]
                projected = (K @ (np.asarray(camera["R"]) @ world.T + np.asarray(camera["t"])[:, None])).T
                projected = projected[:, :2] / projected[:, 2:]
                order = np.argmin(np.linalg.norm(found[:, None] - projected[None], axis=-1), axis=1)
                candidates.append((_rms(projected[order] - found), projected[order]))
        error, exact = min(candidates, key=lambda c: c[0])
        assert error < 0.5
        refined, mask = refine_chessboard_corners(grey, found, board.rows, board.cols)
        print(f"{name}_{side}: edges {_rms(refined - exact):.4f} px, findChessboardCornersSB "
              f"{_rms(found - exact):.4f} px")
        # measured: main 0.025 / 0.033 px (OpenCV 0.067 / 0.10), oblique 0.011 / 0.011 px (OpenCV 0.029 / 0.025)
        assert mask.all()
        assert _rms(refined - exact) <= 0.04
        assert _rms(refined - exact) <= 0.6 * _rms(found - exact)
