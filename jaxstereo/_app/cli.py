"""The `jaxstereo` command line: a thin shell over library functions."""

from __future__ import annotations

import dataclasses
import gc
import os
import sys
from pathlib import Path

import numpy as np

from .._geometry.errors import JaxStereoError
from .allocator import keep_arrays_on_small_pages, keep_freed_memory
from .garbage import collect_garbage_rarely
from .gil import switch_threads_often
from .parser import build_parser


def _cmd_incidence_report(args) -> int:
    from .._geometry.incidence import IncidenceRig, incidence_report, plot_incidence_report
    from .io import write_text_atomic

    rig = IncidenceRig(
        height_m=args.height,
        depth_m=args.depth,
        baseline_m=args.baseline,
        focal_px=args.focal_px,
        n_air=args.n_air,
        n_water=args.n_water,
        disparity_noise_px=args.disparity_noise,
    )
    if args.step_deg <= 0 or args.max_deg <= 0:
        raise JaxStereoError("--max-deg and --step-deg must be positive")
    angles = np.arange(0.0, args.max_deg + 1e-9, args.step_deg)
    report = incidence_report(angles, rig, args.sigma_depths)
    print(report.to_markdown())
    for column, threshold, unit in (("angle_error_deg", 0.5, "deg"), ("pixel_error_px", 1.0, "px"),
                                    ("error_3d_mm", 1.0, "mm")):
        first = report.first_exceeding(column, threshold)
        where = f"first exceeded at {first:g} deg" if first is not None else "never exceeded in this range"
        print(f"{column} > {threshold:g} {unit}: {where}")
    out = Path(args.output)
    plot_incidence_report(report, out)
    if args.markdown:
        write_text_atomic(args.markdown, report.to_markdown() + "\n")
    print(f"figure: {out}")
    return 0


def _cmd_calibrate(args) -> int:
    from .._calibration.boards import BoardSpec
    from .._calibration.calibration import calibrate_stereo, detect_all, world_frame_rig
    from .._calibration.rig import Rig, save_rig
    from .plots import plot_calibration_errors
    from .progress import Progress

    board = BoardSpec.parse(args.board)
    left_paths, right_paths, left_images, right_images, size = _calibration_images(args)
    print(f"calibrate: {len(left_paths)} pairs of {size[0]}x{size[1]} images, board {board}")
    names = [p.name for p in left_paths]
    right_names = [p.name for p in right_paths]
    progress = Progress(2 * len(left_paths), "images", stream=sys.stdout)  # stderr holds only an error's line
    every_name = names + right_names
    detections = detect_all(left_images + right_images, board, on_each=lambda k, found: progress.advance(
        f"{every_name[k]}: {'board found' if found is not None else 'no board'}"))
    left_det, right_det = detections[: len(left_paths)], detections[len(left_paths):]
    origin = _origin_detections(args, board, size)
    stereo = calibrate_stereo(left_det, right_det, board, size, drop_outliers=not args.keep_outliers,
                              origin=None if args.no_refine else origin)
    rig, report = world_frame_rig(stereo, board, origin[0], origin[1], refine=not args.no_refine)
    calibration = {
        "board": str(board),
        "pairs": len(left_paths),
        "left_views_used": [names[i] for i in stereo.left.views],
        "right_views_used": [right_names[i] for i in stereo.right.views],
        "dropped_left": [names[i] for i in stereo.left.dropped],
        "dropped_right": [right_names[i] for i in stereo.right.dropped],
        "pairs_left_out": _pairs_left_out(stereo.missing, left_det, right_det, names, right_names),
        "rms_left_px": stereo.left.rms_px,
        "rms_right_px": stereo.right.rms_px,
        "rms_stereo_px": stereo.rms_px,
        "baseline_m": stereo.baseline_m,
        "distortion_model": stereo.distortion_model,
        "focal_std_rel": stereo.focal_std_rel,
        "world_frame": report,
    }
    rig = Rig(rig.left, rig.right, None, calibration)
    _print_calibration(stereo, report, rig, calibration)
    figure = Path(args.figure) if args.figure else Path(args.output).with_name(Path(args.output).stem + "_errors.png")
    plot_calibration_errors(stereo, figure, names)
    save_rig(rig, args.output)
    print(f"rig: {args.output}\nfigure: {figure}")
    return 0


def _calibration_images(args):
    """The calibration pairs: `(left paths, right paths, left images, right images, (width, height))`."""
    from .images import expand_images, read_images_same_size

    left_paths = expand_images(args.left, "left images")
    right_paths = expand_images(args.right, "right images")
    if len(left_paths) != len(right_paths):
        raise JaxStereoError(
            f"{len(left_paths)} left images match {args.left!r} but {len(right_paths)} right images match "
            f"{args.right!r}: the pairs must match one to one (sorted by name)"
        )
    left_images, size = read_images_same_size(left_paths)
    right_images, size_r = read_images_same_size(right_paths)
    if size_r != size:
        raise JaxStereoError(f"left images are {size[0]}x{size[1]} but right images are {size_r[0]}x{size_r[1]}")
    return left_paths, right_paths, left_images, right_images, size


