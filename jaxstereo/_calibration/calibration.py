"""Calibration: intrinsics per camera, the stereo pose, and the world frame from a board on z = 0."""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import cv2
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._geometry.camera import Camera
from .._geometry.errors import JaxStereoError
from .._geometry.pose import Pose
from .._geometry.precision import float64
from .._stereo.row_bands import available_cores
from .boards import BoardSpec
from .detect import Detection, detect_board
from .pose_covariance import covariance_with_smooth_errors, right_pose_covariance
from .rig import Rig

log = logging.getLogger("jaxstereo")

MIN_VIEWS = 3


@dataclasses.dataclass(frozen=True)
class CameraCalibration:
    """Intrinsics of one camera and how well they fit.

    **Fields:** `K` (3, 3) pixels; `dist` (5,) OpenCV order; `rms_px` overall reprojection RMS;
    `view_rms_px` (n_views,) per view; `views` indices (into the input list) of the views used;
    `dropped` indices of views dropped as outliers; `focal_std_px` OpenCV's standard deviation of fx.
    """

    K: np.ndarray
    dist: np.ndarray
    rms_px: float
    view_rms_px: np.ndarray
    views: list[int]
    dropped: list[int]
    focal_std_px: float = float("nan")


@dataclasses.dataclass(frozen=True)
class StereoCalibration:
    """Both cameras and their relative pose (`x_right = R x_left + T`, metres).

    **Fields:** `left`, `right` (`CameraCalibration`); `R` (3, 3); `T` (3,) metres; `rms_px` stereo RMS;
    `pair_rms_px` (n_pairs,) per pair used; `pairs` indices of the pairs used; `missing` indices of the
    pairs where the board was not found in one or both images; `origin_rvec`, `origin_tvec` the pose
    (board -> left camera, Rodrigues vector and metres) of the origin board when it was part of the
    joint adjustment, else None; `distortion_model` the distortion terms estimated; `right_pose_cov`
    (6, 6) the right camera's pose covariance in the left camera's frame (see `right_pose_covariance`).
    """

    left: CameraCalibration
    right: CameraCalibration
    R: np.ndarray
    T: np.ndarray
    rms_px: float
    pair_rms_px: np.ndarray
    pairs: list[int]
    missing: list[int]
    image_size: tuple[int, int]
    origin_rvec: np.ndarray | None = None
    origin_tvec: np.ndarray | None = None
    distortion_model: str = "k1,k2"
    right_pose_cov: np.ndarray | None = None

    @property
    def baseline_m(self) -> float:
        return float(np.linalg.norm(self.T))

    @property
    def focal_std_rel(self) -> float:
        """The larger of the two cameras' relative focal-length standard deviations (from their own calibrations):
        the relative uncertainty of every distance measured from the cameras."""
        return float(max(self.left.focal_std_px / self.left.K[0, 0], self.right.focal_std_px / self.right.K[0, 0]))


def _view_errors(board, detections, K, dist, rvecs, tvecs):
    errs = []
    for det, rvec, tvec in zip(detections, rvecs, tvecs):
        proj, _ = cv2.projectPoints(board.corners[det.ids], rvec, tvec, K, dist)
        errs.append(float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - det.pixels) ** 2, axis=1)))))
    return np.asarray(errs)


SQUARE_PIXELS = cv2.CALIB_FIX_ASPECT_RATIO
RADIAL_K1_K2 = cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST
SIGNIFICANCE = 0.01  # F-test level at which a distortion term (p1 and p2, or k3) is added to k1, k2


