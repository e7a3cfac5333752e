"""The experiments run from the command line and write their tables; the README updater splices them."""

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from experiments.__main__ import main, update_readme


def test_incidence_limit_experiment_and_readme_update(tmp_path):
    assert main(["incidence-limit", "--out", str(tmp_path)]) == 0
    table = (tmp_path / "incidence-limit" / "table.md").read_text()
    row = next(line for line in table.splitlines() if line.startswith("| 0.3 |"))
    assert row.split("|")[2].strip() == "0.405"  # the angular error at 20 deg
    assert (tmp_path / "incidence-limit" / "incidence_limit.png").stat().st_size > 0
    readme = tmp_path / "README.md"
    readme.write_text("# x\n\n## Results\n\n<!-- results:start -->\nSTALE-TABLE\n<!-- results:end -->\n\nafter\n")
    update_readme(tmp_path, readme)
    text = readme.read_text()
    assert "STALE-TABLE" not in text and "| 0.3 | 0.405 |" in text and text.endswith("after\n")


def test_exposed_flume_passes_the_right_images_alone_through_the_other_response(tmp_path):
    """`exposed_rig_data`: the right images' levels as the response says, the left ones as decoded, all as PNG."""
    import json

    import cv2
    import numpy as np

    from experiments.exposed_rig_data import respond, write_exposed

    levels = np.array([[[0, 64, 128], [200, 250, 255]]], np.uint8)  # one image, R G B
    expected = np.rint(255 * (levels / 255.0) ** 1.3 * np.array([0.9, 0.85, 0.8]) + 4)
    assert np.array_equal(respond(levels, (0.9, 0.85, 0.8), 4, 1.3), np.clip(expected, 0, 255))
    assert respond(levels, (1, 1, 1), 0, 1.0).tolist() == levels.tolist()  # the identity
    source = tmp_path / "flume"
    (source / "calib").mkdir(parents=True)
    rng = np.random.default_rng(0)
    for name in ("calib/c_L.jpg", "calib/c_R.jpg", "scene_L.jpg", "scene_R.jpg"):
        cv2.imwrite(str(source / name), rng.integers(0, 256, (12, 16, 3), dtype=np.uint8))
    (source / "truth.json").write_text(json.dumps({"K": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "size": [16, 12]}))
    out = tmp_path / "exposed"
    assert write_exposed(source, out, (0.9, 0.85, 0.8), 4, 1.0) == 2
    assert json.loads((out / "truth.json").read_text())["images"].startswith("png")
    for name in ("calib/c_L", "calib/c_R", "scene_L", "scene_R"):
        decoded = cv2.imread(str(source / f"{name}.jpg"))
        written = cv2.imread(str(out / f"{name}.png"))
        if name.endswith("_R"):
            decoded = respond(decoded[..., ::-1], (0.9, 0.85, 0.8), 4, 1.0)[..., ::-1]
        assert np.array_equal(written, decoded), name


def test_resampled_flume_moves_pixels_as_its_camera_matrix_says(tmp_path):
    """`scaled_rig_data`: a blob's centroid in a resampled image lies where the scaled camera matrix projects the
    point the original matrix put at the blob's centre (pixel centres at whole numbers, both sizes)."""
    import json

    import cv2
    import numpy as np

    from experiments.scaled_rig_data import scaled_matrix, write_scaled

    K = np.array([[400.0, 0.0, 79.5], [0.0, 400.0, 59.5], [0.0, 0.0, 1.0]])
    ray = np.array([0.07, -0.04, 1.0])  # a direction in the camera frame
    u, v = (K @ ray)[:2]
    yy, xx = np.mgrid[0:120, 0:160]
    blob = np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * 3.0**2))
    source = tmp_path / "flume"
    (source / "calib").mkdir(parents=True)
    cv2.imwrite(str(source / "calib" / "c_L.jpg"), np.uint8(np.rint(250 * blob)), [cv2.IMWRITE_JPEG_QUALITY, 100])
    (source / "truth.json").write_text(json.dumps({"K": K.tolist(), "size": [160, 120]}))
    for scale in (0.75, 1.25):
        out = tmp_path / f"x{scale}"
        assert write_scaled(source, out, scale) == 1
        truth = json.loads((out / "truth.json").read_text())
        assert truth["size"] == [round(160 * scale), round(120 * scale)]
        assert np.allclose(truth["K"], scaled_matrix(K, scale))
        image = cv2.imread(str(out / "calib" / "c_L.png"), cv2.IMREAD_GRAYSCALE).astype(float)
        image[image < 10] = 0  # the JPEG's faint ringing off the blob
        rows, cols = np.mgrid[0 : image.shape[0], 0 : image.shape[1]]
        centroid = np.array([(image * cols).sum(), (image * rows).sum()]) / image.sum()
        expected = (np.asarray(truth["K"]) @ ray)[:2]
        assert np.abs(centroid - expected).max() < 0.05, (scale, centroid, expected)
        assert np.abs(centroid - np.array([u, v]) * scale).max() > 0.1  # the half-pixel shift is there to see