def _pairs_left_out(missing: list[int], left_det, right_det, left_names, right_names) -> list[str]:
    """The pairs (indices `missing`) the stereo calibration could not use, each named by what is wrong: the
    image or images in which no board was found, or both names when each image showed part of the board but
    fewer than 6 of its corners were seen in both."""
    named = []
    for i in missing:
        lacking = [name for name, found in ((left_names[i], left_det[i]), (right_names[i], right_det[i]))
                   if found is None]
        named.append(" and ".join(lacking) + " (no board)" if lacking
                     else f"{left_names[i]} + {right_names[i]} (fewer than 6 corners seen in both)")
    return named


def _origin_detections(args, board, size) -> tuple:
    """The board lying on z = 0, detected in the origin pair; `JaxStereoError` naming the image otherwise."""
    from .._calibration.detect import detect_board
    from .images import read_image

    origin = []
    for path in (args.origin_left, args.origin_right):
        image = read_image(path, grayscale=True)
        if (image.shape[1], image.shape[0]) != size:
            raise JaxStereoError(f"origin image {path!r} is {image.shape[1]}x{image.shape[0]}, not {size[0]}x{size[1]}")
        det = detect_board(image, board)
        if det is None:
            raise JaxStereoError(f"no board {board} found in origin image {path!r}")
        origin.append(det)
    return origin[0], origin[1]


def _print_calibration(stereo, report: dict, rig, calibration: dict) -> None:
    """The calibration's figures as an aligned table on stdout, then the views it dropped."""
    heights = [float(np.asarray(c.center)[2]) for c in (rig.left, rig.right)]
    rows = [
        ("views used (left / right / pairs)", f"{len(stereo.left.views)} / {len(stereo.right.views)} / {len(stereo.pairs)}"),
        ("RMS left / right / stereo (px)", f"{stereo.left.rms_px:.3f} / {stereo.right.rms_px:.3f} / {stereo.rms_px:.3f}"),
        ("baseline (m)", f"{stereo.baseline_m:.5f}"),
        ("focal length left / right (px)", (f"{stereo.left.K[0, 0]:.2f} / {stereo.right.K[0, 0]:.2f} "
                                            f"(+/- {100 * stereo.focal_std_rel:.3f} %)")),
        ("distortion model", stereo.distortion_model),
        ("world frame from", report["pose_from"]),
        ("camera heights above z = 0 (m)", f"{heights[0]:.4f} / {heights[1]:.4f}"),
    ]
    if "origin_rms_px_after" in report:
        rows.append(("origin board RMS (px)", f"{report['origin_rms_px_after']:.3f}"))
    if "frame_tilt_std_mrad" in report:
        tilt = report["frame_tilt_std_mrad"]
        rows.append(("world frame std: tilt (mrad), height (mm)",
                     f"{tilt[0]:.2f} / {tilt[1]:.2f}, {1e3 * report['frame_height_std_m']:.2f}"))
    if "right_pose_cov" in report:
        std = np.sqrt(np.diag(np.asarray(report["right_pose_cov"])))
        rows.append(("right pose std: rotation (deg), centre (mm)",
                     f"{np.degrees(std[:3]).max():.5f}, {1e3 * std[3:].max():.3f}"))
    width = max(len(r[0]) for r in rows)
    for name, value in rows:
        print(f"  {name:<{width}}  {value}")
    for label, items in (("dropped (left)", calibration["dropped_left"]), ("dropped (right)", calibration["dropped_right"]),
                         ("pairs left out", calibration["pairs_left_out"])):
        if items:
            print(f"  {label}: {', '.join(items)}")