def calibrate_camera(
    detections: list[Detection | None], board: BoardSpec, image_size: tuple[int, int], drop_outliers: bool = True,
    outlier_factor: float = 3.0, name: str = "camera", flags: int = SQUARE_PIXELS | RADIAL_K1_K2,
) -> CameraCalibration:
    """Intrinsics from board detections (None entries are views without the board).

    Views whose RMS exceeds `outlier_factor` times the median (and 0.3 px) are dropped once and the
    calibration repeated, when `drop_outliers`. `flags` are OpenCV's calibration flags (default:
    square pixels, radial k1 and k2 only).
    """
    views = [i for i, d in enumerate(detections) if d is not None]
    if len(views) < MIN_VIEWS:
        raise JaxStereoError(
            f"{name}: the board {board} was found in only {len(views)} of {len(detections)} image(s); at least "
            f"{MIN_VIEWS} are needed (is the board specification right? are the images exposed?)"
        )
    dropped: list[int] = []
    for attempt in range(2):
        obj = [board.corners[detections[i].ids].astype(np.float32) for i in views]
        img = [detections[i].pixels.astype(np.float32) for i in views]
        K0 = np.array([[1.0, 0.0, (image_size[0] - 1) / 2], [0.0, 1.0, (image_size[1] - 1) / 2], [0.0, 0.0, 1.0]])
        rms, K, dist, rvecs, tvecs, std_intrinsics, _, _ = cv2.calibrateCameraExtended(obj, img, image_size, K0, None,
                                                                                       flags=flags)
        errs = _view_errors(board, [detections[i] for i in views], K, dist, rvecs, tvecs)
        if not drop_outliers or attempt == 1:
            break
        limit = max(outlier_factor * float(np.median(errs)), 0.3)
        bad = [v for v, e in zip(views, errs) if e > limit]
        if not bad or len(views) - len(bad) < MIN_VIEWS:
            break
        for v in bad:
            log.info("%s: view %d dropped (RMS %.2f px > %.2f px)", name, v, errs[views.index(v)], limit)
        dropped = bad
        views = [v for v in views if v not in bad]
    std = np.asarray(std_intrinsics).ravel()
    # With square pixels OpenCV fits fy and ties fx to it: its standard deviation is fy's.
    return CameraCalibration(K, dist.ravel()[:5].copy(), float(rms), errs, views, dropped, float(max(std[0], std[1])))


# The distortion terms a camera may need beyond radial k1, k2, and the OpenCV flags that leave each out.
EXTRA_TERMS = {"p1,p2": cv2.CALIB_ZERO_TANGENT_DIST, "k3": cv2.CALIB_FIX_K3}
TERM_ORDER = ("k1", "k2", "p1", "p2", "k3")


def _model_flags(terms: frozenset[str]) -> int:
    """OpenCV's flags for square pixels and the distortion terms k1, k2 plus `terms` (of `EXTRA_TERMS`)."""
    flags = SQUARE_PIXELS
    for name, flag in EXTRA_TERMS.items():
        if name not in terms:
            flags |= flag
    return flags


def _model_name(terms: frozenset[str]) -> str:
    """The distortion model's terms in OpenCV's order, e.g. "k1,k2,p1,p2"."""
    names = {"k1", "k2"} | {t for term in terms for t in term.split(",")}
    return ",".join(t for t in TERM_ORDER if t in names)


def _distortion_terms_needed(detections, board, image_size, drop_outliers, name) -> frozenset[str]:
    """The distortion terms beyond k1, k2 that a camera's residuals call for (of `EXTRA_TERMS`): added one at a
    time (the tangential pair p1, p2, or k3), the most significant first, while its F-test rejects the model
    without it at `SIGNIFICANCE` (forward selection).

    A term the lens lacks still takes a value from the corners' noise, and one the boards barely determine (k3,
    where they never reach the image's corners) trades off with k2: inside the boards' reach the model fits as
    well, beyond it, at the image's corners, it bends. Taking p1, p2 and k3 together, as soon as the two tangential
    terms were needed, did that: on the POV-Ray flume's oblique rig (ideal pinholes) the right camera's k3 came
    out 1.74 and its lens model moved the image's corners by 3.2 px, against 0.21 px now; on the same flume seen
    through decentred 35 mm lenses (`experiments/distorted_rig_data.py`) 0.25 px (1.0 px on the oblique rig),
    against 0.07 (0.21) px now."""
    from scipy.special import fdtrc  # the F distribution's survival function (scipy.stats takes 5x as long to import)

    def fit(terms):
        return calibrate_camera(detections, board, image_size, drop_outliers, name=name, flags=_model_flags(terms))

    terms: frozenset[str] = frozenset()
    current = fit(terms)
    while True:
        best = None
        for extra in EXTRA_TERMS.keys() - terms:
            bigger = terms | {extra}
            candidate = fit(bigger)
            if candidate.views != current.views:
                continue
            n = 2 * sum(len(detections[i].ids) for i in candidate.views)
            added = len(extra.split(","))
            p = 4 + 2 + sum(len(t.split(",")) for t in bigger) + 6 * len(candidate.views)  # intrinsics, lens, poses
            ss_small, ss_big = n * current.rms_px**2, n * candidate.rms_px**2
            if ss_big <= 0 or n <= p:
                continue
            stat = ((ss_small - ss_big) / added) / (ss_big / (n - p))
            p_value = float(fdtrc(added, n - p, stat))
            if p_value < SIGNIFICANCE and (best is None or p_value < best[0]):
                best = (p_value, bigger, candidate)
        if best is None:
            return terms
        log.info("%s: distortion model %s (F-test p = %.2g)", name, _model_name(best[1]), best[0])
        terms, current = best[1], best[2]


