"""Bundle adjustment through refraction: the water level, interface tilt and right-camera pose from
the wet images themselves (optimistix).

Each sparse correspondence is triangulated inside the residual function (exact refraction, so the
3-D points are eliminated and only a handful of parameters remain), re-projected exactly into both
images, and compared with the observed pixels. Control terms make the water level observable: points
known to lie on a surface (the flume floor) or control points with known coordinates. The left camera
fixes the gauge.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Sequence

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import ArrayLike

from .._calibration.rig import Rig
from .._geometry.camera import Camera
from .._geometry.errors import JaxStereoError
from .._geometry.interface import Interface, check_camera_above, tilt_normal
from .._geometry.precision import float64
from .._geometry.refraction import intersect_plane, project_refracted, refract_directions
from .._geometry.triangulate import triangulate_rays
from .._surface.grid import DEM, dem_heights

log = logging.getLogger("jaxstereo")

PARAMETERS = ("water", "tilt", "right-pose")
MIN_CORRESPONDENCES = 12
# The level is written only when its 95 % interval (two standard deviations) lies within this of it, metres.
LEVEL_TOLERANCE_M = 0.001


def find_correspondences(left_image: np.ndarray, right_image: np.ndarray, max_points: int = 4000,
                         ratio: float = 0.75) -> tuple[np.ndarray, np.ndarray]:
    """Sparse matches between the two images: SIFT, Lowe's ratio test and a mutual (left-right) check.

    **Returns:** `(left_pixels, right_pixels)`, each (n, 2) float64, the best `max_points` by distance.
    """
    grey = [cv2.cvtColor(im, cv2.COLOR_RGB2GRAY) if im.ndim == 3 else im for im in (left_image, right_image)]
    sift = cv2.SIFT_create(nfeatures=4 * max_points)
    (kl, dl), (kr, dr) = (sift.detectAndCompute(g, None) for g in grey)
    if dl is None or dr is None or len(kl) < 2 or len(kr) < 2:
        return np.zeros((0, 2)), np.zeros((0, 2))
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    forward = matcher.knnMatch(dl, dr, k=2)
    backward = {m.queryIdx: m.trainIdx for m in matcher.match(dr, dl)}
    good = [m for m, n in (p for p in forward if len(p) == 2) if m.distance < ratio * n.distance
            and backward.get(m.trainIdx) == m.queryIdx]
    good = sorted(good, key=lambda m: m.distance)[:max_points]
    pl = np.array([kl[m.queryIdx].pt for m in good], dtype=np.float64).reshape(-1, 2)
    pr = np.array([kr[m.trainIdx].pt for m in good], dtype=np.float64).reshape(-1, 2)
    return pl, pr


class _Model(eqx.Module):
    """Maps the refined parameter vector to the rig's right camera and the interface."""

    left: Camera
    right: Camera
    level0: jax.Array
    tilt0: jax.Array
    n_air: jax.Array
    n_water: jax.Array
    across: jax.Array  # (2, 3) unit vectors perpendicular to the baseline
    prior: jax.Array  # (5, 5) whitening of the right pose's calibration covariance (zeros: no prior)
    which: tuple[str, ...] = eqx.field(static=True)

    def unpack(self, theta):
        k = 0
        level, tilt, pose = self.level0, self.tilt0, jnp.zeros(6, theta.dtype)
        # Units chosen so that a unit step moves the residuals by similar amounts: level in centimetres,
        # tilt and rotation in milliradians, translation in millimetres.
        if "water" in self.which:
            level = self.level0 + theta[k] * 1e-2
            k += 1
        if "tilt" in self.which:
            tilt = self.tilt0 + theta[k : k + 2] * 1e-3
            k += 2
        if "right-pose" in self.which:
            # Rotation in milliradians; the centre moves (millimetres) across the baseline only: the
            # baseline's length is the scale of the survey, fixed by the calibration (a gauge choice).
            shift = (theta[k + 3] * self.across[0] + theta[k + 4] * self.across[1]) * 1e-3
            pose = jnp.concatenate([theta[k : k + 3] * 1e-3, shift])
        interface = Interface(level, tilt_normal(tilt[0], tilt[1]), self.n_air, self.n_water)
        right = self.right.with_pose(self.right.pose.retract(pose))
        return right, interface

    def prior_residuals(self, theta):
        """The right pose's move in standard deviations of its calibration (5,): zeros without a prior."""
        if "right-pose" not in self.which:
            return jnp.zeros(5, theta.dtype)
        k = ("water" in self.which) + 2 * ("tilt" in self.which)
        return self.prior @ (theta[k : k + 5] * 1e-3)

    @property
    def size(self) -> int:
        return ("water" in self.which) + 2 * ("tilt" in self.which) + 5 * ("right-pose" in self.which)


