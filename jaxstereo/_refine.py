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

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ._camera import Camera
from ._errors import JaxStereoError
from ._grid import DEM
from ._interface import Interface, check_camera_above, tilt_normal
from ._precision import float64
from ._refraction import intersect_plane, project_refracted, refract_directions
from ._rig import Rig
from ._triangulate import triangulate_rays

log = logging.getLogger("jaxstereo")

PARAMETERS = ("water", "tilt", "right-pose")
MIN_CORRESPONDENCES = 12
# A parameter whose standard deviation exceeds this is reported as not determined.
LEVEL_STD_LIMIT_M = 0.002


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
    across = jnp.asarray(np.stack([e1, np.cross(baseline, e1)]))
    model = _Model(rig.left, rig.right, jnp.asarray(float(level_guess)), tilt0, jnp.asarray(n_air),
                   jnp.asarray(n_water), across, which)
    return model, Interface(float(level_guess), normal, n_air, n_water)


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
    """Reprojection residuals (pixels, both images), floor residuals (metres, 0 off the floor), then
    control-point residuals (metres, 3 per point)."""
    model, pl, pr, control_mask, control_z, gcp_l, gcp_r, gcp_xyz = args
    right, interface = model.unpack(theta)
    points = _triangulate_any(model.left, right, interface, pl, pr)
    ql, _ = project_refracted(model.left, interface, points)
    qr, _ = project_refracted(right, interface, points)
    reproj = jnp.concatenate([(ql - pl).ravel(), (qr - pr).ravel()])
    control = jnp.where(control_mask, points[:, 2] - control_z, 0.0)
    gcp = _triangulate_any(model.left, right, interface, gcp_l, gcp_r) - gcp_xyz
    return jnp.concatenate([reproj, control, gcp.ravel()])


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
    in user units (level m, tilt deg, rotation deg, translation mm); `level_determined` whether the water
    level's standard deviation is below 2 mm; `rms_before_px`, `rms_after_px` reprojection RMS of the
    inliers; `n_correspondences`, `n_control`; `steps` solver steps; `result` the last solve's outcome in
    words ("converged", "stopped at its step limit", "diverged", ...), `converged` whether every solve
    converged; `seconds`; `surface_sigma_m` the standard deviation given to the floor or DEM control terms
    (the larger of the one asked for and the points' own scatter about the surface), metres.
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


def _check_which(refine) -> tuple[str, ...]:
    which = tuple(dict.fromkeys(refine))
    for name in which:
        if name not in PARAMETERS:
            raise JaxStereoError(f"cannot refine {name!r}: choose from {', '.join(PARAMETERS)}")
    if not which:
        raise JaxStereoError("nothing to refine")
    return which


@float64
def refine_rig(
    rig: Rig, left_pixels: np.ndarray, right_pixels: np.ndarray, level_guess: float,
    refine=("water", "right-pose"), control: str | None = "floor", floor_z: float = 0.0,
    floor_band_m: float = 0.01, floor_sigma_m: float = 0.001, pixel_sigma: float = 0.3,
    robust_sigmas: float = 3.0, max_steps: int = 100, floor_region: tuple[float, float] | None = None,
    control_points=None, control_sigma_m: float = 0.001, dem_sigma_m: float = 0.002,
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

    A single control plane (the floor) fixes the level only while the camera poses are fixed: with
    the right camera's rotation free too, the level trades against the cameras' convergence. Control
    points at several heights (or a dry survey) are then needed; the standard deviations say so.
    """
    start = time.perf_counter()
    which = _check_which(refine)
    pl = np.asarray(left_pixels, dtype=np.float64).reshape(-1, 2)
    pr = np.asarray(right_pixels, dtype=np.float64).reshape(-1, 2)
    if pl.shape != pr.shape:
        raise JaxStereoError(f"{pl.shape[0]} left but {pr.shape[0]} right correspondences")
    if pl.shape[0] < MIN_CORRESPONDENCES:
        raise JaxStereoError(f"only {pl.shape[0]} correspondences; at least {MIN_CORRESPONDENCES} are needed")
    model, guess = _build_model(rig, level_guess, which)
    check_camera_above(rig.left.center, guess, "left camera")
    check_camera_above(rig.right.center, guess, "right camera")
    tilt0 = model.tilt0

    # Inliers: consistent with the refracted epipolar geometry of the guess (loose: the guess is rough).
    pl_j, pr_j = jnp.asarray(pl), jnp.asarray(pr)
    points0 = np.asarray(_triangulate_any(rig.left, rig.right, guess, pl_j, pr_j))
    no_gcp = (jnp.zeros((0, 2)), jnp.zeros((0, 2)), jnp.zeros((0, 3)))
    err0 = np.asarray(_residuals(jnp.zeros(model.size), (model, pl_j, pr_j, jnp.zeros(len(pl), bool),
                                                         jnp.zeros(len(pl)), *no_gcp))[: 4 * len(pl)])
    err0 = np.linalg.norm(err0.reshape(2, -1, 2), axis=-1).max(axis=0)
    inlier = np.isfinite(err0) & (err0 < 5.0) & np.all(np.isfinite(points0), axis=1)
    if inlier.sum() < MIN_CORRESPONDENCES:
        raise JaxStereoError(f"only {int(inlier.sum())} correspondences agree with the rig's epipolar geometry; "
                             f"at least {MIN_CORRESPONDENCES} are needed")
    pl, pr, points0 = pl[inlier], pr[inlier], points0[inlier]
    mask = np.zeros(len(pl), bool)
    in_region = np.ones(len(pl), bool)
    if floor_region is not None:
        in_region = (points0[:, 0] >= floor_region[0]) & (points0[:, 0] <= floor_region[1])
    control_z = np.full(len(pl), float(floor_z))
    surface_sigma = floor_sigma_m
    if isinstance(control, DEM):
        control_z = dem_heights(control, points0[:, :2])
        mask = in_region & np.isfinite(control_z)
        if not mask.any():
            p_lo, p_hi = points0[:, :2].min(axis=0), points0[:, :2].max(axis=0)
            raise JaxStereoError(
                f"the control DEM (x {control.x[0]:.3f} to {control.x[-1]:.3f} m, y {control.y[0]:.3f} to "
                f"{control.y[-1]:.3f} m) does not overlap the correspondences (x {p_lo[0]:.3f} to {p_hi[0]:.3f} m, "
                f"y {p_lo[1]:.3f} to {p_hi[1]:.3f} m): is it in the same world frame?")
        control_z = np.where(mask, control_z, 0.0)
        surface_sigma = dem_sigma_m
    elif control == "floor":
        lowest = np.percentile(points0[in_region, 2], 2) if in_region.any() else np.inf
        mask = in_region & (points0[:, 2] <= lowest + floor_band_m)
    elif control is not None:
        raise JaxStereoError(f"unknown control {control!r}: use 'floor', a DEM or None")
    if control_points is not None:
        gcp = tuple(jnp.asarray(np.asarray(a, dtype=np.float64).reshape(-1, k))
                    for a, k in zip(control_points, (2, 2, 3)))
        if not (gcp[0].shape[0] == gcp[1].shape[0] == gcp[2].shape[0]):
            raise JaxStereoError("control points: left pixels, right pixels and coordinates differ in number")
    else:
        gcp = no_gcp
    args = (model, jnp.asarray(pl), jnp.asarray(pr), jnp.asarray(mask), jnp.asarray(control_z), *gcp)
    n_reproj = 4 * len(pl)

    def weights_for(sigma):
        return jnp.concatenate([jnp.full(n_reproj, 1.0 / pixel_sigma), jnp.full(len(pl), 1.0 / sigma),
                                jnp.full(3 * gcp[0].shape[0], 1.0 / control_sigma_m)])

    def fn(theta, problem):
        # Residuals in units of their standard deviations, then a Cauchy loss at `robust_sigmas`.
        a, weights = problem
        return _robust(_residuals(theta, a) * weights, robust_sigmas)

    theta0 = jnp.zeros(model.size)
    solver = optx.LevenbergMarquardt(rtol=1e-10, atol=1e-10)
    sol = optx.least_squares(fn, solver, theta0, (args, weights_for(surface_sigma)), max_steps=max_steps, throw=False)
    outcomes = [result_in_words(sol.result)]
    theta = sol.value
    base_sigma = surface_sigma
    if control is not None:
        # Re-select the control with the refined geometry and solve again, twice. The control's standard
        # deviation is the larger of the given one and the scatter of the points about the surface (their
        # depth noise from the pixels): too tight a value would cut the noise distribution and bias the level.
        for _ in range(2):
            right, interface = model.unpack(theta)
            points = np.asarray(_triangulate_any(model.left, right, interface, args[1], args[2]))
            if isinstance(control, DEM):
                control_z = dem_heights(control, points[:, :2])
            d = points[:, 2] - control_z
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
            args = (model, args[1], args[2], jnp.asarray(mask), jnp.asarray(np.where(mask, control_z, 0.0)), *args[5:])
            sol = optx.least_squares(fn, solver, theta, (args, weights_for(surface_sigma)), max_steps=max_steps,
                                     throw=False)
            outcomes.append(result_in_words(sol.result))
            theta = sol.value
    problem = (args, weights_for(surface_sigma))
    raw_before = np.asarray(_residuals(theta0, args))[:n_reproj]
    raw_after = np.asarray(_residuals(theta, args))[:n_reproj]
    rms_before = float(np.sqrt(np.mean(raw_before**2) * 2))
    rms_after = float(np.sqrt(np.mean(raw_after**2) * 2))

    # Gauss-Newton covariance at the solution, scaled by the residual variance.
    J = np.asarray(jax.jacfwd(fn)(theta, problem))
    r = np.asarray(fn(theta, problem))
    dof = max(1, r.size - theta.size)
    sigma2 = float(r @ r) / dof
    try:
        cov = np.linalg.inv(J.T @ J) * sigma2
        std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    except np.linalg.LinAlgError:
        std = np.full(theta.size, np.inf)
    right, interface = model.unpack(theta)
    params = {}
    k = 0
    values = np.asarray(theta)
    if "water" in which:
        params["water level (m)"] = (float(interface.level), float(std[k] * 1e-2))
        k += 1
    if "tilt" in which:
        t = np.asarray(tilt0) + values[k : k + 2] * 1e-3
        params["tilt x (deg)"] = (float(np.rad2deg(t[0])), float(np.rad2deg(std[k] * 1e-3)))
        params["tilt y (deg)"] = (float(np.rad2deg(t[1])), float(np.rad2deg(std[k + 1] * 1e-3)))
        k += 2
    if "right-pose" in which:
        for i, axis in enumerate("xyz"):
            params[f"right rotation {axis} (deg)"] = (float(np.rad2deg(values[k + i] * 1e-3)),
                                                      float(np.rad2deg(std[k + i] * 1e-3)))
        for i, axis in enumerate("12"):
            params[f"right shift across baseline {axis} (mm)"] = (float(values[k + 3 + i]), float(std[k + 3 + i]))
    level_std = params.get("water level (m)", (0.0, 0.0))[1]
    converged = all(o == "converged" for o in outcomes)
    determined = bool(np.isfinite(level_std) and level_std < LEVEL_STD_LIMIT_M and converged)
    calibration = dict(rig.calibration)
    calibration["refine"] = {"parameters": {k_: list(v) for k_, v in params.items()},
                             "level_determined": determined, "rms_before_px": rms_before, "rms_after_px": rms_after,
                             "correspondences": int(len(pl)), "control_points": int(mask.sum()),
                             "surface_sigma_m": surface_sigma, "solver": outcomes[-1], "converged": converged}
    refined = Rig(rig.left, right, interface, calibration)
    return RefineResult(refined, params, determined, rms_before, rms_after, int(len(pl)),
                        int(mask.sum()) + int(gcp[0].shape[0]),
                        int(sol.stats["num_steps"]), outcomes[-1], time.perf_counter() - start, surface_sigma, converged)


def dem_heights(dem: DEM, xy: np.ndarray) -> np.ndarray:
    """Bilinear height (metres) of a DEM at world points `xy` (n, 2); NaN outside it or next to a hole."""
    from scipy.interpolate import RegularGridInterpolator

    interp = RegularGridInterpolator((dem.y, dem.x), dem.z, method="linear", bounds_error=False, fill_value=np.nan)
    return interp(np.column_stack([xy[:, 1], xy[:, 0]]))


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
    weights = jnp.concatenate([jnp.full(4 * pl.shape[0], 1.0 / 0.3), jnp.full(pl.shape[0], 1.0 / floor_sigma_m)])

    def fn(theta, a):
        return _robust(_residuals(theta, a) * weights, 3.0)

    return fn, jnp.zeros(model.size), args