def calibrate_stereo(
    left_detections: list[Detection | None], right_detections: list[Detection | None], board: BoardSpec,
    image_size: tuple[int, int], drop_outliers: bool = True, origin: tuple[Detection, Detection] | None = None,
) -> StereoCalibration:
    """Intrinsics of both cameras, then one joint adjustment of both cameras' intrinsics and their relative pose.

    Pixels are square; the distortion model is radial k1, k2, with the tangential p1, p2 and the radial k3 each
    added when it reduces either camera's residuals significantly (`_distortion_terms_needed`). `origin`, the
    (left, right) detections of the board lying on z = 0, joins the joint adjustment as one more pair: its pose
    then comes out of the same fit as the intrinsics and the stereo pose (`origin_rvec`, `origin_tvec`), for
    `world_frame_rig`.
    """
    if len(left_detections) != len(right_detections):
        raise JaxStereoError(
            f"{len(left_detections)} left images but {len(right_detections)} right images: pairs must match"
        )
    cameras = ((left_detections, "left camera"), (right_detections, "right camera"))
    terms = frozenset().union(*(_distortion_terms_needed(dets, board, image_size, drop_outliers, name)
                                for dets, name in cameras))
    flags = _model_flags(terms)
    left = calibrate_camera(left_detections, board, image_size, drop_outliers, name="left camera", flags=flags)
    right = calibrate_camera(right_detections, board, image_size, drop_outliers, name="right camera", flags=flags)
    pairs, missing, obj, img_l, img_r = [], [], [], [], []
    for i, (dl, dr) in enumerate(zip(left_detections, right_detections)):
        if dl is None or dr is None:
            missing.append(i)
            continue
        if i in left.dropped or i in right.dropped:
            continue
        if _add_pair(board, dl, dr, obj, img_l, img_r):
            pairs.append(i)
        else:
            missing.append(i)
    if len(pairs) < MIN_VIEWS:
        raise JaxStereoError(
            f"the board was found in both images of only {len(pairs)} pair(s); at least {MIN_VIEWS} are needed"
        )
    if origin is not None and not _add_pair(board, origin[0], origin[1], obj, img_l, img_r):
        raise JaxStereoError("the origin board's corners seen in both images are too few (fewer than 6)")
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-10)
    rms, Kl, dl_, Kr, dr_, R, T, _, _, rvecs, tvecs, per_view = cv2.stereoCalibrateExtended(
        obj, img_l, img_r, left.K, left.dist, right.K, right.dist, image_size, None, None,
        flags=cv2.CALIB_USE_INTRINSIC_GUESS | flags, criteria=criteria,
    )
    left = dataclasses.replace(left, K=Kl, dist=dl_.ravel()[:5].copy())
    right = dataclasses.replace(right, K=Kr, dist=dr_.ravel()[:5].copy())
    pose_cov = right_pose_covariance(Kl, dl_, Kr, dr_, R, T, image_size, obj, img_l, img_r, rvecs, tvecs)
    pair_rms = np.sqrt(np.mean(np.asarray(per_view) ** 2, axis=1))
    origin_pose = (np.asarray(rvecs[-1]).ravel(), np.asarray(tvecs[-1]).ravel()) if origin is not None else (None, None)
    if origin is not None:
        pair_rms = pair_rms[:-1]
    return StereoCalibration(left, right, R, T.ravel(), float(rms), pair_rms, pairs, missing, image_size,
                             *origin_pose, _model_name(terms), pose_cov)