def _build_model(rig: Rig, level_guess: float, which: tuple[str, ...]) -> tuple[_Model, Interface]:
    """The parameter model around the rig (its interface's normal and indices, else level defaults) and
    the interface at the guessed level."""
    normal = np.asarray(rig.interface.normal) if rig.interface is not None else np.array([0.0, 0.0, 1.0])
    n_air = float(rig.interface.n_air) if rig.interface is not None else 1.0
    n_water = float(rig.interface.n_water) if rig.interface is not None else 1.333
    tilt0 = jnp.array([-np.arcsin(normal[1]), np.arctan2(normal[0], normal[2])])
    baseline = np.asarray(rig.right.center) - np.asarray(rig.left.center)
    baseline /= np.linalg.norm(baseline)
    e1 = np.cross(baseline, [0.0, 0.0, 1.0])
    if np.linalg.norm(e1) < 1e-6:
        e1 = np.cross(baseline, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    across = np.stack([e1, np.cross(baseline, e1)])
    model = _Model(rig.left, rig.right, jnp.asarray(float(level_guess)), tilt0, jnp.asarray(n_air),
                   jnp.asarray(n_water), jnp.asarray(across), jnp.asarray(_pose_prior(rig, across)), which)
    return model, Interface(float(level_guess), normal, n_air, n_water)


def _pose_prior(rig: Rig, across: np.ndarray) -> np.ndarray:
    """Whitening (5, 5) of the right pose's covariance from calibration (`world_frame.right_pose_cov`, world
    axes, `Pose.retract`'s convention), in the refined parameters: three rotations (rad) and the centre's
    two shifts across the baseline (m). Zeros when the rig has no such record.
    """
    frame = rig.calibration.get("world_frame") if isinstance(rig.calibration, dict) else None
    cov = np.asarray(frame.get("right_pose_cov", np.zeros((0, 0))), dtype=np.float64) if isinstance(frame, dict) else None
    if cov is None or cov.shape != (6, 6) or not np.all(np.isfinite(cov)):
        return np.zeros((5, 5))
    M = np.zeros((5, 6))
    M[:3, :3] = np.eye(3)
    M[3:, 3:] = across
    try:
        return np.linalg.inv(np.linalg.cholesky(M @ cov @ M.T))
    except np.linalg.LinAlgError:
        return np.zeros((5, 5))


def _triangulate_any(left: Camera, right: Camera, interface: Interface, pl, pr):
    """Triangulate pixel pairs: in air where the in-air point is above the water, else through it."""
    o1, d1 = left.backproject(pl)
    o2, d2 = right.backproject(pr)
    p_air, _ = triangulate_rays(o1, d1, o2, d2)
    rays = []
    for o, d in ((o1, d1), (o2, d2)):
        hit, _ = intersect_plane(o, d, interface.normal, interface.level)
        t, _ = refract_directions(d, interface.normal, interface.n_air, interface.n_water)
        rays.append((hit, t))
    p_water, _ = triangulate_rays(rays[0][0], rays[0][1], rays[1][0], rays[1][1])
    above = interface.height_of(p_air) >= 0
    return jnp.where(above[:, None], p_air, p_water)


def _residuals(theta, args):
    """Reprojection residuals (pixels) in four blocks of one row per correspondence (left u, left v, right u,
    right v: the layout the weights, residual groups and jackknife blocks index), floor residuals (metres, 0 off
    the floor), control-point residuals (metres, 3 per point), then the pose prior's."""
    model, pl, pr, control_mask, control_z, gcp_l, gcp_r, gcp_xyz = args
    right, interface = model.unpack(theta)
    points = _triangulate_any(model.left, right, interface, pl, pr)
    ql, _ = project_refracted(model.left, interface, points)
    qr, _ = project_refracted(right, interface, points)
    reproj = jnp.concatenate([(ql - pl).T.ravel(), (qr - pr).T.ravel()])
    control = jnp.where(control_mask, points[:, 2] - control_z, 0.0)
    gcp = _triangulate_any(model.left, right, interface, gcp_l, gcp_r) - gcp_xyz
    return jnp.concatenate([reproj, control, gcp.ravel(), model.prior_residuals(theta)])


_RESULT_WORDS = (("successful", "converged"), ("nonlinear_max_steps_reached", "stopped at its step limit"),
                 ("nonlinear_divergence", "diverged"), ("nonfinite", "met non-finite values"))


def result_in_words(result) -> str:
    """optimistix's result code in words: "converged", "stopped at its step limit", "diverged", ..."""
    for name, words in _RESULT_WORDS:
        item = getattr(optx.RESULTS, name, None)
        if item is not None and bool(result == item):
            return words
    return "failed"


def _robust(r, scale):
    """Cauchy loss as a residual rescaling: `r sqrt(log(1 + u) / u)`, `u = (r / scale)^2` (smooth at 0)."""
    u = (r / scale) ** 2
    small = u < 1e-8
    ratio = jnp.where(small, 1.0 - u / 2.0, jnp.log1p(u) / jnp.where(small, 1.0, u))
    return r * jnp.sqrt(ratio)


@dataclasses.dataclass(frozen=True)
class RefineResult:
    """Outcome of `refine_rig`.

    **Fields:** `rig` the refined rig (interface set); `parameters` name -> (value, standard deviation)
    in user units (level m, tilt deg, rotation deg, translation mm); for the level the standard deviation
    combines the fit's (`level_std_fit_m`: the larger of the Gauss-Newton one, scaled by the residuals' own
    noise, and a jackknife over 16 blocks of the image, which sees errors correlated in space) and the world
    frame's (`level_std_frame_m`: the calibration's scale, see `scale_level_std`); `level_determined` whether
    twice that standard deviation (its 95 % interval) is within `level_tolerance_m` (1 mm by default), every solve
    converged and at least `MIN_CORRESPONDENCES` correspondences lie under the refined level (`n_submerged`);
    `rms_before_px`, `rms_after_px` reprojection RMS of the inliers; `n_correspondences`, `n_control`; `steps`
    solver steps; `result` the last solve's outcome in words ("converged", "stopped at its step limit",
    "diverged", ...), `outcomes` every solve's in order (the solve, then a solve after each re-selection of the
    control terms), `converged` whether each of them converged (the solves that only place the start, with the
    level held at the guess, are recorded in the rig but need not converge); `seconds`; `surface_sigma_m` the
    standard deviation given to the floor or DEM control terms (the larger of the one asked for and the points'
    own scatter about the surface).
    """

    rig: Rig
    parameters: dict
    level_determined: bool
    rms_before_px: float
    rms_after_px: float
    n_correspondences: int
    n_control: int
    steps: int
    result: str
    seconds: float
    surface_sigma_m: float
    converged: bool = True
    level_std_fit_m: float = float("nan")
    level_std_frame_m: float = 0.0
    n_submerged: int = -1
    outcomes: tuple[str, ...] = ()


def _check_which(refine) -> tuple[str, ...]:
    which = tuple(dict.fromkeys(refine))
    for name in which:
        if name not in PARAMETERS:
            raise JaxStereoError(f"cannot refine {name!r}: choose from {', '.join(PARAMETERS)}")
    if not which:
        raise JaxStereoError("nothing to refine")
    return which


_SOLVER = optx.LevenbergMarquardt(rtol=1e-10, atol=1e-10)
N_PRIOR = 5  # residuals of the right pose's calibration prior, last in the residual vector
_NO_GCP = (np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 3)))