@pytest.mark.parametrize("turn", [90, 180])
def test_turned_flume_moves_pixels_as_its_turned_cameras_say(tmp_path, turn):
    """`turned_rig_data`: a blob's centroid in a turned image lies where the turned truth camera (its `R`, `t` and
    `K`) projects the world point the original camera put at the blob's centre."""
    import json

    import cv2
    import numpy as np

    from experiments.turned_rig_data import write_turned

    K = np.array([[400.0, 0.0, 79.5], [0.0, 400.0, 59.5], [0.0, 0.0, 1.0]])
    R, t = np.diag([1.0, -1.0, -1.0]), np.array([-0.1, 0.05, 2.0])  # nadir, 2 m up
    point = np.array([0.13, 0.02, 0.1])  # in the world
    u, v = (K @ (R @ point + t) / (R @ point + t)[2])[:2]
    yy, xx = np.mgrid[0:120, 0:160]
    blob = np.uint8(np.rint(250 * np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * 3.0**2))))
    source = tmp_path / "flume"
    source.mkdir()
    for side in "LR":
        cv2.imwrite(str(source / f"c_{side}.jpg"), blob if side == "L" else blob // 2, [cv2.IMWRITE_JPEG_QUALITY, 100])
    camera = {"R": R.tolist(), "t": t.tolist()}
    (source / "truth.json").write_text(json.dumps({"K": K.tolist(), "size": [160, 120],
                                                   "rigs": {"main": {"L": camera, "R": camera}}}))
    out = tmp_path / f"turned{turn}"
    assert write_turned(source, out, turn) == 2
    truth = json.loads((out / "truth.json").read_text())
    assert truth["size"] == ([120, 160] if turn == 90 else [160, 120])
    side = "L" if turn == 90 else "R"  # a half turn swaps the cameras: the left image came from the right one
    image = cv2.imread(str(out / f"c_{side}.png"), cv2.IMREAD_GRAYSCALE).astype(float)
    assert image.max() > 200  # the bright (left) blob
    image[image < 10] = 0
    rows, cols = np.mgrid[0 : image.shape[0], 0 : image.shape[1]]
    centroid = np.array([(image * cols).sum(), (image * rows).sum()]) / image.sum()
    cam = truth["rigs"]["main"][side]
    X = np.asarray(cam["R"]) @ point + np.asarray(cam["t"])
    expected = (np.asarray(truth["K"]) @ X / X[2])[:2]
    assert np.abs(centroid - expected).max() < 0.05, (turn, centroid, expected)
    assert np.abs(centroid - np.array([u, v])).max() > 10  # the blob did move


def test_distorted_flume_moves_pixels_as_its_lens_says(tmp_path):
    """`distorted_rig_data`: a blob's centroid in a distorted image lies where OpenCV's `projectPoints` puts the ray
    through the blob's centre in the ideal image, through the distorted camera matrix and the lens of its side."""
    import json

    import cv2
    import numpy as np

    from experiments.distorted_rig_data import distorted_matrix, write_distorted

    K = np.array([[400.0, 0.0, 79.5], [0.0, 400.0, 59.5], [0.0, 0.0, 1.0]])
    lenses = {"L": (-0.3, 0.1, 1e-3, -2e-3, 0.0), "R": (0.4, 0.0, 0.0, 0.0, 0.05)}  # barrel; pincushion
    ray = np.array([0.16, 0.11, 1.0])  # a direction in the camera frame
    u, v = (K @ ray)[:2]
    yy, xx = np.mgrid[0:120, 0:160]
    blob = np.uint8(np.rint(250 * np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * 3.0**2))))
    source = tmp_path / "flume"
    (source / "calib").mkdir(parents=True)
    for side in "LR":
        cv2.imwrite(str(source / "calib" / f"c_{side}.jpg"), blob, [cv2.IMWRITE_JPEG_QUALITY, 100])
    (source / "truth.json").write_text(json.dumps({"K": K.tolist(), "size": [160, 120]}))
    out = tmp_path / "distorted"
    assert write_distorted(source, out, lenses, zoom=1.05) == 2
    truth = json.loads((out / "truth.json").read_text())
    assert np.allclose(truth["K"], distorted_matrix(K, 1.05)) and truth["lens_distortion"]["L"] == list(lenses["L"])
    for side, dist in lenses.items():
        image = cv2.imread(str(out / "calib" / f"c_{side}.png"), cv2.IMREAD_GRAYSCALE).astype(float)
        image[image < 10] = 0  # the spline's faint ringing off the blob
        rows, cols = np.mgrid[0 : image.shape[0], 0 : image.shape[1]]
        centroid = np.array([(image * cols).sum(), (image * rows).sum()]) / image.sum()
        expected, _ = cv2.projectPoints(ray[None], np.zeros(3), np.zeros(3), np.asarray(truth["K"]), np.asarray(dist))
        expected = expected.ravel()
        assert np.abs(centroid - expected).max() < 0.05, (side, centroid, expected)
        assert np.abs(centroid - (np.asarray(truth["K"]) @ ray)[:2]).max() > 0.5  # the lens's move is there to see