def _cmd_reconstruct(args) -> int:
    import time
    from concurrent.futures import ThreadPoolExecutor, wait

    from .images import check_pair, read_image
    from .io import write_bytes_atomic, write_text_atomic

    output = Path(args.output)
    if output.suffix != ".npz":
        raise JaxStereoError(f"output {args.output!r} must end in .npz")
    from .._calibration.rig import load_rig
    from .._stereo.matching import MatchOptions
    from .._stereo.reconstruct import ReconstructOptions, reconstruct
    from .._stereo.survey import SurveyWriter, survey_preview_png, survey_summary_json

    start = time.perf_counter()
    rig = load_rig(args.rig)
    reading = getattr(args, "images_read_ahead", {})
    left, right = (reading[path].result() if path in reading else read_image(path) for path in (args.left, args.right))
    check_pair(left, right, rig.image_size, f"left image {args.left!r}", f"right image {args.right!r}")
    load_s = time.perf_counter() - start
    z_range = tuple(args.z_range) if args.z_range else None
    if z_range is not None and not z_range[0] < z_range[1]:
        raise JaxStereoError(f"--z-range must be ZMIN ZMAX with ZMIN < ZMAX, got {args.z_range}")
    if not (args.photometric_ratio >= 0):
        raise JaxStereoError(f"--photometric-ratio must be >= 0 (0 keeps every match), got {args.photometric_ratio}")
    options = ReconstructOptions(model=args.model, z_range_m=z_range,
                                 match=MatchOptions(block_size=args.block_size, two_way=not args.one_way,
                                                    match_exposure=not args.levels_as_they_are,
                                                    narrow_search=not args.full_search),
                                 water_level_std_m=args.water_level_std,
                                 max_photometric_ratio=args.photometric_ratio or None)
    preview = Path(args.preview) if args.preview else output.with_name(output.stem + "_preview.png")
    # While the points' errors are propagated, the preview is drawn (in memory) on one thread, and the points and
    # then the covariances, as they come, are written on another (one step after the other: `SurveyWriter`).
    with ThreadPoolExecutor(1, thread_name_prefix="preview") as drawer, \
            ThreadPoolExecutor(1, thread_name_prefix="survey-file") as filer:
        drawing, writing = [], []
        writer = None

        def ahead(points):
            nonlocal writer
            writer = SurveyWriter(output)  # its temporary file from here on: a command stopped before leaves none
            title = (f"{output.name}: {len(points)} points, model {points.model}, "
                     f"{100 * points.submerged.mean():.0f}% submerged")
            drawing.append(drawer.submit(survey_preview_png, points, rig.image_size, title))
            writing.append(filer.submit(writer.write_points, points))

        def error_rows(fields, first, stop):
            writing.append(filer.submit(writer.error_rows, fields, first, stop))

        try:
            survey, summary = reconstruct(left, right, rig, args.water_level, options, on_points=ahead,
                                          match_ahead=getattr(args, "match_ahead", None), on_error_rows=error_rows)
            start = time.perf_counter()
            writing.append(filer.submit(_finish_survey_files, writer, survey, args.ply))
            png = drawing[0].result()
            for step in writing:  # the first failure, in order
                step.result()
        except BaseException:
            wait(writing)  # nothing writes the file any more
            if writer is not None:
                writer.discard()
            raise
    write_bytes_atomic(preview, png)  # only once the survey is written: a failed command leaves no preview
    summary["seconds"] = {"load (s)": load_s, **summary["seconds"],
                          "write and preview (s)": time.perf_counter() - start}
    summary_path = output.with_name(output.stem + "_summary.json")
    write_text_atomic(summary_path, survey_summary_json(summary) + "\n")
    level = "dry" if summary["water_level_m"] != summary["water_level_m"] else f"{summary['water_level_m']:.4f} m"
    print(f"reconstruct: model {survey.model}, water level {level}")
    print(f"  points                      {len(survey)}")
    print(f"  submerged fraction          {summary['submerged_fraction']:.3f}")
    _print_exposure(summary.get("exposure_right_to_left"))
    print(f"  exact curve off the rows    {summary['vertical_parallax_px_mean']:.3f} / "
          f"{summary['vertical_parallax_px_max']:.3f} px mean / max (under water; matches moved onto it)")
    print(f"  dropped                     {summary['dropped_rays_apart']} rays apart, "
          f"{summary['dropped_outside_height_range']} outside the height range, "
          f"{summary['dropped_undetermined']} not determined (disparity std over 1 px), "
          f"{summary['dropped_off_surface']} off the smooth surface around them, "
          f"{summary['dropped_photometric']} colours unlike their neighbours' matches")
    _print_sigma(summary)
    for warning in summary["warnings"]:
        print(f"  WARNING: {warning}")
    for stage, seconds in summary["seconds"].items():
        print(f"  {stage:<27} {seconds:.2f}")
    print(f"survey: {output}\npreview: {preview}\nsummary: {summary_path}" + (f"\nply: {args.ply}" if args.ply else ""))
    return 0


def _print_exposure(exposure: dict | None) -> None:
    """One line on the map given to the right image's grey levels before matching (`exposure.py`)."""
    if exposure is None:
        return
    if not exposure["applied"]:
        print("  right camera's levels       as the left's (no map)")
        return
    parts = []
    if exposure["levels_mapped"]:
        shape = max(exposure["fit_rms_levels"])
        parts.append("gain " + " / ".join(f"{g:.3f}" for g in exposure["gain"]) + ", offset "
                     + " / ".join(f"{o:+.1f}" for o in exposure["offset_levels"]) + " levels"
                     + (f" (tone curve off a line by {shape:.1f} levels RMS)" if shape >= 1.0 else ""))
    if exposure["shading_applied"]:
        low, high = exposure["shading_gain_range"]
        parts.append(f"times a gain varying over the image from {low:.3f} to {high:.3f}")
    print("  right camera's levels       mapped onto the left's and matched again: " + "; ".join(parts))


def _finish_survey_files(writer, survey, ply: str | None) -> None:
    """The survey `.npz` whose points `writer` (a `SurveyWriter`) wrote and, when asked for, its PLY."""
    from .._stereo.survey import save_ply

    writer.finish(survey)
    if ply:
        save_ply(survey, ply)


def _print_sigma(summary: dict) -> None:
    """The survey's median vertical std, emerged and submerged, and the part the matching alone gives."""
    for name in ("emerged", "submerged"):
        if f"median_sigma_z_{name}_mm" in summary:
            print(f"  median sigma_z {name:<11} {summary[f'median_sigma_z_{name}_mm']:.2f} mm "
                  f"({summary[f'median_sigma_z_match_{name}_mm']:.2f} mm from matching, the rest shared)")
    missing = [k for k, found in summary.get("shared_recorded", {}).items() if not found]
    if missing:
        print(f"  not in the rig's record     {', '.join(missing)} (counted as exact in sigma_z)")