def _add_pair(board, dl: Detection, dr: Detection, obj, img_l, img_r) -> bool:
    """Append a pair's common corners to the adjustment's lists; False when fewer than 6 are common."""
    if board.kind == "chessboard":
        dr = align_chessboard_order(dl, dr)
    common, il, ir = np.intersect1d(dl.ids, dr.ids, return_indices=True)
    if common.size < 6:
        return False
    obj.append(board.corners[common].astype(np.float32))
    img_l.append(dl.pixels[il].astype(np.float32))
    img_r.append(dr.pixels[ir].astype(np.float32))
    return True


def align_chessboard_order(reference: Detection, other: Detection) -> Detection:
    """Reverse `other`'s corner order if it runs opposite to `reference`'s (the 180-degree ambiguity).

    For two views of one board from nearby viewpoints (a stereo pair), the image direction from the
    first to the last corner agrees; when it does not, the detector numbered the corners the other way.
    """
    d_ref = reference.pixels[-1] - reference.pixels[0]
    d_other = other.pixels[-1] - other.pixels[0]
    if float(d_ref @ d_other) < 0:
        return Detection(other.ids, other.pixels[::-1].copy())
    return other


def _flip_to_z_up(R_bc: np.ndarray, t_bc: np.ndarray):
    """Board->camera pose such that the board frame's Z points towards the camera (up)."""
    center_b = -R_bc.T @ t_bc
    if center_b[2] < 0:
        flip = np.diag([1.0, -1.0, -1.0])  # 180 degrees about the board's X axis
        R_bc = R_bc @ flip
    return R_bc, t_bc