def test_real_pair_scores_each_estimate_against_the_true_disparity(tmp_path):
    """`real_pair`: on a textured pair whose right image is the left one moved by a known inclined disparity (the
    truth written as Middlebury's bottom-up PFM), SGBM matches nearly every pixel, the sub-pixel step's values lie
    closer to the truth than SGBM's own, and the table's figures are the errors recomputed from its estimates."""
    import cv2
    import numpy as np

    from experiments._common import Output
    from experiments.real_pair import evaluate, main, read_disparity, score

    rng = np.random.default_rng(3)
    h, w = 120, 200
    texture = cv2.GaussianBlur(rng.uniform(0, 255, (h, w + 40, 3)).astype(np.float32), (0, 0), 1.2)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    truth = (14.3 + 0.01 * xx + 0.006 * yy).astype(np.float32)
    left = np.clip(texture[:, 20:20 + w], 0, 255).astype(np.uint8)
    # the right image sees the left pixel x at x - d: R(x - d) = L(x), so R(x') = L(x' + d) with d taken at x'
    right_map = xx + 20 + (14.3 + 0.01 * xx + 0.006 * yy) / (1 - 0.01)
    right = np.clip(cv2.remap(texture, right_map, yy, cv2.INTER_CUBIC), 0, 255).astype(np.uint8)
    pfm = tmp_path / "disp0.pfm"
    pfm.write_bytes(b"Pf\n%d %d\n-1.0\n" % (w, h) + truth[::-1].astype("<f4").tobytes())
    assert np.array_equal(read_disparity(pfm), truth)
    rows, estimates = evaluate(left, right, read_disparity(pfm), Output(tmp_path, "real-pair"))
    scored = estimates["scored"]
    assert scored[:, 40:].mean() > 0.9  # right of the search range's start, nearly every pixel matched
    by_name = {row[0]: row for row in rows}
    sgbm = score(estimates["SGBM's own sub-pixel values"], truth, scored)
    shipped = score(estimates["sub-pixel step as shipped (47 px, 9 px)"], truth, scored)
    assert sgbm["bad_percent"] < 1.0 and shipped["bad_percent"] < 1.0
    assert shipped["mean_abs_rest_px"] < 0.05 < sgbm["mean_abs_rest_px"]
    assert by_name["SGBM's own sub-pixel values"][3] == f"{sgbm['mean_abs_rest_px']:.3f}"
    error = np.abs(estimates["SGBM's own sub-pixel values"] - truth)[scored]
    assert sgbm["bad_percent"] == 100 * np.mean(error > 1) and sgbm["pixels"] == scored.sum()
    # the error bars: 0.3 px off, sigma 0.1 px alone (2 sigma 0.2) misses it, with a 0.2 px disagreement (2 sigma
    # 0.45) a survey's point covers it; SGBM's own values carry none
    off = score(truth + 0.3, truth, scored, np.full_like(truth, 0.1), np.full_like(truth, 0.2))
    assert off["within_2_sigma_percent"] == 0.0 and off["within_2_survey_sigma_percent"] == 100.0
    assert by_name["SGBM's own sub-pixel values"][-2:] == ["-", "-"]
    assert float(by_name["sub-pixel step as shipped (47 px, 9 px)"][-1]) >= float(
        by_name["sub-pixel step as shipped (47 px, 9 px)"][-2])
    with pytest.raises(SystemExit, match="one size"):
        evaluate(left, right[:, 1:], truth, Output(tmp_path, "real-pair"))
    for name, image in (("left.png", left), ("right.png", right)):
        cv2.imwrite(str(tmp_path / name), image[..., ::-1])
    np.save(tmp_path / "truth.npy", truth)
    assert main([str(tmp_path / "left.png"), str(tmp_path / "right.png"), str(tmp_path / "truth.npy"),
                 "--out", str(tmp_path / "out")]) == 0
    table = (tmp_path / "out" / "real-pair" / "table.md").read_text()
    assert "| " + by_name["SGBM's own sub-pixel values"][3] + " |" in table
    assert (tmp_path / "out" / "real-pair" / "real_pair.png").read_bytes()[:4] == b"\x89PNG"