def _objective(theta, problem):
    """Residuals in units of their standard deviations, through a Cauchy loss (module level: compiled once
    per problem shape, not once per call)."""
    args, weights, scale = problem
    return _robust(_residuals(theta, args) * weights, scale)


_jacobian = jax.jit(jax.jacfwd(_objective))
_objective_jit = jax.jit(_objective)
_triangulate_jit = jax.jit(_triangulate_any)
_residuals_jit = jax.jit(_residuals)


def _padded_size(n: int) -> int:
    """Correspondences are padded to 256, 512, 1024, ... so that calls of similar size share a compilation."""
    size = 256
    while size < n:
        size *= 2
    return size


def _pad(a: np.ndarray, size: int) -> np.ndarray:
    """`a` (n, k) padded to (size, k) with copies of its first row (finite, weighted zero)."""
    return np.concatenate([a, np.repeat(a[:1], size - a.shape[0], axis=0)]) if a.shape[0] < size else a


def _gate(model, guess, pl, pr):
    """Correspondences consistent with the refracted epipolar geometry of the guess (within 5 px: the guess is
    rough), and their points at the guess."""
    size = _padded_size(len(pl))
    a, b = jnp.asarray(_pad(pl, size)), jnp.asarray(_pad(pr, size))
    points = np.asarray(_triangulate_jit(model.left, model.right, guess, a, b))[: len(pl)]
    args = (model, a, b, jnp.zeros(size, bool), jnp.zeros(size), *(jnp.asarray(g) for g in _NO_GCP))
    err = np.asarray(_residuals_jit(jnp.zeros(model.size), args))[: 4 * size]
    err = np.linalg.norm(err.reshape(2, 2, -1), axis=1).max(axis=0)[: len(pl)]  # (image, coordinate, point)
    inlier = np.isfinite(err) & (err < 5.0) & np.all(np.isfinite(points), axis=1)
    if inlier.sum() < MIN_CORRESPONDENCES:
        raise JaxStereoError(f"only {int(inlier.sum())} correspondences agree with the rig's epipolar geometry; "
                             f"at least {MIN_CORRESPONDENCES} are needed")
    return inlier, points


