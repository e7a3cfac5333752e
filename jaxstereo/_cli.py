"""The `jaxstereo` command line: a thin shell over library functions."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ._errors import JaxStereoError


def _cmd_incidence_report(args) -> int:
    from ._incidence import IncidenceRig, incidence_report, plot_incidence_report
    from ._io import write_text_atomic

    import numpy as np

    rig = IncidenceRig(
        height_m=args.height,
        depth_m=args.depth,
        baseline_m=args.baseline,
        focal_px=args.focal_px,
        n_air=args.n_air,
        n_water=args.n_water,
    )
    if args.step_deg <= 0 or args.max_deg <= 0:
        raise JaxStereoError("--max-deg and --step-deg must be positive")
    angles = np.arange(0.0, args.max_deg + 1e-9, args.step_deg)
    report = incidence_report(angles, rig)
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


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="jaxstereo",
        description="Refraction-aware stereo photogrammetry of wave-flume models through the water surface.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

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
    p.add_argument("--max-deg", type=float, default=40.0, help="largest incidence angle, degrees (default 40)")
    p.add_argument("--step-deg", type=float, default=5.0, help="step between angles, degrees (default 5)")
    p.add_argument("-o", "--output", default="incidence-report.png", help="PNG figure to write")
    p.add_argument("--markdown", help="also write the table to this Markdown file")
    p.set_defaults(func=_cmd_incidence_report)
    return parser


def main(argv=None) -> int:
    """Run the command line; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 0
    try:
        return args.func(args)
    except (JaxStereoError, OSError) as err:
        print(f"jaxstereo {args.command}: error: {err}", file=sys.stderr)
        return 2
