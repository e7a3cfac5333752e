"""The stereo rig: two cameras in the world frame, the water interface once known, and its JSON file.

The rig file is one JSON object:

```
{
  "format": "jaxstereo-rig", "version": 1,
  "image_size": [width, height],                       # pixels, both cameras
  "left":  {"fx": .., "fy": .., "cx": .., "cy": ..,    # pixels
            "dist": [k1, k2, p1, p2, k3, k4, k5, k6],  # OpenCV order
            "R": [[..], [..], [..]], "t": [..]},       # world -> camera, metres
  "right": {...},
  "interface": null | {"normal": [nx, ny, nz], "level": h, "n_air": 1.0, "n_water": 1.333},
  "calibration": {...}                                 # residuals and provenance (free-form)
}
```

Numbers are written with Python's shortest round-trip repr, so a rig loads back bit for bit.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from .._app.io import write_text_atomic
from .._geometry.camera import Camera
from .._geometry.errors import JaxStereoError
from .._geometry.interface import Interface
from .._geometry.module import Module, field
from .._geometry.pose import Pose
from .._geometry.precision import float64
from .._geometry.types import PathLike

FORMAT = "jaxstereo-rig"
VERSION = 1


class Rig(Module):
    """A calibrated stereo rig, a `Module` like its cameras (a PyTree: equinox's `filter_jit` and `tree_at` work
    on it; the provenance dict's entries are leaves that are not arrays).

    **Fields:** `left`, `right` (`Camera`, world frame Z up); `interface` (`Interface` or None until the
    water level is known); `calibration` (dict of residuals and provenance, JSON-serialisable).
    """

    left: Camera
    right: Camera
    interface: Interface | None = None
    calibration: dict = field(default_factory=dict)

    def __check_init__(self):
        if not isinstance(self.left, Camera) or not isinstance(self.right, Camera):
            raise JaxStereoError("a rig's left and right must be Cameras")
        if self.interface is not None and not isinstance(self.interface, Interface):
            raise JaxStereoError(f"a rig's interface must be an Interface or None, got {type(self.interface).__name__}")

    @property
    def image_size(self) -> tuple[int, int]:
        """(width, height) pixels."""
        return self.left.image_size

    @property
    def baseline_m(self) -> float:
        """Distance between the camera centres, metres."""
        return float(np.linalg.norm(np.asarray(self.left.center) - np.asarray(self.right.center)))

    def with_interface(self, interface: Interface | None) -> "Rig":
        """The same rig with another interface."""
        return Rig(self.left, self.right, interface, self.calibration)


def _camera_to_dict(camera: Camera) -> dict:
    return {
        "fx": float(camera.fx), "fy": float(camera.fy), "cx": float(camera.cx), "cy": float(camera.cy),
        "dist": [float(v) for v in np.asarray(camera.dist)],
        "R": [[float(v) for v in row] for row in np.asarray(camera.pose.R)],
        "t": [float(v) for v in np.asarray(camera.pose.t)],
    }


def rig_to_dict(rig: Rig) -> dict:
    """The rig as a JSON-ready dict (the file format above)."""
    interface = None
    if rig.interface is not None:
        interface = {
            "normal": [float(v) for v in np.asarray(rig.interface.normal)],
            "level": float(rig.interface.level),
            "n_air": float(rig.interface.n_air),
            "n_water": float(rig.interface.n_water),
        }
    return {
        "format": FORMAT, "version": VERSION, "image_size": list(rig.image_size),
        "left": _camera_to_dict(rig.left), "right": _camera_to_dict(rig.right),
        "interface": interface, "calibration": rig.calibration,
    }


def save_rig(rig: Rig, path: PathLike) -> None:
    """Write the rig JSON to `path` atomically (temporary file, then rename)."""
    text = json.dumps(rig_to_dict(rig), indent=2, allow_nan=False, default=_json_default)
    write_text_atomic(path, text + "\n")


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def _number(d: dict, key: str, where: str, source: str) -> float:
    if key not in d:
        raise JaxStereoError(f"rig {source}: field {where}.{key} is missing")
    value = d[key]
    if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value):
        raise JaxStereoError(f"rig {source}: field {where}.{key} must be a finite number, got {value!r}")
    return float(value)


def _numbers(d: dict, key: str, where: str, source: str, shape) -> np.ndarray:
    if key not in d:
        raise JaxStereoError(f"rig {source}: field {where}.{key} is missing")
    try:
        arr = np.asarray(d[key], dtype=np.float64)
    except (TypeError, ValueError):
        raise JaxStereoError(f"rig {source}: field {where}.{key} must be numbers, got {d[key]!r}") from None
    if shape is not None and arr.shape != shape:
        raise JaxStereoError(f"rig {source}: field {where}.{key} must have shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise JaxStereoError(f"rig {source}: field {where}.{key} contains NaN or infinite values")
    return arr


def _camera_from_dict(d, name: str, image_size, source: str) -> Camera:
    if not isinstance(d, dict):
        raise JaxStereoError(f"rig {source}: field {name} is missing or not an object")
    fx, fy, cx, cy = (_number(d, k, name, source) for k in ("fx", "fy", "cx", "cy"))
    dist = _numbers(d, "dist", name, source, None)
    if dist.ndim != 1 or dist.size > 8:
        raise JaxStereoError(f"rig {source}: field {name}.dist must be a list of at most 8 numbers")
    R = _numbers(d, "R", name, source, (3, 3))
    t = _numbers(d, "t", name, source, (3,))
    try:
        return Camera(fx, fy, cx, cy, dist, Pose(R, t), image_size)
    except JaxStereoError as err:
        raise JaxStereoError(f"rig {source}: {name}: {err}") from None


@float64
def rig_from_dict(data: dict, source: str = "<dict>") -> Rig:
    """Build a `Rig` from the JSON dict; `JaxStereoError` names any missing or bad field."""
    if not isinstance(data, dict):
        raise JaxStereoError(f"rig {source}: not a JSON object")
    if data.get("format") != FORMAT:
        raise JaxStereoError(f"rig {source}: field format must be {FORMAT!r}, got {data.get('format')!r}")
    size = _numbers(data, "image_size", "rig", source, (2,))
    if np.any(size <= 0) or np.any(size != np.round(size)):
        raise JaxStereoError(f"rig {source}: field image_size must be two positive integers")
    image_size = (int(size[0]), int(size[1]))
    left = _camera_from_dict(data.get("left"), "left", image_size, source)
    right = _camera_from_dict(data.get("right"), "right", image_size, source)
    interface = None
    itf = data.get("interface")
    if itf is not None:
        if not isinstance(itf, dict):
            raise JaxStereoError(f"rig {source}: field interface must be an object or null")
        try:
            interface = Interface(
                _number(itf, "level", "interface", source),
                _numbers(itf, "normal", "interface", source, (3,)),
                _number(itf, "n_air", "interface", source),
                _number(itf, "n_water", "interface", source),
            )
        except JaxStereoError as err:
            raise JaxStereoError(f"rig {source}: {err}") from None
    return Rig(left, right, interface, dict(data.get("calibration") or {}))


def load_rig(path: PathLike) -> Rig:
    """Read a rig JSON file; `JaxStereoError` names the file and the field that is wrong."""
    path = Path(path)
    if not path.is_file():
        raise JaxStereoError(f"rig file {str(path)!r} does not exist")
    try:
        data = json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise JaxStereoError(f"rig file {str(path)!r} is not valid JSON ({err})") from None
    return rig_from_dict(data, str(path))
