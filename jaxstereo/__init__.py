"""jaxstereo: refraction-aware stereo photogrammetry in JAX.

The public API is exactly what this file names. Each name is imported when first used (PEP 562), so that
the command line starts without loading what its command does not need (matplotlib, the synthetic
renderer, the batch machinery); `from jaxstereo import X` and `jaxstereo.X` work as with eager imports.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

_PUBLIC: dict[str, tuple[str, ...]] = {
    "_app.batch": ("BatchResult", "run_batch"),
    "_app.batch_job": ("run_pair",),
    "_app.images": ("read_image", "write_image"),
    "_app.manifest": ("Manifest", "PairEntry", "load_manifest"),
    "_calibration.boards": ("BoardSpec",),
    "_calibration.calibration": (
        "CameraCalibration", "StereoCalibration", "calibrate_camera", "calibrate_stereo", "detect_all",
        "world_frame_rig",
    ),
    "_calibration.detect": ("Detection", "detect_board"),
    "_calibration.rig": ("Rig", "load_rig", "save_rig"),
    "_geometry.camera": ("Camera", "distort_normalized", "undistort_normalized"),
    "_geometry.errors": ("JaxStereoError",),
    "_geometry.first_order": (
        "backproject_first_order", "first_order_homography", "project_first_order", "refraction_angle_exact",
        "refraction_angle_first_order", "virtual_camera",
    ),
    "_geometry.incidence": ("IncidenceReport", "IncidenceRig", "incidence_report", "plot_incidence_report"),
    "_geometry.interface": ("Interface", "tilt_normal"),
    "_geometry.pose": ("Pose", "so3_exp", "so3_log"),
    "_geometry.precision": ("float64",),
    "_geometry.refraction": (
        "backproject_refracted", "intersect_plane", "optical_path_length", "project_refracted", "refract_directions",
        "refraction_points",
    ),
    "_geometry.triangulate": ("triangulate_rays",),
    "_stereo.evaluation": ("layer_errors", "layer_table_markdown"),
    "_stereo.matching": ("MatchOptions",),
    "_stereo.reconstruct": ("ReconstructOptions", "reconstruct"),
    "_stereo.rectify": ("Rectification", "rectify"),
    "_stereo.refine": ("RefineResult", "find_correspondences", "refine_rig"),
    "_stereo.survey": ("Survey", "load_survey", "save_ply", "save_survey"),
    "_stereo.table_cache": ("use_table_cache",),
    "_surface.damage": (
        "DemDamage", "ProfileDamage", "Zone", "damage_level", "dem_damage", "parse_slope", "profile_damage",
    ),
    "_surface.damage_report": ("StretchDamage", "stretch_damage", "write_damage_report"),
    "_surface.gap_fill": ("survey_baseline_xy",),
    "_surface.grid": (
        "DEM", "fill_holes", "grid_delaunay", "grid_median", "grid_survey", "load_dem", "load_surface", "save_dem",
    ),
    "_surface.profiles": ("moving_average", "profile_from_dem", "profile_from_points"),
    "_synthetic.board_render": ("board_poses", "render_board"),
    "_synthetic.campaign": ("write_synthetic_campaign",),
    "_synthetic.flume_rig": ("RigSpec", "flume_rig"),
    "_synthetic.heightfield": ("Heightfield",),
    "_synthetic.render": ("RenderedView", "RenderOptions", "render_view"),
    "_synthetic.scenes": (
        "Breakwater", "Damage", "Extent", "FlatFloor", "Scene", "SlopingBoard", "build_scene", "scene_from_json",
        "scene_to_json",
    ),
}
_MODULE_OF = {name: module for module, names in _PUBLIC.items() for name in names}
__all__ = sorted(_MODULE_OF)  # noqa: PLE0605 (built from _PUBLIC, the one list of names)
__version__ = "0.1.0"


def __getattr__(name: str):
    module = _MODULE_OF.get(name)
    if module is None:
        raise AttributeError(f"module 'jaxstereo' has no attribute {name!r}")
    value = getattr(importlib.import_module("." + module, __name__), name)
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})


if TYPE_CHECKING:  # the same names, eagerly, for type checkers and editors
    from ._app.batch import BatchResult as BatchResult, run_batch as run_batch
    from ._app.batch_job import run_pair as run_pair
    from ._app.images import read_image as read_image, write_image as write_image
    from ._app.manifest import Manifest as Manifest, PairEntry as PairEntry, load_manifest as load_manifest
    from ._calibration.boards import BoardSpec as BoardSpec
    from ._calibration.calibration import (
        CameraCalibration as CameraCalibration,
        StereoCalibration as StereoCalibration,
        calibrate_camera as calibrate_camera,
        calibrate_stereo as calibrate_stereo,
        detect_all as detect_all,
        world_frame_rig as world_frame_rig,
    )
    from ._calibration.detect import Detection as Detection, detect_board as detect_board
    from ._calibration.rig import Rig as Rig, load_rig as load_rig, save_rig as save_rig
    from ._geometry.camera import (
        Camera as Camera,
        distort_normalized as distort_normalized,
        undistort_normalized as undistort_normalized,
    )
    from ._geometry.errors import JaxStereoError as JaxStereoError
    from ._geometry.first_order import (
        backproject_first_order as backproject_first_order,
        first_order_homography as first_order_homography,
        project_first_order as project_first_order,
        refraction_angle_exact as refraction_angle_exact,
        refraction_angle_first_order as refraction_angle_first_order,
        virtual_camera as virtual_camera,
    )
    from ._geometry.incidence import (
        IncidenceReport as IncidenceReport,
        IncidenceRig as IncidenceRig,
        incidence_report as incidence_report,
        plot_incidence_report as plot_incidence_report,
    )
    from ._geometry.interface import Interface as Interface, tilt_normal as tilt_normal
    from ._geometry.pose import Pose as Pose, so3_exp as so3_exp, so3_log as so3_log
    from ._geometry.precision import float64 as float64
    from ._geometry.refraction import (
        backproject_refracted as backproject_refracted,
        intersect_plane as intersect_plane,
        optical_path_length as optical_path_length,
        project_refracted as project_refracted,
        refract_directions as refract_directions,
        refraction_points as refraction_points,
    )
    from ._geometry.triangulate import triangulate_rays as triangulate_rays
    from ._stereo.evaluation import layer_errors as layer_errors, layer_table_markdown as layer_table_markdown
    from ._stereo.matching import MatchOptions as MatchOptions
    from ._stereo.reconstruct import ReconstructOptions as ReconstructOptions, reconstruct as reconstruct
    from ._stereo.rectify import Rectification as Rectification, rectify as rectify
    from ._stereo.refine import (
        RefineResult as RefineResult,
        find_correspondences as find_correspondences,
        refine_rig as refine_rig,
    )
    from ._stereo.survey import (
        Survey as Survey,
        load_survey as load_survey,
        save_ply as save_ply,
        save_survey as save_survey,
    )
    from ._stereo.table_cache import use_table_cache as use_table_cache
    from ._surface.damage import (
        DemDamage as DemDamage,
        ProfileDamage as ProfileDamage,
        Zone as Zone,
        damage_level as damage_level,
        dem_damage as dem_damage,
        parse_slope as parse_slope,
        profile_damage as profile_damage,
    )
    from ._surface.damage_report import (
        StretchDamage as StretchDamage,
        stretch_damage as stretch_damage,
        write_damage_report as write_damage_report,
    )
    from ._surface.gap_fill import survey_baseline_xy as survey_baseline_xy
    from ._surface.grid import (
        DEM as DEM,
        fill_holes as fill_holes,
        grid_delaunay as grid_delaunay,
        grid_median as grid_median,
        grid_survey as grid_survey,
        load_dem as load_dem,
        load_surface as load_surface,
        save_dem as save_dem,
    )
    from ._surface.profiles import (
        moving_average as moving_average,
        profile_from_dem as profile_from_dem,
        profile_from_points as profile_from_points,
    )
    from ._synthetic.board_render import board_poses as board_poses, render_board as render_board
    from ._synthetic.campaign import write_synthetic_campaign as write_synthetic_campaign
    from ._synthetic.flume_rig import RigSpec as RigSpec, flume_rig as flume_rig
    from ._synthetic.heightfield import Heightfield as Heightfield
    from ._synthetic.render import (
        RenderedView as RenderedView,
        RenderOptions as RenderOptions,
        render_view as render_view,
    )
    from ._synthetic.scenes import (
        Breakwater as Breakwater,
        Damage as Damage,
        Extent as Extent,
        FlatFloor as FlatFloor,
        Scene as Scene,
        SlopingBoard as SlopingBoard,
        build_scene as build_scene,
        scene_from_json as scene_from_json,
        scene_to_json as scene_to_json,
    )