def test_povray_flume_cameras_and_true_surface_without_povray():
    """`povray_flume`: POV-Ray's camera vectors shoot each pixel along the OpenCV pinhole's ray, and the true surface
    is each rock's exact top (an analytic sphere; a turned ellipsoid's quadric), the core's elsewhere."""
    import re

    import cv2
    import numpy as np

    from experiments import povray_flume as pf

    K = np.array([[2700.0, 0, 850.2], [0, 2705.0, 580.7], [0, 0, 1]])  # principal point off the image's centre
    R = cv2.Rodrigues(np.array([3.1, 0.02, -0.01]))[0]
    t = np.array([-0.3, 0.2, 2.0])
    size = (1728, 1152)
    text = pf.camera_pov(K, R, t, size)
    vectors = {k: np.array(re.search(k + r" <([^>]*)>", text).group(1).split(","), float)
               for k in ("location", "direction", "right", "up")}
    assert np.allclose(vectors["location"], -R.T @ t)
    for u, v in ((0, 0), (1727, 1151), (400.0, 900.0)):
        pov = (vectors["direction"] + ((u + 0.5) / size[0] - 0.5) * vectors["right"]
               + (0.5 - (v + 0.5) / size[1]) * vectors["up"])  # POV-Ray's ray through the pixel's centre
        pinhole = R.T @ np.linalg.solve(K, [u, v, 1.0])
        assert np.allclose(np.cross(pov, pinhole), 0, atol=1e-12) and pov @ pinhole > 0

    x = np.arange(0.30, 0.50, 0.001)
    y = np.arange(0.20, 0.40, 0.001)
    sphere = {"centre": np.array([[0.4, 0.3, 0.2]]), "R": np.eye(3)[None], "semi": np.full((1, 3), 0.02)}
    z = pf.heightfield(sphere, np.array([True]), x, y)
    X, Y = np.meshgrid(x, y)
    inside = np.hypot(X - 0.4, Y - 0.3) < 0.0199
    top = 0.2 + np.sqrt(np.maximum(0.02**2 - (X - 0.4) ** 2 - (Y - 0.3) ** 2, 0))
    assert np.allclose(z[inside], top[inside], atol=1e-6)
    outside = np.hypot(X - 0.4, Y - 0.3) > 0.0201
    assert np.allclose(z[outside], pf.core_height(X)[outside], atol=1e-6)  # the core, sloping in x

    stones = pf.rocks(seed=5)
    one = {k: v[:1] for k, v in stones.items()}
    c, Rr, s = one["centre"][0], one["R"][0], one["semi"][0]
    x, y = np.arange(c[0] - 0.04, c[0] + 0.04, 0.001), np.arange(c[1] - 0.04, c[1] + 0.04, 0.001)
    z = pf.heightfield(one, np.array([True]), x, y).astype(float)
    X, Y = np.meshgrid(x, y)
    on = z > pf.core_height(X) + 1e-4
    local = (np.stack([X[on], Y[on], z[on]], 1) - c) @ Rr / s  # the rock's own frame, semi-axes 1
    assert on.sum() > 500 and np.allclose(np.sum(local**2, axis=1), 1.0, atol=1e-4)  # on the ellipsoid
    assert np.all((local / s) @ Rr.T[:, 2] > 0)  # the upper root: the quadric's gradient points up there
    lost = pf.hole(stones, (0.4, 0.3))
    assert 2 <= lost.sum() <= 12 and set(stones["layer"][lost]) <= {1, 2}