def _cmd_grid(args) -> int:
    from .._stereo.survey import load_survey
    from .._surface.grid import SIGMA_LAYERS, grid_delaunay, grid_survey_filled, save_dem

    survey = load_survey(args.survey)
    if len(survey) == 0:
        raise JaxStereoError(f"survey {args.survey!r} holds no points")
    if not args.spacing > 0:
        raise JaxStereoError(f"--spacing must be positive, got {args.spacing}")
    if args.method == "delaunay":
        dem = grid_delaunay(survey.points, args.spacing)
    else:
        dem = grid_survey_filled(survey, args.spacing, args.max_gap)
    save_dem(dem, args.output)
    filled = float(np.isfinite(dem.z).mean()) if dem.z.size else 0.0
    print(f"grid: {len(survey)} points -> {dem.z.shape[1]} x {dem.z.shape[0]} cells of {args.spacing:g} m "
          f"({100 * filled:.0f}% with data), method {args.method}")
    if dem.has_sigma:
        ok = np.isfinite(dem.z)
        parts = ", ".join(f"{key.removeprefix('sigma_')} {1e3 * np.median(getattr(dem, key)[ok]):.2f}"
                          for key in SIGMA_LAYERS)
        print(f"  sigma layers: median total {1e3 * np.median(dem.sigma[ok]):.2f} mm ({parts} mm; matching "
              f"errors correlated over {1e3 * dem.correlation_m:.0f} mm)")
        if dem.sigma_coverage is not None:
            part = ok & (dem.sigma_coverage > 0)
            median = (f": their coverage std median {1e3 * np.median(dem.sigma_coverage[part]):.1f} mm"
                      if part.any() else "")
            print(f"  {100 * part.sum() / max(ok.sum(), 1):.1f}% of the cells seen in part or filled{median}")
    else:
        print("  no sigma layer: " + ("Delaunay gridding interpolates, it does not average" if args.method == "delaunay"
                                      else "the survey has no error bars (made before they existed?)"))
    print(f"DEM: {args.output}")
    return 0


def _cmd_damage(args) -> int:
    from .._surface.damage import parse_slope
    from .._surface.damage_report import ACTIVE_ZONE_DN50, write_damage_report
    from .._surface.damage_uncertainty import stretch_damage_with_sigma
    from .._surface.grid import load_surface

    if not (args.dn50 > 0):
        raise JaxStereoError(f"--dn50 must be positive (metres), got {args.dn50}")
    if args.seen_tolerance is not None and not args.seen_tolerance >= 0:
        raise JaxStereoError(f"--seen-tolerance must be 0 or more (metres, or inf), got {args.seen_tolerance}")
    cot = parse_slope(args.slope)
    spacing = args.spacing
    before = load_surface(args.before, spacing, max_gap_m=args.max_gap)
    after = load_surface(args.after, spacing, before.x, before.y, max_gap_m=args.max_gap)
    if not np.any(np.isfinite(before.z) & np.isfinite(after.z)):
        raise JaxStereoError(f"{args.before!r} and {args.after!r} do not overlap: are they in the same world frame?")
    origin, rises_toward = _design_slope_line(args, cot, before)
    result, sigma = stretch_damage_with_sigma(
        before, after, args.dn50, cot, args.swl, origin, args.profile_spacing, rises_toward=rises_toward,
        stretch=tuple(args.stretch) if args.stretch else None,
        active_zone_dn50=tuple(args.active_zone) if args.active_zone else ACTIVE_ZONE_DN50,
        seen_tolerance_m=args.seen_tolerance)
    paths = write_damage_report(result, before, after, args.output, sigma)
    a = result.averaged

    def pm(value: float, key: str, scale: float = 1.0, digits: int = 2) -> str:
        """value +- sigma [low, high] (sigma and the 95 % interval when known), all times `scale`."""
        s = sigma.sigma.get(key) if sigma is not None else None
        bounds = sigma.interval(key, value) if sigma is not None else None
        return (f"{value * scale:.{digits}f}" + ("" if s is None else f" +- {s * scale:.{digits}f}")
                + ("" if bounds is None else f" [{bounds[0] * scale:.{digits}f}, {bounds[1] * scale:.{digits}f}]"))

    width = "whole surveyed width" if result.whole_width else "tested stretch"
    print(f"damage: Dn50 {args.dn50:g} m, slope 1:{cot:g}, SWL {args.swl:g} m, {len(result.profiles)} profiles")
    print(f"  {width:<18} y {result.stretch[0]:.3f} to {result.stretch[1]:.3f} m")
    print(f"  active zone        z {result.active_zone[0]:.3f} to {result.active_zone[1]:.3f} m on the design slope, "
          f"which rises toward {result.rises_toward}")
    if np.isfinite(result.seen_tolerance):
        print(f"  seen by both       {100 * result.carried:.1f} % of the cells, not seen wholly by one survey, take "
              "the change of the cells around them that both saw wholly")
    print(f"  averaged profile   A_e {pm(a.A_e, 'A_e_m2', 1e4)} cm2  L_e {pm(a.L_e, 'L_e_m', 1e3, 0)} mm  "
          f"d_e {pm(a.d_e, 'd_e_m', 1e3, 1)} mm  S {pm(a.S, 'S')}  E2D {pm(a.E2D, 'E2D')}")
    print(f"  over the stretch   S mean {pm(result.S_mean, 'S_mean_above_threshold')} (S > {result.threshold:g})  "
          f"S max {pm(result.S_max, 'S_max')} (y {result.S_max_y:+.3f} m)  "
          f"L_e max {pm(result.L_e_max, 'L_e_max_m', 1e3, 0)} mm  "
          f"d_e max {pm(result.d_e_max, 'd_e_max_m', 1e3, 1)} mm")
    e3d = "not measurable (no Dn50 circle covered by both surveys)" if result.volumes.E3D is None else \
        pm(result.volumes.E3D, "E3D")
    print(f"  3-D                eroded {pm(result.volumes.eroded_m3, 'eroded_volume_m3', 1e6, 0)} cm3  accreted "
          f"{pm(result.volumes.accreted_m3, 'accreted_volume_m3', 1e6, 0)} cm3  E3D {e3d}")
    print(f"  damage level       {result.level} (S {pm(a.S, 'S')} of the averaged profile, slope 1:{cot:g})")
    if sigma is None:
        print("  no error bars: a surface has no sigma layers (surveys made before jaxstereo wrote them?)")
    else:
        print(f"  error bars         from {sigma.draws} draws of the surveys' errors; calibration "
              f"{'common to' if sigma.shared_calibration else 'independent in'} both, water level "
              f"{'common to' if sigma.shared_level else 'independent in'} both; [low, high] the 95 % interval (the "
              "wider of +- 2 sigma and the middle 95 % of the draws)")
    for y, why in result.skipped:
        print(f"  profile y {y:+.3f} m not computed: {why}")
    print("report: " + ", ".join(str(p) for p in paths))
    return 0


