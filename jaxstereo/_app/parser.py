"""The `jaxstereo` command line's arguments: one parser, one function per command."""

from __future__ import annotations

import argparse
import re
from importlib import metadata


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of every command; `args.command` names the one chosen (None: no command)."""
    parser = argparse.ArgumentParser(
        prog="jaxstereo",
        description="Refraction-aware stereo photogrammetry of wave-flume models through the water surface.",
    )
    parser.add_argument("--version", action=_Versions, nargs=0,
                        help="print jaxstereo's version and those of the packages it runs on, then exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    _add_demo(sub)
    _add_batch(sub)
    _add_incidence_report(sub)
    _add_calibrate(sub)
    _add_reconstruct(sub)
    _add_refine(sub)
    _add_grid(sub)
    _add_damage(sub)
    return parser


def versions() -> str:
    """jaxstereo's version, then the version installed of each package it depends on (its metadata's requirements
    outside the extras, and jaxlib beside jax), one line each: a bug report's first lines. Read from the packages'
    metadata, none of them imported."""
    from .. import __version__

    lines = [f"jaxstereo {__version__}"]
    try:
        required = metadata.requires("jaxstereo") or []
    except metadata.PackageNotFoundError:
        return lines[0] + " (not installed: its dependencies' versions unknown)"
    for requirement in required:
        if "extra ==" in requirement:
            continue
        name = re.match(r"[A-Za-z0-9._-]+", requirement).group(0)
        lines.append(_installed(name))
        if name == "jax":
            lines.append(_installed("jaxlib"))
    return "\n".join(lines)


def _installed(name: str) -> str:
    """One line of `versions`: `name` and its version installed, or that it is not."""
    try:
        return f"  {name} {metadata.version(name)}"
    except metadata.PackageNotFoundError:
        return f"  {name} not installed"


class _Versions(argparse.Action):
    """`--version`: print `versions()` and exit with status 0."""

    def __call__(self, parser, namespace, values, option_string=None):
        print(versions())
        parser.exit()


def _add_demo(sub) -> None:
    p = sub.add_parser("demo", help="the whole survey on a synthetic flume: calibrate, refine, reconstruct, damage",
                       description="Builds a synthetic flume (board photographs, a breakwater, three damage stages) and "
                       "runs calibrate, refine, reconstruct, grid and damage end to end; writes a report folder.")
    p.add_argument("-o", "--output", default="jaxstereo-demo", help="report folder (default jaxstereo-demo)")


def _add_batch(sub) -> None:
    p = sub.add_parser(
        "batch", help="a whole campaign from a manifest: reconstruct, grid and damage every pair; resumable",
        description="Runs every stereo pair of a campaign manifest (TOML) through reconstruct, grid and damage "
        "against its test's reference stage. Finished pairs are skipped (resumable), a failing pair is logged and "
        "skipped (exit status 1 at the end), and summary.csv plus a damage-versus-stage figure per test are "
        "written. The manifest format is documented in the README.")
    p.add_argument("manifest", metavar="MANIFEST|FOLDER",
                   help="campaign manifest (TOML), or a folder of TEST_STAGE_L.png / TEST_STAGE_R.png pairs")
    p.add_argument("--rig", help="rig JSON (folder of pairs only)")
    p.add_argument("--water-level", type=float, help="water level, m (folder of pairs only)")
    p.add_argument("--dn50", type=float, help="armour Dn50, m, for damage (folder of pairs only)")
    p.add_argument("--slope", help="design slope, e.g. 1:2, for damage (folder of pairs only)")
    p.add_argument("--swl", type=float, help="still water level, m, for damage (folder of pairs only)")
    p.add_argument("--slope-origin", type=float, nargs=2, metavar=("X", "Z"),
                   help="a point of the design slope line, m (folder of pairs only)")
    p.add_argument("--fit-slope", action="store_true",
                   help="fit the design slope to each test's reference survey (folder of pairs only)")
    p.add_argument("--stretch", type=float, nargs=2, metavar=("Y0", "Y1"),
                   help="the tested stretch, m (folder of pairs only; default the whole surveyed width)")
    p.add_argument("--active-zone", type=float, nargs=2, metavar=("BELOW", "ABOVE"),
                   help="erosion counted from BELOW to ABOVE Dn50 about the SWL (folder of pairs only; default 6 4)")
    p.add_argument("-o", "--output", help="output folder (default: the manifest's output, or MANIFEST-out)")
    p.add_argument("--workers", type=int, default=1, help="local worker processes (default 1: this process)")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="run on a Dask distributed cluster (optional extra 'dask'), e.g. tcp://10.0.0.5:8786")


def _add_incidence_report(sub) -> None:
    p = sub.add_parser(
        "incidence-report",
        help="error of the first-order (virtual camera) model versus exact Snell, by incidence angle",
        description="Tabulate and plot the first-order model's refraction-angle, pixel and 3-D error versus incidence.",
    )
    p.add_argument("--height", type=float, default=2.0, help="camera height above the water, m (default 2.0)")
    p.add_argument("--depth", type=float, default=0.3, help="depth of the point below the water, m (default 0.3)")
    p.add_argument("--baseline", type=float, default=0.16, help="stereo baseline, m (default 0.16)")
    p.add_argument("--focal-px", type=float, default=3935.0, help="focal length, pixels (default 3935)")
    p.add_argument("--n-air", type=float, default=1.0, help="refractive index of air (default 1.000)")
    p.add_argument("--n-water", type=float, default=1.333, help="refractive index of water (default 1.333)")
    p.add_argument("--disparity-noise", type=float, default=0.15, help="the matching's disparity std, px, for the "
                   "predicted sigma_z (default 0.15; reconstruct's summary gives yours as median_sigma_disparity_px)")
    p.add_argument("--sigma-depths", type=float, nargs="+", metavar="M", help="depths below the water, m, for the "
                   "predicted sigma_z (default: a third, two thirds and all of --depth)")
    p.add_argument("--max-deg", type=float, default=40.0, help="largest incidence angle, degrees (default 40)")
    p.add_argument("--step-deg", type=float, default=5.0, help="step between angles, degrees (default 5)")
    p.add_argument("-o", "--output", default="incidence-report.png", help="PNG figure to write")
    p.add_argument("--markdown", help="also write the table to this Markdown file")


def _add_calibrate(sub) -> None:
    p = sub.add_parser(
        "calibrate",
        help="calibrate a stereo rig from board photographs; world frame Z up from a board on the floor",
        description="Intrinsics of both cameras, their relative pose, and the world frame (z = 0 on the origin "
        "board, Z up) from board photographs; writes the rig JSON and a PNG of per-view errors.",
    )
    p.add_argument("--left", required=True, help="left images (glob pattern, quoted)")
    p.add_argument("--right", required=True, help="right images (glob pattern, quoted), same order")
    p.add_argument("--board", required=True,
                   help="chessboard:COLSxROWS:SQUARE (inner corners) or charuco:COLSxROWS:SQUARE:MARKER:DICT")
    p.add_argument("--origin-left", required=True, help="left image of the board lying on z = 0")
    p.add_argument("--origin-right", required=True, help="right image of the board lying on z = 0")
    p.add_argument("-o", "--output", required=True, help="rig JSON to write")
    p.add_argument("--figure", help="PNG of per-view errors (default: next to the rig, *_errors.png)")
    p.add_argument("--keep-outliers", action="store_true", help="do not drop views with outlying errors")
    p.add_argument("--no-refine", action="store_true",
                   help="world frame from the origin board in the left image alone (solvePnP), not from the joint "
                        "adjustment of the origin pair with the calibration pairs")


def _add_reconstruct(sub) -> None:
    p = sub.add_parser(
        "reconstruct",
        help="dense survey of a partly submerged scene from one stereo pair",
        description="Rectify, match (SGBM) and triangulate a wet stereo pair with exact refraction (or the "
        "first-order model, or none); writes the survey .npz, a preview PNG and a summary JSON.",
    )
    p.add_argument("left", help="left image")
    p.add_argument("right", help="right image")
    p.add_argument("--rig", required=True, help="rig JSON (from jaxstereo calibrate or refine)")
    p.add_argument("--water-level", type=float, help="water level, m (world Z); default: the rig's interface, "
                   "or a dry survey if it has none")
    p.add_argument("--water-level-std", type=float, help="the water level's standard deviation, m, for the points' "
                   "error bars (default: the one refine recorded for the rig's own level, else 0: a given level is exact)")
    p.add_argument("--model", choices=["exact", "first-order", "none"], default="exact",
                   help="refraction model for under-water points (default exact)")
    p.add_argument("--z-range", type=float, nargs=2, metavar=("ZMIN", "ZMAX"),
                   help="height range of the scene, m: bounds the disparity search and every point (default -0.03 to "
                        "level + 0.4)")
    p.add_argument("--block-size", type=int, default=5, help="SGBM block size, pixels (odd, default 5)")
    p.add_argument("--photometric-ratio", type=float, default=2.5,
                   help="drop matches whose colour residual exceeds this multiple of the median residual of the "
                        "matches around them (default 2.5; 0 keeps every match)")
    p.add_argument("--one-way", action="store_true",
                   help="skip matching the right image against the left (about 0.1 s less on a 2-megapixel pair; "
                        "keeps more foreground disparities carried past occluding edges)")
    p.add_argument("--full-search", action="store_true",
                   help="search every disparity the height range allows (default: only those a match of the pair at "
                        "a quarter of its size finds, 16 px either side, within that range)")
    p.add_argument("--levels-as-they-are", action="store_true",
                   help="match the images' grey levels as the cameras recorded them (default: the right image's "
                        "levels are mapped onto the left's at the first matches, and the pair matched again where "
                        "the cameras' exposure, white balance, tone curve or shading over the image differ)")
    p.add_argument("-o", "--output", required=True, help="survey .npz to write")
    p.add_argument("--ply", help="also write the points as PLY")
    p.add_argument("--preview", help="preview PNG (default: next to the survey, *_preview.png)")


def _add_refine(sub) -> None:
    p = sub.add_parser("refine", help="water level (and tilt, right-camera pose) from a wet pair by bundle adjustment",
                       description="Bundle adjustment through exact refraction (optimistix): refines the water level, "
                       "optionally the interface tilt and the right camera's pose, and writes the refined rig.")
    p.add_argument("left", help="left image")
    p.add_argument("right", help="right image")
    p.add_argument("--rig", required=True, help="rig JSON")
    p.add_argument("--water-level-guess", type=float, required=True, help="starting water level, m")
    p.add_argument("--control", action="append", metavar="floor|DEM.npz|POINTS.csv",
                   help="control: 'floor' (points on z = 0) or a dry survey of the model (DEM or survey .npz: "
                   "the parts that did not move), and/or a CSV of control points "
                   "(u_left,v_left,u_right,v_right,x,y,z); may be repeated")
    p.add_argument("--floor-x", type=float, nargs=2, metavar=("XMIN", "XMAX"),
                   help="world x range where the floor is bare (e.g. in front of the toe)")
    p.add_argument("--refine", default="water", help="comma list of water, tilt, right-pose (default water)")
    p.add_argument("--max-points", type=int, help="correspondences to use, at most (default 6000 from the dense "
                   "matching against a dry survey or DEM, 2000 otherwise)")
    p.add_argument("--matches", choices=["dense", "sift"], default="dense",
                   help="correspondences from the dense matching, spread over the image (default; SIFT when it "
                        "finds too few), or SIFT features")
    p.add_argument("--level-tolerance", type=float, default=0.001, metavar="M",
                   help="write the level only when its 95 %% interval (two standard deviations) is within this, m "
                        "(default 0.001)")
    p.add_argument("--keep-guess", action="store_true",
                   help="when the images cannot determine the level, write the rig at the guessed level (said so in "
                        "its provenance) instead of refusing")
    p.add_argument("-o", "--output", required=True, help="refined rig JSON")


def _add_grid(sub) -> None:
    p = sub.add_parser("grid", help="grid a survey into a DEM (median per cell, or Delaunay as the paper)",
                       description="Grid a survey .npz into a DEM .npz (x, y, z with NaN where no data, spacing).")
    p.add_argument("survey", help="survey .npz")
    p.add_argument("--spacing", type=float, default=0.005, help="cell size, m (default 0.005)")
    p.add_argument("--method", choices=["median", "delaunay"], default="median",
                   help="median per cell (fast, robust; default) or linear on the Delaunay triangulation")
    p.add_argument("--max-gap", type=float, default=0.0,
                   help="fill holes up to this size, m (median only): from the nearest seen cell, or from the lower of "
                        "the two nearest along the stereo baseline where both lie within reach")
    p.add_argument("-o", "--output", required=True, help="DEM .npz to write")


def _add_damage(sub) -> None:
    p = sub.add_parser("damage", help="armour-layer damage between two surveys or DEMs: S, E2D, E3D, volumes",
                       description="Compare a before and an after survey (or DEM): per-profile and averaged damage "
                       "(A_e, L_e, d_e, S, E2D), eroded and accreted volumes and E3D; JSON, CSV and PNG report.")
    p.add_argument("before", help="survey or DEM .npz before the test")
    p.add_argument("after", help="survey or DEM .npz after the test")
    p.add_argument("--dn50", type=float, required=True, help="nominal diameter of the armour units, m")
    p.add_argument("--slope", required=True, help="design slope: cotangent (2) or V:H (1:2); it may rise toward +x "
                   "or -x (the initial survey says which)")
    p.add_argument("--swl", type=float, required=True, help="still water level, m (world Z)")
    p.add_argument("--slope-origin", type=float, nargs=2, metavar=("X", "Z"),
                   help="a point of the design slope line (its toe, say), m")
    p.add_argument("--slope-points", type=float, nargs=4, metavar=("X1", "Z1", "X2", "Z2"),
                   help="two points of the design slope line, m (checked against --slope; the slope rises from the lower "
                        "to the higher)")
    p.add_argument("--fit-slope", action="store_true",
                   help="fit the design slope line to the initial survey near the SWL (its fit error is printed)")
    p.add_argument("--stretch", type=float, nargs=2, metavar=("Y0", "Y1"),
                   help="the tested stretch (characterisation width), y from Y0 to Y1, m (default: the whole "
                        "surveyed width)")
    p.add_argument("--active-zone", type=float, nargs=2, metavar=("BELOW", "ABOVE"), default=None,
                   help="count the erosion zones that reach into BELOW Dn50 under the SWL to ABOVE Dn50 over it, "
                        "along the slope, each whole (default 6 4)")
    p.add_argument("--seen-tolerance", type=float, default=None, metavar="M",
                   help="a cell whose coverage std exceeds M metres in either survey (seen only in part, or filled) "
                        "takes the change of the cells around it that both surveys saw wholly (default 0: every "
                        "such cell; inf: compare every cell as surveyed)")
    p.add_argument("--spacing", type=float, default=0.005, help="grid spacing for surveys, m (default 0.005)")
    p.add_argument("--max-gap", type=float, default=0.01,
                   help="fill holes up to this size, m (default 0.01; a gap along the stereo baseline from its lower "
                        "side)")
    p.add_argument("--profile-spacing", type=float, help="distance between profiles, m (default Dn50)")
    p.add_argument("-o", "--output", required=True, help="report folder")