def _initial_control(control, points, in_region, floor_z, floor_band_m, floor_region=None):
    """Control mask and heights for the first solve: the floor's lowest points, or the DEM's heights. A floor
    region (x_min, x_max, m) that no correspondence falls in is refused by name: the bare floor is not in view
    of both cameras there (under water it is seen nearer the cameras' nadir than in air)."""
    if isinstance(control, DEM):
        heights = dem_heights(control, points[:, :2])
        mask = in_region & np.isfinite(heights)
        if not mask.any():
            p_lo, p_hi = points[:, :2].min(axis=0), points[:, :2].max(axis=0)
            raise JaxStereoError(
                f"the control DEM (x {control.x[0]:.3f} to {control.x[-1]:.3f} m, y {control.y[0]:.3f} to "
                f"{control.y[-1]:.3f} m) does not overlap the correspondences (x {p_lo[0]:.3f} to {p_hi[0]:.3f} m, "
                f"y {p_lo[1]:.3f} to {p_hi[1]:.3f} m): is it in the same world frame?")
        return mask, np.where(mask, heights, 0.0)
    heights = np.full(len(points), float(floor_z))
    if control == "floor" and floor_region is not None and not in_region.any():
        raise JaxStereoError(
            f"no correspondence lies in the floor region x {floor_region[0]:.3f} to {floor_region[1]:.3f} m (at the "
            f"guessed level they span x {points[:, 0].min():.3f} to {points[:, 0].max():.3f} m): the bare floor there "
            "is not seen by both cameras; give a region of it nearer the images' middle, or another control")
    if control == "floor":
        lowest = np.percentile(points[in_region, 2], 2) if in_region.any() else np.inf
        return in_region & (points[:, 2] <= lowest + floor_band_m), heights
    if control is None:
        return np.zeros(len(points), bool), heights
    raise JaxStereoError(f"unknown control {control!r}: use 'floor', a DEM or None")


@dataclasses.dataclass(frozen=True)
class _Data:
    """What a solve needs: the model, the (unpadded) correspondences and control, and the weighting."""

    model: _Model
    pl: np.ndarray
    pr: np.ndarray
    gcp: tuple
    pixel_sigma: float
    control_sigma_m: float
    robust_sigmas: float

    def problem(self, mask, heights, surface_sigma):
        """The padded problem `(args, weights, scale)` for `_objective`."""
        n, size, k = len(self.pl), _padded_size(len(self.pl)), self.gcp[0].shape[0]
        live = np.arange(size) < n
        pixel = np.where(live, 1.0 / self.pixel_sigma, 0.0)
        weights = np.concatenate([np.tile(pixel, 4), np.full(size, 1.0 / surface_sigma),
                                  np.full(3 * k, 1.0 / self.control_sigma_m), np.ones(N_PRIOR)])
        args = (self.model, jnp.asarray(_pad(self.pl, size)), jnp.asarray(_pad(self.pr, size)),
                jnp.asarray(np.pad(mask, (0, size - n))), jnp.asarray(np.pad(heights, (0, size - n))),
                *(jnp.asarray(g) for g in self.gcp))
        return args, jnp.asarray(weights), jnp.asarray(self.robust_sigmas)

    def points(self, theta):
        right, interface = self.model.unpack(theta)
        size = _padded_size(len(self.pl))
        pts = _triangulate_jit(self.model.left, right, interface, jnp.asarray(_pad(self.pl, size)),
                               jnp.asarray(_pad(self.pr, size)))
        return np.asarray(pts)[: len(self.pl)]


def _solve(problem, theta, max_steps):
    sol = optx.least_squares(_objective, _SOLVER, theta, problem, max_steps=max_steps, throw=False)
    return sol.value, result_in_words(sol.result), int(sol.stats["num_steps"])


def _reselect(data: _Data, theta, control, in_region, heights, base_sigma, surface_sigma, floor_band_m):
    """Control chosen again at the refined geometry: points within 3 sigma of the surface, sigma the larger of
    the given one and the points' own robust scatter about it (their depth noise: a tighter sigma would cut the
    noise distribution and bias the level)."""
    points = data.points(theta)
    if isinstance(control, DEM):
        heights = dem_heights(control, points[:, :2])
    d = points[:, 2] - heights
    candidates = in_region & np.isfinite(d)
    if not isinstance(control, DEM):
        candidates &= np.abs(d) <= max(floor_band_m, 3 * surface_sigma)
    if candidates.sum() >= MIN_CORRESPONDENCES:
        dc = d[candidates]
        surface_sigma = max(base_sigma, 1.4826 * float(np.median(np.abs(dc - np.median(dc)))))
    mask = candidates & (np.abs(d) <= 3 * surface_sigma)
    if not mask.any():
        raise JaxStereoError("no correspondence lies on the control surface at the solution: the control "
                             "does not fit these images (wrong DEM, floor region or world frame?)")
    return mask, np.where(mask, heights, 0.0), surface_sigma