def _design_slope_line(args, cot: float, before) -> tuple[tuple[float, float], str | None]:
    """The design slope line from --slope-origin, --slope-points or (on request) --fit-slope: `(origin,
    rises_toward)`, a point (x, z) of the line, metres, and the direction along x in which it rises ("+x" or
    "-x") where the arguments say it (--slope-points, in the order of their heights), else None: the initial
    survey says it (`slope_direction`). Two points that rise the other way than the initial survey are taken as
    given, with a warning."""
    from .._surface.damage_report import _column_mean, fit_design_slope
    from .._surface.slope_direction import slope_direction

    given = [name for name in ("slope_origin", "slope_points", "fit_slope") if getattr(args, name)]
    if len(given) != 1:
        raise JaxStereoError("place the design slope with exactly one of --slope-origin X Z (its toe, say), "
                             "--slope-points X1 Z1 X2 Z2 or --fit-slope" + (f" (got {len(given)})" if given else ""))
    if args.slope_origin:
        return tuple(args.slope_origin), None
    if args.slope_points:
        x1, z1, x2, z2 = args.slope_points
        if x2 == x1 or (z2 - z1) == 0:
            raise JaxStereoError("--slope-points must be two distinct points of a sloping line")
        cot_points = abs((x2 - x1) / (z2 - z1))
        if abs(cot_points - cot) > 0.05 * cot:
            raise JaxStereoError(f"--slope-points give a slope of 1:{cot_points:.2f} but --slope is 1:{cot:g}")
        rises_toward = "+x" if (z2 - z1) * (x2 - x1) > 0 else "-x"
        surveyed = slope_direction(before, cot, args.swl, (x1, z1), args.dn50)
        if surveyed != rises_toward:
            print(f"  WARNING: --slope-points rise toward {rises_toward}, but the initial survey follows a slope rising "
                  f"toward {surveyed} through them: the points are taken as given (check their coordinates)")
        return (x1, z1), rises_toward
    origin, rms = fit_design_slope(before.x, _column_mean(before.z), cot, args.swl, args.dn50)
    print(f"design slope fitted to the initial survey near the SWL: x0 {origin[0]:.4f} m at z 0, RMS "
          f"{1e3 * rms:.1f} mm normal to the slope")
    if rms > 0.5 * args.dn50:
        print(f"  WARNING: the initial survey departs from a 1:{cot:g} line by {1e3 * rms:.0f} mm RMS near the SWL: "
              "is --slope right? Prefer --slope-origin.")
    return origin, None


def _read_control_points(path):
    """CSV with a header and columns u_left, v_left, u_right, v_right, x, y, z (pixels, metres)."""
    p = Path(path)
    if not p.is_file():
        raise JaxStereoError(f"control points file {path!r} does not exist")
    try:
        data = np.loadtxt(p, delimiter=",", skiprows=1, ndmin=2)
    except ValueError as err:
        raise JaxStereoError(f"control points file {path!r}: {err}") from None
    if data.shape[1] != 7 or data.shape[0] == 0:
        raise JaxStereoError(f"control points file {path!r} must have 7 columns "
                             "(u_left, v_left, u_right, v_right, x, y, z) and at least one row")
    if not np.all(np.isfinite(data)):
        raise JaxStereoError(f"control points file {path!r} contains NaN or infinite values")
    return data[:, 0:2], data[:, 2:4], data[:, 4:7]


