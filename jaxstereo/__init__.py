"""jaxstereo: refraction-aware stereo photogrammetry in JAX.

The public API is exactly what this file re-exports.
"""

from ._camera import (
    Camera as Camera,
    distort_normalized as distort_normalized,
    undistort_normalized as undistort_normalized,
)
from ._errors import JaxStereoError as JaxStereoError
from ._first_order import (
    backproject_first_order as backproject_first_order,
    first_order_homography as first_order_homography,
    project_first_order as project_first_order,
    refraction_angle_exact as refraction_angle_exact,
    refraction_angle_first_order as refraction_angle_first_order,
    virtual_camera as virtual_camera,
)
from ._incidence import (
    IncidenceReport as IncidenceReport,
    IncidenceRig as IncidenceRig,
    incidence_report as incidence_report,
    plot_incidence_report as plot_incidence_report,
)
from ._interface import Interface as Interface, tilt_normal as tilt_normal
from ._pose import Pose as Pose, so3_exp as so3_exp, so3_log as so3_log
from ._precision import float64 as float64
from ._refraction import (
    backproject_refracted as backproject_refracted,
    intersect_plane as intersect_plane,
    optical_path_length as optical_path_length,
    project_refracted as project_refracted,
    refract_directions as refract_directions,
    refraction_points as refraction_points,
)
from ._triangulate import triangulate_rays as triangulate_rays

__version__ = "0.1.0"
