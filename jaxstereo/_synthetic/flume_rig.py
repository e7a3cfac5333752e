"""Stereo rigs from physical parameters: the synthetic flume's cameras."""

from __future__ import annotations

import dataclasses

import numpy as np

from .._geometry.camera import Camera
from .._geometry.errors import JaxStereoError
from .._geometry.pose import Pose


@dataclasses.dataclass(frozen=True)
class RigSpec:
    """A two-camera rig above a flume, described as a lab would.

    **Fields:**

    - `focal_mm`, `sensor_width_mm`: lens focal length and sensor width, millimetres.
    - `image_size`: (width, height) pixels.
    - `camera_height_m`: height of the camera centres above the water level, metres.
    - `water_level_m`: the water level (world Z, metres) that the camera height is measured from.
    - `baseline_m`: distance between the camera centres along world X, metres.
    - `center_xy_m`: world (x, y) of the point midway between the cameras, metres.
    - `tilt_deg`: both optical axes tilted from nadir towards +Y (a rotation about world X), degrees.
    - `convergence_deg`: toe-in of each camera towards the other (about world Y), degrees.
    - `dist`: OpenCV distortion coefficients shared by both cameras (k1, k2, p1, p2, k3), or zeros.
    - `misalignment_deg`: per camera (left, right), small rotations (about the camera's x, y, z axes,
      degrees) applied after the nominal pose: real rigs are never exactly parallel.
    """

    focal_mm: float = 35.0
    sensor_width_mm: float = 22.2
    image_size: tuple[int, int] = (1728, 1152)
    camera_height_m: float = 2.0
    water_level_m: float = 0.18
    baseline_m: float = 0.16
    center_xy_m: tuple[float, float] = (0.0, 0.0)
    tilt_deg: float = 0.0
    convergence_deg: float = 0.0
    dist: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)
    misalignment_deg: tuple[tuple[float, float, float], tuple[float, float, float]] = ((0.0, 0.0, 0.0),
                                                                                      (0.0, 0.0, 0.0))

    def __post_init__(self):
        for name in ("focal_mm", "sensor_width_mm", "camera_height_m", "baseline_m"):
            value = getattr(self, name)
            if not np.isfinite(value) or value <= 0:
                raise JaxStereoError(f"rig {name} must be positive, got {value}")
        if min(self.image_size) <= 0:
            raise JaxStereoError(f"rig image_size must be positive, got {self.image_size}")

    @property
    def focal_px(self) -> float:
        """Focal length in pixels."""
        return self.focal_mm / self.sensor_width_mm * self.image_size[0]

    def scaled(self, image_size: tuple[int, int]) -> "RigSpec":
        """The same rig with another image size (the sensor and lens unchanged)."""
        return dataclasses.replace(self, image_size=tuple(image_size))


def _rot_x(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _rot_y(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rot_z(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def realistic_rig_spec(**overrides) -> RigSpec:
    """The paper's rig as it is really mounted: each camera tilted and turned by 0.3-0.7 degrees, a 35 mm
    lens's radial distortion (k1 -0.08, k2 0.12). Fields can be overridden."""
    spec = RigSpec(dist=(-0.08, 0.12, 0.0, 0.0, 0.0), misalignment_deg=((0.4, -0.3, 0.6), (-0.5, 0.7, -0.35)))
    return dataclasses.replace(spec, **overrides)


def jpeg(image: np.ndarray, quality: int = 95) -> np.ndarray:
    """The image as a camera saves it: through JPEG at `quality` (RGB or grey uint8 in and out)."""
    import cv2

    ok, data = cv2.imencode(".jpg", image[..., ::-1] if image.ndim == 3 else image, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise JaxStereoError("JPEG encoding failed")
    out = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    return out[..., ::-1].copy() if out.ndim == 3 else out


def flume_rig(spec: RigSpec = RigSpec()) -> tuple[Camera, Camera]:
    """The left and right cameras of a rig spec (left at -X, image x along world X when nadir).

    **Returns:** `(left, right)` cameras in the world frame (Z up).
    """
    w, h = spec.image_size
    f = spec.focal_px
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    nadir = np.diag([1.0, -1.0, -1.0])  # rows: camera x, y, z axes in world coordinates
    tilt = _rot_x(np.deg2rad(spec.tilt_deg))
    cams = []
    for sign, (ax, ay, az) in zip((-1.0, 1.0), spec.misalignment_deg):
        center = np.array([spec.center_xy_m[0] + sign * spec.baseline_m / 2, spec.center_xy_m[1],
                           spec.water_level_m + spec.camera_height_m])
        toe_in = _rot_y(sign * np.deg2rad(spec.convergence_deg))
        R = nadir @ (tilt @ toe_in).T
        R = _rot_x(np.deg2rad(ax)) @ _rot_y(np.deg2rad(ay)) @ _rot_z(np.deg2rad(az)) @ R
        cams.append(Camera(f, f, cx, cy, np.asarray(spec.dist, dtype=np.float64), Pose.from_center(R, center),
                           spec.image_size))
    return cams[0], cams[1]