MIN_DENSE_CORRESPONDENCES = 100  # below this many dense matches, refine falls back to SIFT


def _cmd_refine(args) -> int:
    from .._calibration.rig import load_rig, save_rig
    from .._stereo.refine import refine_rig
    from .images import check_pair, read_image

    if not (np.isfinite(args.level_tolerance) and args.level_tolerance > 0):
        raise JaxStereoError(f"--level-tolerance must be a positive number of metres, got {args.level_tolerance}")
    if args.max_points is not None and args.max_points < 1:
        raise JaxStereoError(f"--max-points must be a positive number of correspondences, got {args.max_points}")
    rig = load_rig(args.rig)
    left, right = read_image(args.left), read_image(args.right)
    check_pair(left, right, rig.image_size, f"left image {args.left!r}", f"right image {args.right!r}")
    refine = tuple(v.strip() for v in args.refine.split(",") if v.strip())
    control, points = _refine_control(args.control or [])
    pl, pr = _refine_correspondences(args, left, right, rig, control)
    result = refine_rig(rig, pl, pr, args.water_level_guess, refine=refine, control=control,
                        floor_region=tuple(args.floor_x) if args.floor_x else None, control_points=points,
                        level_tolerance_m=args.level_tolerance)
    _print_refinement(result, refine, control, points)
    if not result.converged:
        raise JaxStereoError(f"the bundle adjustment did not converge (its solves: {', '.join(result.outcomes)}): "
                             "no rig written (check the level guess, the control and the correspondences)")
    if "water" in refine and not result.level_determined:
        result = _keep_guess_or_refuse(args, result)
    save_rig(result.rig, args.output)
    print(f"rig: {args.output}")
    return 0


def _refine_control(items: list[str]):
    """`--control` values: `(surface, points)`, the surface "floor", a DEM or None, and the CSV's control points."""
    control, points = None, None
    for item in items:
        if item.endswith(".csv"):
            points = _read_control_points(item)
            continue
        if control is not None:
            raise JaxStereoError(f"--control {item!r}: give one control surface (floor or a DEM), not two")
        if item == "floor":
            control = "floor"
        elif item.endswith(".npz"):
            from .._surface.grid import load_surface

            control = load_surface(item, 0.005)
            if not np.isfinite(control.z).any():
                raise JaxStereoError(f"control DEM {item!r} holds no heights")
        else:
            raise JaxStereoError(f"--control {item!r}: use 'floor', a DEM or survey .npz, or a control-points .csv")
    return control, points


def _refine_correspondences(args, left, right, rig, control):
    """Correspondences from the dense matching (SIFT when it finds too few), or SIFT on request; against a DEM
    `control`, measured along the rows as the survey that made it measures its points."""
    from .._stereo.correspondences import CORRESPONDENCES, dense_correspondences
    from .._stereo.refine import find_correspondences
    from .._surface.grid import DEM

    # SIFT keeps 2000 against a DEM too: on the POV-Ray flume's wet pair 6000 asked gave the same 435 consistent
    # matches (and the same refused level) in 23 s against 10 s
    if args.matches == "dense":
        estimator = "survey" if isinstance(control, DEM) else "lucas-kanade"
        pl, pr = dense_correspondences(left, right, rig, args.water_level_guess, args.max_points, estimator)
        source = "the dense matching"
    if args.matches == "sift" or len(pl) < MIN_DENSE_CORRESPONDENCES:
        if args.matches == "dense":
            print(f"refine: only {len(pl)} dense matches; SIFT instead")
        pl, pr = find_correspondences(left, right, args.max_points or CORRESPONDENCES)
        source = "SIFT"
    print(f"refine: {len(pl)} correspondences from {source}")
    return pl, pr


def _print_refinement(result, refine, control, points) -> None:
    print(f"  {result.n_correspondences} consistent with the rig, {result.n_control} control terms, "
          f"{result.steps} steps ({result.seconds:.1f} s)")
    for name, (value, std) in result.parameters.items():
        print(f"  {name:<34} {value:+.5f} +/- {std:.5f}")
    if "water" in refine:
        print(f"  level std: fit {1e3 * result.level_std_fit_m:.2f} mm, world frame {1e3 * result.level_std_frame_m:.2f} mm")
    print(f"  reprojection RMS before / after    {result.rms_before_px:.3f} / {result.rms_after_px:.3f} px")
    if control is not None:
        print(f"  control surface std (from the data) {1e3 * result.surface_sigma_m:.2f} mm, "
              f"{result.n_control - (0 if points is None else len(points[0]))} points on it")
    print(f"  solver                             {result.result}")