@float64
def world_frame_rig(
    stereo: StereoCalibration, board: BoardSpec, origin_left: Detection, origin_right: Detection | None = None,
    refine: bool = True,
) -> tuple[Rig, dict]:
    """Place the calibrated rig in the world frame of a board lying on z = 0.

    The world origin is the board frame's origin: for a chessboard, the inner corner nearest the
    top-left of the left image; for a ChArUco board, OpenCV's board origin (the board's outer corner
    diagonally next to corner id 0). X runs along the board's columns, Z points up towards the
    cameras and Y = Z x X. The left camera's pose is the origin board's pose from the joint adjustment
    when `stereo` was calibrated with the origin pair (`calibrate_stereo(..., origin=...)`: its corners
    in both images, fitted together with the intrinsics and the stereo pose), else from `solvePnP` in
    the left image; the right camera's follows from the stereo pose. Without the joint pose, `refine`
    and `origin_right` move the two cameras together (their relative pose kept) to minimise, with
    optimistix, the reprojection of the board's corners in both images; the result is kept only when
    it lowers that RMS.

    **Returns:** `(rig, report)`; the report says where the pose came from and has the origin board's RMS
    (pixels) and, with both origin images, the frame's covariance (`frame_cov`, see `_frame_covariance`);
    the rig's `calibration` holds it under "world_frame", beside the focal length's relative std.
    """
    obj = board.corners[origin_left.ids]
    joint = stereo.origin_rvec is not None
    if joint:
        rvec, tvec = np.asarray(stereo.origin_rvec, float), np.asarray(stereo.origin_tvec, float)
    else:
        ok, rvec, tvec = cv2.solvePnP(obj, origin_left.pixels, stereo.left.K, stereo.left.dist,
                                      flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok:
            raise JaxStereoError("the origin board's pose could not be solved in the left image")
    R_bc, _ = cv2.Rodrigues(rvec)
    R_bc, t_bc = _flip_to_z_up(R_bc, tvec.ravel())
    flipped = not np.allclose(R_bc, cv2.Rodrigues(rvec)[0])
    size = stereo.image_size
    left = Camera(stereo.left.K[0, 0], stereo.left.K[1, 1], stereo.left.K[0, 2], stereo.left.K[1, 2],
                  stereo.left.dist, Pose(jnp.asarray(R_bc), jnp.asarray(t_bc)), size)
    R_r = stereo.R @ R_bc
    t_r = stereo.R @ t_bc + stereo.T
    right = Camera(stereo.right.K[0, 0], stereo.right.K[1, 1], stereo.right.K[0, 2], stereo.right.K[1, 2],
                   stereo.right.dist, Pose(jnp.asarray(R_r), jnp.asarray(t_r)), size)
    world_obj = obj * np.array([1.0, -1.0, -1.0]) if flipped else obj
    report = {"origin_corners": int(len(obj)), "z_flipped": bool(flipped),
              "pose_from": "joint adjustment with the calibration pairs" if joint else "solvePnP, left image"}
    if origin_right is not None:
        if board.kind == "chessboard":
            origin_right = align_chessboard_order(origin_left, origin_right)
        world_obj_r = board.corners[origin_right.ids] * (np.array([1.0, -1.0, -1.0]) if flipped else 1.0)
        before = _origin_rms(left, right, world_obj, origin_left.pixels, world_obj_r, origin_right.pixels)
        report["origin_rms_px_before"] = before
        report["origin_rms_px_after"] = before
        if refine and not joint:
            new_left, new_right, after, steps = _refine_poses(left, right, world_obj, origin_left.pixels,
                                                              world_obj_r, origin_right.pixels)
            report["refine_steps"] = steps
            if after < before:
                left, right = new_left, new_right
                report["origin_rms_px_after"] = after
        report.update(_frame_covariance(left, right, world_obj, origin_left.pixels, world_obj_r, origin_right.pixels))
    if stereo.right_pose_cov is not None and np.all(np.isfinite(stereo.right_pose_cov)):
        # Rotation vectors and centre shifts in the left camera's frame -> world axes (x_cam = R_bc x_world).
        Q = np.kron(np.eye(2), np.asarray(left.pose.R).T)
        report["right_pose_cov"] = (Q @ stereo.right_pose_cov @ Q.T).tolist()
    provenance = {"world_frame": report}
    if np.isfinite(stereo.focal_std_rel):
        provenance["focal_std_rel"] = stereo.focal_std_rel
    rig = Rig(left, right, None, provenance)
    return rig, report


# The corners' smooth error over one board (pixels RMS per axis, see `covariance_with_smooth_errors`). Against
# the exact corners of POV-Ray's origin boards (11 flumes, 22 images), an offset and gradients fitted to each image's
# corner errors leave 0.009 px RMS beyond what their 0.03 px of independent noise explains, and 0.02-0.03 px on a
# few. With independent noise alone the frame's tilt erred by 1.7 times its std (RMS over the flumes' 24 axes, 2
# past 3 std); with 0.01 px by 1.07 times, 3 past 2 std; with 0.015 px by 0.83 times, 1 past 2 std
# (`experiments/frame_tilt.py`).
SMOOTH_CORNER_ERROR_PX = 0.015


def _frame_covariance(left: Camera, right: Camera, obj_l, px_l, obj_r, px_r) -> dict:
    """How well the origin board fixes the world frame: the covariance (6, 6) of a small move of the frame,
    `X -> X + w x X + v` (w radians, v metres, world axes), from the board corners' reprojection in both
    images with the cameras' calibration held, the pixel noise estimated from the residuals themselves, and a
    smooth error shared by each image's corners of `SMOOTH_CORNER_ERROR_PX` (the detector's, on top of that
    noise; it dominates the tilt's std).

    **Returns:** `{"frame_cov": 6x6 list, "frame_tilt_std_mrad": [about x, about y], "frame_height_std_m":
    at the origin, "frame_noise_px"}` for the rig's provenance; `refine` turns it into the floor's height
    uncertainty where its control points lie.
    """
    pixels = np.concatenate([px_l, px_r])
    image = np.repeat([0, 1], [len(px_l), len(px_r)])
    cov, noise = covariance_with_smooth_errors(_frame_residuals, 6, pixels, image, SMOOTH_CORNER_ERROR_PX, left, right,
                                               jnp.asarray(obj_l), jnp.asarray(obj_r), jnp.asarray(pixels))
    if not np.all(np.isfinite(cov)):  # too few corners to fix the frame: no record, no frame term in refine
        return {}
    return {"frame_cov": cov.tolist(), "frame_tilt_std_mrad": [1e3 * float(np.sqrt(cov[k, k])) for k in (0, 1)],
            "frame_height_std_m": float(np.sqrt(cov[5, 5])), "frame_noise_px": noise}


def _frame_residuals(p, left: Camera, right: Camera, obj_l, obj_r, seen):
    """Reprojection residuals (pixels) of the origin board's corners in both images, the world frame moved by
    `p`: `X -> X + p[:3] x X + p[3:]`."""
    moved_l, moved_r = (obj + jnp.cross(p[:3], obj) + p[3:] for obj in (obj_l, obj_r))
    return (jnp.concatenate([left.project(moved_l), right.project(moved_r)]) - seen).ravel()


def _origin_rms(left, right, obj_l, px_l, obj_r, px_r) -> float:
    rl = np.asarray(left.project(jnp.asarray(obj_l))) - px_l
    rr = np.asarray(right.project(jnp.asarray(obj_r))) - px_r
    both = np.concatenate([rl, rr])
    return float(np.sqrt(np.mean(np.sum(both**2, axis=1))))


def _refine_poses(left: Camera, right: Camera, obj_l, px_l, obj_r, px_r):
    """Refine the rig's pose in the world (6 parameters, the calibrated left-right pose kept) with optimistix.

    Minimises the reprojection of the origin board's corners in both images. Moving the two cameras
    together keeps the stereo calibration intact; refining them separately on one planar view would
    trade lateral position against rotation, which a single board barely constrains.
    """
    obj_l, px_l, obj_r, px_r = (jnp.asarray(a) for a in (obj_l, px_l, obj_r, px_r))
    relative = right.pose.compose(left.pose.inverse())  # left camera frame -> right camera frame

    def cameras(delta):
        pose_l = left.pose.retract(delta)
        return left.with_pose(pose_l), right.with_pose(relative.compose(pose_l))

    def residuals(delta, _):
        cl, cr = cameras(delta)
        return jnp.concatenate([(cl.project(obj_l) - px_l).ravel(), (cr.project(obj_r) - px_r).ravel()])

    solver = optx.LevenbergMarquardt(rtol=1e-10, atol=1e-10)
    sol = optx.least_squares(residuals, solver, jnp.zeros(6), max_steps=100, throw=False)
    new_left, new_right = cameras(sol.value)
    after = _origin_rms(new_left, new_right, obj_l, np.asarray(px_l), obj_r, np.asarray(px_r))
    return new_left, new_right, after, int(sol.stats["num_steps"])


def detect_all(images: list[np.ndarray], board: BoardSpec,
               on_each: Callable[[int, Detection | None], None] | None = None,
               workers: int | None = None) -> list[Detection | None]:
    """`detect_board` on every image (None where the board is not found), in the images' order.

    The images are searched on `workers` threads (default: one per core, at most 8; OpenCV's detectors
    release the interpreter: 8 of the POV-Ray flume's 1728x1152 boards in 0.76x the time on 2 cores);
    `on_each(index, detection)` is called for each image as its turn in the order comes (a progress bar).
    """
    workers = max(1, min(len(images), workers or min(8, available_cores())))  # at most 8 images' working copies
    with ThreadPoolExecutor(workers) as pool:
        found = []
        for k, detection in enumerate(pool.map(lambda image: detect_board(image, board), images)):
            if on_each is not None:
                on_each(k, detection)
            found.append(detection)
    return found