def test_povray_rig_makes_the_rig_asked_and_boards_both_cameras_see_whole():
    """`povray_rig`: the cameras stand where asked (height, baseline along or across the flume), their optical axes
    meet at the convergence asked (within the jitter's spread), and every board pose keeps each corner inside both
    images, facing both cameras; the board's squares' corners are the pattern's."""
    import numpy as np

    from experiments import povray_rig as pr

    K = np.array([[3000.0, 0, 863.5], [0, 3000.0, 575.5], [0, 0, 1]])
    for across, base in ((False, [1, 0, 0]), (True, [0, 1, 0])):
        rig = pr.make_rig(2.3, 0.25, across, 3.0, seed=7)
        R = {s: np.array(rig[s]["R"]) for s in "LR"}
        centre = {s: -R[s].T @ np.array(rig[s]["t"]) for s in "LR"}
        assert np.allclose(R["L"] @ R["L"].T, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(R["L"]), 1.0)
        assert np.allclose(centre["R"] - centre["L"], 0.25 * np.array(base), atol=1e-12)
        assert np.allclose([centre["L"][2], centre["R"][2]], 2.3, atol=1e-12)
        axes = R["L"][2], R["R"][2]
        angle = np.degrees(np.arccos(np.clip(axes[0] @ axes[1], -1, 1)))
        assert abs(angle - 3.0) < 1.5, angle  # 0.4 deg jitter per axis and camera
        assert axes[0] @ base > 0 > axes[1] @ base  # toed in: each looks toward the other
        assert R["L"][0] @ base > 0.99  # the image's x axis along the baseline: the right camera sees d > 0
        poses = pr.board_poses(K, rig, 6, seed=3)
        assert len(poses) == 6
        local = pr.board_corners()
        assert local.shape == (58, 3) and np.isclose(local[1, 0] - local[0, 0], pr.SQUARE)
        for Rb, c in poses:
            X = local @ Rb.T + c
            for s in "LR":
                uv, depth = pr.project(K, rig[s], X)
                assert (depth > 0).all()
                assert (uv >= pr.MARGIN_PX).all() and (uv <= np.array(pr.SIZE) - 1 - pr.MARGIN_PX).all()
                assert Rb[:, 2] @ (centre[s] - c) > 0  # the printed face toward the camera
    stepped = pr.make_rig(2.1, 0.2, False, 2.0, seed=53, step=0.08)
    centres = [-np.array(stepped[s]["R"]).T @ np.array(stepped[s]["t"]) for s in "LR"]
    assert np.allclose(centres[1] - centres[0], [0.2, 0.0, 0.08], atol=1e-12)  # the right camera 8 cm higher