def _keep_guess_or_refuse(args, result):
    """An undetermined level: refuse (no rig), or with --keep-guess the rig at the guess, said so in its provenance."""
    from .._calibration.rig import Rig
    from .._stereo.refine import MIN_CORRESPONDENCES

    level, std = result.parameters["water level (m)"]
    message = (f"water level not determined: {level:.4f} m +/- {1e3 * std:.2f} mm (1 sigma; its 95 % interval "
               f"exceeds +/- {1e3 * args.level_tolerance:g} mm, --level-tolerance) from {result.n_correspondences} "
               f"correspondences and {result.n_control} control terms; add control (--control floor with "
               "--floor-x, a dry DEM, control points)")
    if 0 <= result.n_submerged < MIN_CORRESPONDENCES:
        message = (f"water level not determined: the solver ended at {level:.4f} m, where only {result.n_submerged} "
                   f"of {result.n_correspondences} correspondences lie under the water (check the level guess, "
                   "the rig and the control)")
    if not args.keep_guess:
        raise JaxStereoError(message + ", or pass --keep-guess to write the rig at the guessed level")
    print(f"  WATER LEVEL NOT DETERMINED ({message}); keeping the guess {args.water_level_guess:.4f} m (--keep-guess)")
    kept = result.rig.interface.with_level(float(args.water_level_guess))
    calibration = dict(result.rig.calibration)
    calibration["refine"] = {**calibration["refine"], "level_kept_from_guess": True,
                             "note": "the images did not determine the level; the guess (gauge reading) was kept"}
    return dataclasses.replace(result, rig=Rig(result.rig.left, result.rig.right, kept, calibration))


def _cmd_batch(args) -> int:
    from .batch import run_batch

    campaign = args.manifest
    folder_options = {"--rig": args.rig, "--water-level": args.water_level, "--dn50": args.dn50,
                      "--slope": args.slope, "--swl": args.swl}
    if Path(campaign).is_dir():
        campaign = _campaign_from_folder(Path(campaign), args)
    elif any(v is not None for v in folder_options.values()):
        given = ", ".join(k for k, v in folder_options.items() if v is not None)
        raise JaxStereoError(f"{given}: only for a folder of pairs; a manifest holds its own settings")
    result = run_batch(campaign, args.output, workers=args.workers, scheduler=args.scheduler)
    if result.failed:
        failures = "; ".join(f"{r['test']}/{r['stage']}: {r['error']}" for r in result.rows if r["status"] == "failed")
        print(f"jaxstereo batch: error: {result.failed} of {len(result.rows)} pairs failed (logged in "
              f"{result.output / 'batch.log'}): {failures}", file=sys.stderr)
        return 1
    return 0


def _campaign_from_folder(folder: Path, args):
    """A campaign from a folder of TEST_STAGE_L / TEST_STAGE_R images and the command's options."""
    from .manifest import manifest_from_dict

    if args.rig is None:
        raise JaxStereoError(f"{str(folder)!r} is a folder of pairs: give --rig (and --water-level, and for damage "
                             "--dn50, --slope, --swl), or a manifest")
    data = {"rig": str(Path(args.rig).resolve()), "pairs": str(folder.resolve())}
    if args.water_level is not None:
        data["water_level"] = args.water_level
    damage = {"dn50": args.dn50, "slope": args.slope, "swl": args.swl}
    if any(v is not None for v in damage.values()):
        missing = [f"--{k}" for k, v in damage.items() if v is None]
        if missing:
            raise JaxStereoError(f"damage needs --dn50, --slope and --swl together; missing {', '.join(missing)}")
        if args.slope_origin:
            damage["slope_origin"] = list(args.slope_origin)
        if args.fit_slope:
            damage["fit_slope"] = True
        if args.stretch:
            damage["stretch"] = list(args.stretch)
        if args.active_zone:
            damage["active_zone"] = list(args.active_zone)
        data["damage"] = damage
    return manifest_from_dict(data, folder, folder.resolve().parent)


def _cmd_demo(args) -> int:
    from .._synthetic.demo import run_demo

    run_demo(args.output)
    return 0


def run() -> None:
    """The `jaxstereo` console command (and `python -m jaxstereo`): `main`, then the process ends at once with
    its status. The interpreter's own teardown (JAX's runtime, every module, the survey's arrays) would take
    another half second after a survey; every file the command writes is closed and renamed by then."""
    import logging

    sys.stdout, sys.stderr = _OutlivesItsReader(sys.stdout), _OutlivesItsReader(sys.stderr)
    status = main(own_process=True)
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(status)


class _OutlivesItsReader:
    """The command's standard output or error, which goes on writing into nothing once the program reading its
    pipe has closed it (`jaxstereo batch campaign.toml | head`): the report lines are the reader's to drop, the
    survey, figures and tables are the command's to finish. Without it the first line past the reader's end
    raises `BrokenPipeError` and the command stops there, its files half done."""

    def __init__(self, stream):
        self._stream = stream

    def _quietly(self, method: str, *args):
        try:
            return getattr(self._stream, method)(*args)
        except BrokenPipeError:
            # Point the file descriptor at the null device; the stream's buffer then flushes into it.
            null = os.open(os.devnull, os.O_WRONLY)
            os.dup2(null, self._stream.fileno())
            os.close(null)
            return getattr(self._stream, method)(*args)

    def write(self, text: str) -> int:
        return self._quietly("write", text)

    def flush(self) -> None:
        self._quietly("flush")

    def __getattr__(self, name: str):
        return getattr(self._stream, name)