def _standard_deviations(theta, problem, groups):
    """Gauss-Newton standard deviations at the solution, each group of residuals (reprojection, control terms,
    control points: `groups` lists each one's row indices that carry data) scaled by its own variance, so
    that numerous well-fitting reprojections do not vouch for a few scattered control terms."""
    J = np.asarray(_jacobian(theta, problem))
    r = np.asarray(_objective_jit(theta, problem))
    scaled = np.zeros_like(J)
    scaled[-N_PRIOR:] = J[-N_PRIOR:]  # the pose prior is in standard deviations already
    for rows in groups:
        if rows.size:
            scaled[rows] = J[rows] / np.sqrt(max(float(r[rows] @ r[rows]) / rows.size, 1e-300))
    try:
        return np.sqrt(np.maximum(np.diag(np.linalg.inv(scaled.T @ scaled)), 0.0))
    except np.linalg.LinAlgError:
        return np.full(theta.size, np.inf)


JACKKNIFE_BLOCKS = 4  # per image side: 16 spatial blocks


def _block_jackknife_std(theta, problem, pl, image_size):
    """Standard deviations from a linearised jackknife over spatial blocks of the left image (4 x 4): each
    block left out in turn, the solution moved by one Gauss-Newton step. Match errors on rough, refracted
    texture are correlated over a neighbourhood; the Gauss-Newton covariance, which takes them as
    independent, then says too little, while the spread between blocks shows it."""
    J = np.asarray(_jacobian(theta, problem))
    r = np.asarray(_objective_jit(theta, problem))
    size = _padded_size(len(pl))
    w, h = image_size
    block = (np.minimum(pl[:, 0] * JACKKNIFE_BLOCKS // w, JACKKNIFE_BLOCKS - 1) * JACKKNIFE_BLOCKS
             + np.minimum(pl[:, 1] * JACKKNIFE_BLOCKS // h, JACKKNIFE_BLOCKS - 1)).astype(int)
    rows_of = lambda k: np.concatenate([j * size + np.nonzero(block == k)[0] for j in range(5)])  # noqa: E731
    H, g = J.T @ J, J.T @ r
    estimates = []
    for k in np.unique(block):
        rows = rows_of(k)
        Jb, rb = J[rows], r[rows]
        try:
            estimates.append(-np.linalg.solve(H - Jb.T @ Jb, g - Jb.T @ rb))
        except np.linalg.LinAlgError:
            return np.full(theta.size, np.inf)
    estimates = np.asarray(estimates)
    n = len(estimates)
    if n < 3:
        return np.zeros(theta.size)
    return np.sqrt((n - 1) / n * np.sum((estimates - estimates.mean(axis=0)) ** 2, axis=0))


def _parameters(model, which, theta, std, frame_std_m):
    """Refined values and standard deviations in user units."""
    right, interface = model.unpack(theta)
    values = np.asarray(theta)
    params, k = {}, 0
    if "water" in which:
        params["water level (m)"] = (float(interface.level), float(np.hypot(std[k] * 1e-2, frame_std_m)))
        k += 1
    if "tilt" in which:
        t = np.asarray(model.tilt0) + values[k : k + 2] * 1e-3
        params["tilt x (deg)"] = (float(np.rad2deg(t[0])), float(np.rad2deg(std[k] * 1e-3)))
        params["tilt y (deg)"] = (float(np.rad2deg(t[1])), float(np.rad2deg(std[k + 1] * 1e-3)))
        k += 2
    if "right-pose" in which:
        for i, axis in enumerate("xyz"):
            params[f"right rotation {axis} (deg)"] = (float(np.rad2deg(values[k + i] * 1e-3)),
                                                      float(np.rad2deg(std[k + i] * 1e-3)))
        for i, axis in enumerate("12"):
            params[f"right shift across baseline {axis} (mm)"] = (float(values[k + 3 + i]), float(std[k + 3 + i]))
    return right, interface, params


def scale_level_std(rig: Rig, level: float) -> float:
    """The calibration's share of a level's standard deviation (m): the focal length's relative standard
    deviation (`calibration["focal_std_rel"]`, 0 when unknown) times the cameras' mean height above the water.
    Every distance measured from the cameras scales with the focal length: a level consistent with the
    images is as uncertain, measured from the cameras, as that scale."""
    rel = float(rig.calibration.get("focal_std_rel", 0.0) or 0.0) if isinstance(rig.calibration, dict) else 0.0
    rel = rel if np.isfinite(rel) else 0.0
    height = np.mean([float(np.asarray(c.center)[2]) - level for c in (rig.left, rig.right)])
    return rel * max(height, 0.0)


def floor_level_std(rig: Rig, interface: Interface, floor_xy: np.ndarray) -> float:
    """The world frame's share of a level fixed by the floor (m): the floor's height error where its control
    points lie (world xy (k, 2), metres), from the frame's covariance that calibration recorded
    (`calibration["world_frame"]["frame_cov"]`: the origin board's tilt and height), divided by `n - 1`.

    With the floor as control the level is what puts the floor at z = 0; a floor that truly sits `e` higher
    there moves the level, as measured from the cameras, by `e / (n - 1)` (3 e in water). 0 when the rig
    has no such record or there are no floor points.
    """
    frame = rig.calibration.get("world_frame") if isinstance(rig.calibration, dict) else None
    if not isinstance(frame, dict) or "frame_cov" not in frame or len(floor_xy) == 0:
        return 0.0
    cov = np.asarray(frame["frame_cov"], dtype=np.float64)
    x, y = np.mean(np.asarray(floor_xy, dtype=np.float64), axis=0)
    gradient = np.array([y, -x, 0.0, 0.0, 0.0, 1.0])  # d z / d (w, v) of the moved frame at (x, y, 0)
    floor_std = float(np.sqrt(max(gradient @ cov @ gradient, 0.0)))
    n = float(interface.n_water) / float(interface.n_air)
    return floor_std / (n - 1.0)


@float64
def refine_rig(
    rig: Rig, left_pixels: np.ndarray, right_pixels: np.ndarray, level_guess: float,
    refine: Sequence[str] = ("water", "right-pose"), control: str | DEM | None = "floor", floor_z: float = 0.0,
    floor_band_m: float = 0.01, floor_sigma_m: float = 0.001, pixel_sigma: float = 0.3,
    robust_sigmas: float = 3.0, max_steps: int = 100, floor_region: tuple[float, float] | None = None,
    control_points: tuple[ArrayLike, ArrayLike, ArrayLike] | None = None, control_sigma_m: float = 0.001,
    dem_sigma_m: float = 0.002, level_tolerance_m: float = LEVEL_TOLERANCE_M,
) -> RefineResult:
    """Refine the water level (and optionally the interface tilt and the right camera's pose).

    **Arguments:**

    - `rig`: the calibrated rig; its interface (if any) gives the normal and the indices.
    - `left_pixels`, `right_pixels`: correspondences (n, 2), pixels.
    - `level_guess`: starting water level, metres.
    - `refine`: any of "water", "tilt", "right-pose" (three rotations, and two shifts of the right
      camera's centre across the baseline: the baseline's length, the survey's scale, stays as calibrated).
    - `control`: "floor" (correspondences near the lowest level are taken to lie on `z = floor_z`),
      a `DEM` (a dry survey of the same model: correspondences are taken to lie on it where they agree
      with it within 3 sigma at the solution, i.e. on the parts that did not move), or None (no control:
      the level may then be undetermined, and is reported so). Sigma is the larger of `floor_sigma_m`
      (floor) or `dem_sigma_m` (DEM) and the points' own robust scatter about the surface.
    - `floor_band_m`: how far above the lowest points a correspondence may sit to count as floor.
    - `floor_sigma_m`, `dem_sigma_m`, `pixel_sigma`: standard deviations (m, m, px) weighting the floor or
      DEM control against reprojection.
    - `robust_sigmas`: scale of the Cauchy loss, in standard deviations.
    - `floor_region`: (x_min, x_max) world metres where the floor is bare (e.g. in front of the toe).
    - `control_points`: `(left_pixels (k, 2), right_pixels (k, 2), xyz (k, 3))` points of known world
      coordinates (metres) seen in both images, with standard deviation `control_sigma_m`.
    - `level_tolerance_m`: the level counts as determined (`level_determined`) only when two of its standard
      deviations, its 95 % interval, are within this, metres.

    A single control plane (the floor) fixes the level only while the camera poses are fixed: with
    the right camera's rotation free too, the level trades against the cameras' convergence. Control
    points at several heights (or a dry survey) are then needed; the standard deviations say so.
    """
    start = time.perf_counter()
    if not (np.isfinite(level_tolerance_m) and level_tolerance_m > 0):
        raise JaxStereoError(f"the level tolerance must be a positive number of metres, got {level_tolerance_m!r}")
    which = _check_which(refine)
    pl, pr = _checked_pixels(left_pixels, right_pixels)
    model, guess = _build_model(rig, level_guess, which)
    check_camera_above(rig.left.center, guess, "left camera")
    check_camera_above(rig.right.center, guess, "right camera")
    inlier, points0 = _gate(model, guess, pl, pr)
    pl, pr, points0 = pl[inlier], pr[inlier], points0[inlier]
    in_region = np.ones(len(pl), bool)
    if floor_region is not None:
        in_region = (points0[:, 0] >= floor_region[0]) & (points0[:, 0] <= floor_region[1])
    mask, heights = _initial_control(control, points0, in_region, floor_z, floor_band_m, floor_region)
    gcp = _checked_control_points(control_points)
    data = _Data(model, pl, pr, gcp, pixel_sigma, control_sigma_m, robust_sigmas)
    base_sigma = dem_sigma_m if isinstance(control, DEM) else floor_sigma_m
    theta0 = jnp.zeros(model.size)
    start_outcomes = []
    if "water" in which and len(which) > 1:
        theta0, start_outcomes = _start_at_the_guessed_level(rig, level_guess, which, data, control, mask, heights,
                                                             in_region, base_sigma, floor_band_m, max_steps)
    theta, mask, heights, surface_sigma, outcomes, steps = _solve_and_reselect(
        data, theta0, control, mask, heights, in_region, base_sigma, floor_band_m, max_steps)
    problem = data.problem(mask, heights, surface_sigma)
    rms_before, rms_after = (_reprojection_rms(t, problem, len(pl)) for t in (jnp.zeros(model.size), theta))
    size = _padded_size(len(pl))
    groups = [np.concatenate([j * size + np.arange(len(pl)) for j in range(4)]), 4 * size + np.nonzero(mask)[0],
              5 * size + np.arange(3 * gcp[0].shape[0])]
    std = _standard_deviations(theta, problem, groups)
    right, interface = model.unpack(theta)
    std = np.maximum(std, _block_jackknife_std(theta, problem, pl, rig.image_size))
    frame_std = 0.0
    if "water" in which:
        floor_xy = points0[np.asarray(mask)[: len(points0)], :2] if isinstance(control, str) else np.zeros((0, 2))
        frame_std = float(np.hypot(scale_level_std(rig, float(interface.level)),
                                   floor_level_std(rig, interface, floor_xy)))
    right, interface, params = _parameters(model, which, theta, std, frame_std)
    level_std = params.get("water level (m)", (0.0, 0.0))[1]
    # The start's solves (the level held at the guess) only place the start: held 12 mm off on the POV-Ray flume
    # seen by its cameras turned 180 degrees, the pose-only solve stopped at its step limit while the full
    # refinement from there converged to the true level (0.005 mm off).
    converged = all(o == "converged" for o in outcomes)
    submerged = int(np.sum(data.points(theta)[:, 2] < float(interface.level)))
    if "water" in which and submerged < MIN_CORRESPONDENCES:
        log.warning("at the refined level (%.4f m) only %d correspondences lie under the water: the images do not "
                    "fix it there", float(interface.level), submerged)
    determined = bool(np.isfinite(level_std) and 2 * level_std <= level_tolerance_m and converged
                      and ("water" not in which or submerged >= MIN_CORRESPONDENCES))
    fit_std = float(std[0] * 1e-2) if "water" in which else float("nan")
    calibration = dict(rig.calibration)
    calibration["refine"] = {"parameters": {k_: list(v) for k_, v in params.items()},
                             "level_std_fit_m": fit_std, "level_std_frame_m": frame_std,
                             "level_determined": determined, "rms_before_px": rms_before, "rms_after_px": rms_after,
                             "correspondences": int(len(pl)),
                             "control_points": int(mask.sum()), "surface_sigma_m": surface_sigma,
                             "solver": outcomes[-1], "solves": outcomes, "start_solves": start_outcomes,
                             "converged": converged}
    refined = Rig(rig.left, right, interface, calibration)
    return RefineResult(refined, params, determined, rms_before, rms_after, int(len(pl)),
                        int(mask.sum()) + int(gcp[0].shape[0]), steps, outcomes[-1], time.perf_counter() - start,
                        surface_sigma, converged, fit_std, frame_std, submerged, tuple(outcomes))


def _start_at_the_guessed_level(rig, level_guess, which, data: _Data, control, mask, heights, in_region,
                                base_sigma, floor_band_m, max_steps):
    """The starting parameters of a refinement that frees the level with the pose (or tilt): the other
    parameters solved first with the level held at the guess, the level's own entry left at the guess.

    Started all at once from a camera bumped by a fraction of a degree, the solver can lower the level under
    every correspondence, where no point is refracted, the level moves nothing, and the step is zero: a
    stationary point that is no solution. With the pose settled first the level starts where the water is.

    **Returns:** `(theta0, outcomes)`: the full parameter vector and the first solves' outcomes in words.
    """
    rest = tuple(name for name in which if name != "water")
    model, _ = _build_model(rig, level_guess, rest)
    first = dataclasses.replace(data, model=model)
    theta, *_, outcomes, _ = _solve_and_reselect(first, jnp.zeros(model.size), control, mask, heights, in_region,
                                                 base_sigma, floor_band_m, max_steps)
    return jnp.concatenate([jnp.zeros(1), jnp.asarray(theta)]), outcomes


def _checked_pixels(left_pixels, right_pixels) -> tuple[np.ndarray, np.ndarray]:
    """Correspondences as (n, 2) float64 pixel arrays; `JaxStereoError` if they differ in number or are too few."""
    pl = np.asarray(left_pixels, dtype=np.float64).reshape(-1, 2)
    pr = np.asarray(right_pixels, dtype=np.float64).reshape(-1, 2)
    if pl.shape != pr.shape:
        raise JaxStereoError(f"{pl.shape[0]} left but {pr.shape[0]} right correspondences")
    if pl.shape[0] < MIN_CORRESPONDENCES:
        raise JaxStereoError(f"only {pl.shape[0]} correspondences; at least {MIN_CORRESPONDENCES} are needed")
    return pl, pr


def _checked_control_points(control_points) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`(left (k, 2), right (k, 2), xyz (k, 3))` float64 arrays of the control points (none: k = 0)."""
    if control_points is None:
        return _NO_GCP
    gcp = tuple(np.asarray(a, dtype=np.float64).reshape(-1, k) for a, k in zip(control_points, (2, 2, 3)))
    if not (gcp[0].shape[0] == gcp[1].shape[0] == gcp[2].shape[0]):
        raise JaxStereoError("control points: left pixels, right pixels and coordinates differ in number")
    return gcp


def _solve_and_reselect(data: "_Data", theta0, control, mask, heights, in_region, base_sigma: float,
                        floor_band_m: float, max_steps: int):
    """Solve, then twice re-select the control terms at the solution and solve again (with a control).

    **Returns:** `(theta, mask, heights, surface_sigma, outcomes, steps)`: the final parameters and control
    selection, the control's standard deviation (metres), each solve's outcome in words, the last's steps.
    """
    surface_sigma = base_sigma
    theta, outcome, steps = _solve(data.problem(mask, heights, surface_sigma), theta0, max_steps)
    outcomes = [outcome]
    for _ in range(2 if control is not None else 0):
        mask, heights, surface_sigma = _reselect(data, theta, control, in_region, heights, base_sigma,
                                                 surface_sigma, floor_band_m)
        theta, outcome, steps = _solve(data.problem(mask, heights, surface_sigma), theta, max_steps)
        outcomes.append(outcome)
    return theta, mask, heights, surface_sigma, outcomes, steps


def _reprojection_rms(theta, problem, n: int) -> float:
    """RMS reprojection error (pixels, per image coordinate pair) of the `n` live correspondences at `theta`."""
    size = _padded_size(n)
    live = np.tile(np.arange(size) < n, 4)
    residuals = np.asarray(_residuals_jit(theta, problem[0]))[:4 * size][live]
    return float(np.sqrt(np.mean(residuals**2) * 2))


@float64
def refine_problem(rig: Rig, left_pixels, right_pixels, level_guess: float, refine=("water", "right-pose"),
                   floor_mask=None, floor_sigma_m: float = 0.001, control_z=None):
    """The least-squares problem of `refine_rig` (for comparisons and benchmarks), with the surface
    control given explicitly: `floor_mask` (n,) marks the correspondences that are control terms, at
    heights `control_z` (n,) metres (default 0: the floor), standard deviation `floor_sigma_m`; no mask,
    no control.

    **Returns:** `(fn, theta0, args)` with `fn(theta, args)` the residual vector (in standard deviations,
    robust loss applied) that `refine_rig` minimises.
    """
    model, _ = _build_model(rig, level_guess, _check_which(refine))
    pl = jnp.asarray(np.asarray(left_pixels, dtype=np.float64))
    pr = jnp.asarray(np.asarray(right_pixels, dtype=np.float64))
    mask = jnp.zeros(pl.shape[0], bool) if floor_mask is None else jnp.asarray(floor_mask)
    heights = jnp.zeros(pl.shape[0]) if control_z is None else jnp.asarray(np.asarray(control_z, dtype=np.float64))
    args = (model, pl, pr, mask, heights, jnp.zeros((0, 2)), jnp.zeros((0, 2)), jnp.zeros((0, 3)))
    weights = jnp.concatenate([jnp.full(4 * pl.shape[0], 1.0 / 0.3), jnp.full(pl.shape[0], 1.0 / floor_sigma_m),
                               jnp.ones(N_PRIOR)])

    @float64
    def fn(theta, a):
        return _robust(_residuals(theta, a) * weights, 3.0)

    return fn, jnp.zeros(model.size), args