def test_povray_rig_oblique_rig_aims_at_the_board_and_sees_its_boards_whole():
    """`povray_rig.make_oblique_rig`: the cameras stand at the height and across-flume baseline asked, in front of the
    model, their axes pass within the jitter's reach of the sloping board's middle and tilt by the angle asked from
    the vertical; the right camera sees positive disparities (image x toward -y); `board_poses(follow_axis=True)`
    finds poses both cameras see whole, and the origin board where the rig's axis meets the floor is in both views."""
    import numpy as np

    from experiments import povray_rig as pr

    K = np.array([[2600.0, 0, 863.5], [0, 2600.0, 575.5], [0, 0, 1]])
    for tilt in (25.0, 40.0):
        rig = pr.make_oblique_rig(tilt, 1.65, 0.18, seed=5)
        R = {s: np.array(rig[s]["R"]) for s in "LR"}
        centre = {s: -R[s].T @ np.array(rig[s]["t"]) for s in "LR"}
        assert np.allclose(R["L"] @ R["L"].T, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(R["L"]), 1.0)
        assert np.allclose(centre["L"] - centre["R"], [0.0, 0.18, 0.0], atol=1e-12)
        assert np.allclose([centre["L"][2], centre["R"][2]], 1.65, atol=1e-12)
        assert centre["L"][0] < pr.BOARD_PLANE["x0"]  # in front of the model
        for s in "LR":
            to_aim = pr.BOARD_MIDDLE - centre[s]
            miss = np.linalg.norm(np.cross(R[s][2], to_aim))  # the axis's distance from the board's middle
            assert miss < np.linalg.norm(to_aim) * np.radians(1.5), miss  # 0.4 deg jitter per axis
            assert R[s][0] @ [0, -1, 0] > 0.99  # image x toward -y: the right camera (at -y) sees d > 0
        off_vertical = np.degrees(np.arccos(-np.mean([R["L"][2], R["R"][2]], 0)[2]))
        assert abs(off_vertical - tilt) < 1.5, off_vertical
        poses = pr.board_poses(K, rig, 6, seed=3, follow_axis=True)
        assert len(poses) == 6
        floor_hit = pr.BOARD_MIDDLE[0] + pr.BOARD_MIDDLE[2] * np.tan(np.radians(tilt))
        corners = pr.board_corners()[:-4] + [floor_hit - 4 * pr.SQUARE, pr.BOARD_MIDDLE[1] - 2.5 * pr.SQUARE, 0]
        for s in "LR":
            uv, depth = pr.project(K, rig[s], corners)
            assert (depth > 0).all() and (uv > 0).all() and (uv < np.array(pr.SIZE) - 1).all()


def test_frame_tilt_reads_a_known_tilt_and_height_of_the_world_frame():
    """`frame_tilt.frame_errors`: a calibrated frame turned from the truth's by 0.5 mrad about its x axis and -0.3 about
    y, and shifted 0.2 mm along z, reads the turn back (with its sign turned: the rotation from our up to the truth's)
    and the left camera's height where that move puts it."""
    from types import SimpleNamespace

    import numpy as np

    import jaxstereo as js
    from experiments.frame_tilt import frame_errors

    R_true = np.asarray(js.Pose.look_at([0.3, 0.2, 2.0], [0.35, 0.25, 0.0]).R)
    t_true = -R_true @ np.array([0.3, 0.2, 2.0])
    truth = {"rigs": {"main": {"L": {"R": R_true.tolist(), "t": t_true.tolist()}}}}
    turn = js.so3_exp(np.array([0.5e-3, -0.3e-3, 0.0]))  # our frame from the truth's: X_ours = turn X_true + lift
    lift = np.array([0.0, 0.0, 0.2e-3])
    R_ours = R_true @ np.asarray(turn).T
    t_ours = t_true - R_ours @ lift
    rig = SimpleNamespace(left=SimpleNamespace(pose=SimpleNamespace(R=R_ours, t=t_ours)), calibration={})
    report = {"frame_cov": np.diag([1e-6, 1e-6, 1e-6, 1e-8, 1e-8, 1e-8]).tolist()}
    e = frame_errors(rig, report, truth)
    np.testing.assert_allclose(e["tilt"], [-0.5, 0.3], atol=2e-3)  # mrad, from our up back to the truth's
    centre_true = np.array([0.3, 0.2, 2.0])
    expected_height = (np.asarray(turn) @ centre_true + lift)[2] - centre_true[2]
    np.testing.assert_allclose(e["height"], 1e3 * expected_height, atol=1e-6)
    np.testing.assert_allclose(e["tilt_std"], [1.0, 1.0])