def main(argv=None, *, own_process: bool = False) -> int:
    """Run the command line; returns the exit status. `own_process` (the `jaxstereo` command, `run`): the process
    is the command's alone: its garbage collector runs less often (`garbage.py`), `reconstruct` switches threads
    more often (`gil.py`), keeps numpy's arrays on small pages and its freed memory for reuse, and a repeated
    `reconstruct` takes one malloc arena (`allocator.py`). (Its one OpenBLAS thread is set before numpy loads:
    `command.py`.)"""
    if own_process:
        collect_garbage_rarely()
    parser = build_parser()
    args = parser.parse_args(argv)
    if not args.command:
        parser.print_help()
        return 0
    if own_process and args.command == "reconstruct":
        switch_threads_often()
        keep_arrays_on_small_pages()
        keep_freed_memory()
    handler = {
        "demo": _cmd_demo,
        "batch": _cmd_batch,
        "incidence-report": _cmd_incidence_report,
        "calibrate": _cmd_calibrate,
        "reconstruct": _cmd_reconstruct,
        "refine": _cmd_refine,
        "grid": _cmd_grid,
        "damage": _cmd_damage,
    }[args.command]
    plan = _match_plan(args)
    if own_process and plan is not None and plan.exists():  # a repeat, which compiles nothing: see allocator.py
        from .allocator import use_one_malloc_arena

        use_one_malloc_arena()  # before the threads below allocate
    args.images_read_ahead = _read_images_ahead(args)
    args.match_ahead = _match_ahead(plan, args.images_read_ahead, args)
    import jax

    if own_process:
        gc.freeze()  # JAX's modules live as long as the process: no collection need walk them (garbage.py)

    from .._stereo.table_cache import use_table_cache

    _use_disk_caches(jax)
    try:
        with jax.enable_x64(True):  # geometry in float64, for this command only
            return handler(args)
    except (JaxStereoError, OSError) as err:
        print(f"jaxstereo {args.command}: error: {err}", file=sys.stderr)
        return 2
    finally:
        use_table_cache(None)  # a caller that runs commands in its own process keeps the library's default


def _read_images_ahead(args) -> dict:
    """`reconstruct`'s two images decoding on threads while JAX is imported (about a second; Pillow holds no
    GIL while it decodes): path -> Future of `read_image`. Empty for the other commands."""
    if args.command != "reconstruct":
        return {}
    from concurrent.futures import ThreadPoolExecutor

    from .images import read_image

    readers = ThreadPoolExecutor(2, thread_name_prefix="read-image")
    reading = {path: readers.submit(read_image, path) for path in (args.left, args.right)}
    readers.shutdown(wait=False)
    return reading


def _match_plan(args):
    """`reconstruct`'s match plan file (`match_ahead.plan_path`: kept by an earlier command with the same rig file
    and settings, and there or not); None for the other commands, without the disk caches, or when the rig file
    cannot be read."""
    root = _cache_root()
    if args.command != "reconstruct" or root is None:
        return None
    from .._stereo.match_ahead import plan_path
    from .._stereo.table_cache import source_digest

    arguments = {"water_level": args.water_level, "z_range": args.z_range, "model": args.model,
                 "block_size": args.block_size, "one_way": args.one_way,
                 "levels_as_they_are": args.levels_as_they_are, "full_search": args.full_search}
    return plan_path(os.path.join(root, "tables"), source_digest, args.rig, arguments)


def _match_ahead(plan, reading: dict, args):
    """`reconstruct`'s head start (`MatchAhead`): its pair (`reading`, from `_read_images_ahead`) matched on a
    thread from the `plan` an earlier command with the same rig file and settings kept, while JAX is imported;
    None without a plan path (`_match_plan`)."""
    if plan is None:
        return None
    from .._stereo.match_ahead import MatchAhead

    return MatchAhead(plan, (reading[args.left], reading[args.right]))


def _cache_root() -> str | None:
    """The disk caches' folder: $JAXSTEREO_CACHE_DIR, or jaxstereo under $XDG_CACHE_HOME (~/.cache); None when
    JAXSTEREO_CACHE_DIR is "off"."""
    root = os.environ.get("JAXSTEREO_CACHE_DIR") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"), "jaxstereo")
    return None if root.lower() == "off" else root


def _use_disk_caches(jax) -> None:
    """Keep compiled functions (JAX's persistent cache, in jax/) and the tables computed from the rig alone
    (`table_cache.py`, in tables/) on disk between commands, so that a second command on this machine with
    the same rig compiles and tabulates nothing. The folder is $JAXSTEREO_CACHE_DIR, or jaxstereo under
    $XDG_CACHE_HOME (~/.cache); JAXSTEREO_CACHE_DIR=off disables both. Set by the command line only: the
    library never changes JAX's configuration and keeps no table on disk unless asked."""
    from .._stereo.table_cache import use_table_cache

    root = _cache_root()
    if root is None:
        return
    folder = os.path.join(root, "jax")
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError:
        return  # a read-only home: run without the caches rather than fail
    use_table_cache(os.path.join(root, "tables"))
    jax.config.update("jax_compilation_cache_dir", folder)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
