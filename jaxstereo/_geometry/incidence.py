"""What the first-order model costs: its error versus incidence angle, in angle, pixels and millimetres."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from .camera import Camera
from .errors import JaxStereoError
from .first_order import (
    backproject_first_order,
    project_first_order,
    refraction_angle_exact,
    refraction_angle_first_order,
)
from .interface import N_AIR, N_WATER, Interface
from .pose import Pose
from .precision import float64
from .refraction import backproject_refracted, project_refracted
from .triangulate import triangulate_rays
from .types import PathLike


@dataclasses.dataclass(frozen=True)
class IncidenceRig:
    """A nadir stereo rig for the incidence study (defaults: the paper's rig at 2496x1664).

    **Fields:** `height_m` camera height above the water, `depth_m` point depth below the water,
    `baseline_m` camera separation along X, `focal_px` focal length in pixels, `image_size` (w, h),
    `n_air`, `n_water` refractive indices; `disparity_noise_px` the matching's disparity standard deviation,
    pixels, for the predicted vertical std (default 0.15: the median `reconstruct` measures on the POV-Ray
    development flume's boards; a survey's summary gives yours as `median_sigma_disparity_px`).
    """

    height_m: float = 2.0
    depth_m: float = 0.3
    baseline_m: float = 0.16
    focal_px: float = 3935.0
    image_size: tuple[int, int] = (2496, 1664)
    n_air: float = N_AIR
    n_water: float = N_WATER
    disparity_noise_px: float = 0.15

    def __post_init__(self):
        for name in ("height_m", "depth_m", "baseline_m", "focal_px", "n_air", "n_water", "disparity_noise_px"):
            value = getattr(self, name)
            if not np.isfinite(value) or value <= 0:
                raise JaxStereoError(f"{name} must be positive, got {value}")


@dataclasses.dataclass(frozen=True)
class IncidenceReport:
    """Columns of the incidence study, one row per incidence angle.

    **Fields** (each an array (n,)): `incidence_deg` the ray's incidence at the rig centre;
    `exact_deg` / `first_order_deg` refraction angles; `angle_error_deg` their difference;
    `pixel_error_px` displacement in the left image between first-order and exact projection of the
    same underwater point; `error_3d_mm` distance from the truth of the point triangulated with the
    first-order model from its exact pixels; `vertical_error_mm` its Z component (signed);
    `in_frame` whether the point is inside the left image; `sigma_z_mm` (d, n) the predicted vertical
    standard deviation of an exactly triangulated point at each of `sigma_depths_m` (d,) metres below the water,
    from the rig's disparity noise (JAX derivative of the exact refracted triangulation). `rig` holds the
    geometry.
    """

    incidence_deg: np.ndarray
    exact_deg: np.ndarray
    first_order_deg: np.ndarray
    angle_error_deg: np.ndarray
    pixel_error_px: np.ndarray
    error_3d_mm: np.ndarray
    vertical_error_mm: np.ndarray
    in_frame: np.ndarray
    rig: IncidenceRig
    sigma_depths_m: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    sigma_z_mm: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 0)))

    def first_exceeding(self, column: str, threshold: float) -> float | None:
        """Smallest incidence (degrees) whose `column` exceeds `threshold` in absolute value, or None."""
        values = np.abs(getattr(self, column))
        above = np.nonzero(values > threshold)[0]
        return float(self.incidence_deg[above[0]]) if above.size else None

    def to_markdown(self) -> str:
        """The table as GitHub Markdown."""
        head = ("| incidence (deg) | exact (deg) | first-order (deg) | angle error (deg) | pixel error (px) "
                "| 3-D error (mm) | vertical error (mm) | in frame |"
                + "".join(f" sigma_z at {d:g} m (mm) |" for d in self.sigma_depths_m))
        lines = [head, "|" + "---:|" * 7 + ":---:|" + "---:|" * len(self.sigma_depths_m)]
        for i in range(self.incidence_deg.size):
            lines.append(
                f"| {self.incidence_deg[i]:.1f} | {self.exact_deg[i]:.3f} | {self.first_order_deg[i]:.3f} "
                f"| {self.angle_error_deg[i]:.3f} | {self.pixel_error_px[i]:.2f} | {self.error_3d_mm[i]:.2f} "
                f"| {self.vertical_error_mm[i]:+.2f} | {'yes' if self.in_frame[i] else 'no'} |"
                + "".join(f" {self.sigma_z_mm[k, i]:.2f} |" for k in range(len(self.sigma_depths_m)))
            )
        return "\n".join(lines)


def _nadir_camera(center, rig: IncidenceRig) -> Camera:
    w, h = rig.image_size
    pose = Pose.look_at(center, np.asarray(center) - np.array([0.0, 0.0, 1.0]))
    return Camera(rig.focal_px, rig.focal_px, (w - 1) / 2.0, (h - 1) / 2.0, np.zeros(5), pose, rig.image_size)


@float64
def incidence_report(incidence_deg: Sequence[float] | np.ndarray | None = None, rig: IncidenceRig | None = None,
                     sigma_depths_m: Sequence[float] | np.ndarray | None = None) -> IncidenceReport:
    """Measure the first-order model against exact Snell refraction over incidence angles.

    The water surface is the plane z = 0 with a vertical normal; two nadir cameras sit `height_m`
    above it, `baseline_m` apart along X. For each incidence angle the underwater point is the one at
    `depth_m` that a ray from the rig centre reaches at that incidence (offset along X).

    **Arguments:**

    - `incidence_deg`: angles in degrees (n,); default 0 to 40 in steps of 5.
    - `rig`: an `IncidenceRig`; default the paper's.
    - `sigma_depths_m`: depths below the water (metres) at which to predict the vertical std; default a third,
      two thirds and all of `rig.depth_m`.

    **Returns:** an `IncidenceReport`.
    """
    rig = rig or IncidenceRig()
    if incidence_deg is None:
        incidence_deg = np.arange(0.0, 40.0 + 1e-9, 5.0)
    inc = np.atleast_1d(np.asarray(incidence_deg, dtype=np.float64))
    if inc.size == 0 or np.any(~np.isfinite(inc)) or np.any(inc < 0) or np.any(inc >= 90):
        raise JaxStereoError("incidence_deg must be a non-empty list of angles in [0, 90) degrees")
    n = rig.n_water / rig.n_air
    theta = np.deg2rad(inc)
    exact = np.asarray(refraction_angle_exact(jnp.asarray(theta), n))
    approx = np.asarray(refraction_angle_first_order(jnp.asarray(theta), n))

    interface = Interface(0.0, n_air=rig.n_air, n_water=rig.n_water)
    half = rig.baseline_m / 2.0
    left = _nadir_camera([-half, 0.0, rig.height_m], rig)
    right = _nadir_camera([half, 0.0, rig.height_m], rig)
    offset = rig.height_m * np.tan(theta) + rig.depth_m * np.tan(exact)
    points = np.stack([offset, np.zeros_like(offset), np.full_like(offset, -rig.depth_m)], axis=-1)
    points = jnp.asarray(points)

    px_left, _ = project_refracted(left, interface, points)
    px_right, _ = project_refracted(right, interface, points)
    fo_left, _ = project_first_order(left, interface, points)
    o_l, d_l, _ = backproject_first_order(left, interface, px_left)
    o_r, d_r, _ = backproject_first_order(right, interface, px_right)
    estimate, _ = triangulate_rays(o_l, d_l, o_r, d_r)
    err = np.asarray(estimate - points)
    px = np.asarray(px_left)
    w, h = rig.image_size
    in_frame = (px[:, 0] >= -0.5) & (px[:, 0] <= w - 0.5) & (px[:, 1] >= -0.5) & (px[:, 1] <= h - 0.5)
    return IncidenceReport(
        incidence_deg=inc,
        exact_deg=np.rad2deg(exact),
        first_order_deg=np.rad2deg(approx),
        angle_error_deg=np.rad2deg(approx - exact),
        pixel_error_px=np.linalg.norm(np.asarray(fo_left - px_left), axis=-1),
        error_3d_mm=1e3 * np.linalg.norm(err, axis=-1),
        vertical_error_mm=1e3 * err[:, 2],
        in_frame=in_frame,
        rig=rig,
        **_predicted_sigma_z(rig, theta, exact, interface, left, right, sigma_depths_m),
    )


def _predicted_sigma_z(rig: IncidenceRig, theta, exact, interface, left: Camera, right: Camera, depths) -> dict:
    """`{"sigma_depths_m", "sigma_z_mm"}`: the vertical std (d, n) of points at each depth and incidence, from the
    derivative of the exact refracted triangulation with respect to the right pixel along the rows."""
    depths = np.asarray(depths if depths is not None else rig.depth_m * np.array([1 / 3, 2 / 3, 1.0]), dtype=np.float64)
    if depths.ndim != 1 or np.any(~np.isfinite(depths)) or np.any(depths <= 0):
        raise JaxStereoError(f"sigma_depths_m must be positive depths in metres, got {depths}")

    def height(px_left, px_right):
        o_l, d_l, _ = backproject_refracted(left, interface, px_left)
        o_r, d_r, _ = backproject_refracted(right, interface, px_right)
        return triangulate_rays(o_l, d_l, o_r, d_r)[0][..., 2]

    rows = []
    for depth in depths:
        offset = rig.height_m * np.tan(theta) + depth * np.tan(exact)
        points = jnp.asarray(np.stack([offset, np.zeros_like(offset), np.full_like(offset, -depth)], axis=-1))
        px_left, _ = project_refracted(left, interface, points)
        px_right, _ = project_refracted(right, interface, points)
        tangent = jnp.zeros_like(px_right).at[:, 0].set(1.0)
        _, dz = jax.jvp(lambda p: height(px_left, p), (px_right,), (tangent,))
        rows.append(1e3 * rig.disparity_noise_px * np.abs(np.asarray(dz)))
    return {"sigma_depths_m": depths, "sigma_z_mm": np.stack(rows)}


def plot_incidence_report(report: IncidenceReport, path: PathLike) -> None:
    """Save a three-panel PNG (angle, pixel and 3-D error versus incidence) to `path`, atomically."""
    from .._app.plots import new_figure, save_figure

    fig, axes = new_figure(1, 4, figsize=(17, 3.8))
    x = report.incidence_deg
    panels = [
        (report.angle_error_deg, "refraction-angle error (deg)", 0.5, "deg"),
        (report.pixel_error_px, "pixel displacement, left image (px)", 1.0, "px"),
        (report.error_3d_mm, f"3-D error at {report.rig.depth_m:g} m depth (mm)", 1.0, "mm"),
    ]
    for ax, (y, label, limit, unit) in zip(axes[:3], panels):
        ax.plot(x, y, "o-", color="tab:blue")
        ax.axhline(limit, color="tab:red", lw=0.8, ls="--", label=f"{limit:g} {unit}")
        ax.axvline(20.0, color="0.4", lw=0.8, ls=":", label="20 deg (paper's limit)")
        ax.set_xlabel("incidence angle (deg)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    for k, depth in enumerate(report.sigma_depths_m):
        axes[3].plot(x, report.sigma_z_mm[k], "o-", label=f"{depth:g} m deep")
    axes[3].axvline(20.0, color="0.4", lw=0.8, ls=":")
    axes[3].set_xlabel("incidence angle (deg)")
    axes[3].set_ylabel(f"predicted sigma_z, exact model (mm)\nat {report.rig.disparity_noise_px:g} px of disparity noise")
    axes[3].grid(alpha=0.3)
    axes[3].legend(fontsize=8)
    rig = report.rig
    fig.suptitle(
        f"First-order (virtual camera) vs exact Snell: n = {rig.n_water / rig.n_air:.3f}, camera {rig.height_m:g} m "
        f"above water, baseline {rig.baseline_m:g} m, f = {rig.focal_px:g} px"
    )
    save_figure(fig, path)
