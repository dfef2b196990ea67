"""`tiltfit report` (residual, blur and coverage plots, and the photos against the target rendered through the
calibration) and `tiltfit compare` (two calibrations' projection difference against what their σ predict)."""
from __future__ import annotations

import os
import sys

from camio.errors import os_reason

from .errors import CliError, as_cli_error, progress_printer


def cmd_report(args) -> int:
    """`tiltfit report CALIB.json -o DIR`."""
    from tiltfit.files.calib import read_calib
    from tiltfit.report.plots import write_report

    if os.path.exists(args.output) and not os.path.isdir(args.output):
        raise CliError(args.output, "not a folder")
    try:
        data = read_calib(args.calib)
    except ValueError as e:
        raise as_cli_error(args.calib, e) from None
    options = _real_vs_rendered_options(args)
    _check_report_options(options, data)
    try:
        files = write_report(data, args.output, args.calib, options)
    except OSError as e:
        raise CliError(args.output, f"cannot write ({os_reason(e)})") from None
    except ValueError as e:
        raise as_cli_error(args.calib, e) from None
    say = progress_printer(args.quiet)
    for f in files:
        say(f"wrote {f}")
    return 0


def _check_report_options(options, data: dict) -> None:
    """Refuse --views and --scale that do not fit the calibration before anything is written (one size for
    every view: refused once, not skipped view by view)."""
    from tiltfit.report.real_vs_rendered import RealVsRenderedError, comparison_scale, pick_views

    n = len(data.get("views") or [])
    if options.views is not None:
        bad = [v for v in options.views if not -n <= v < n]
        if bad:
            raise CliError("--views", f"view {bad[0]} does not exist (the calibration has {n} views"
                                      + (f": 0 to {n - 1})" if n else ")"))
        pick_views(n, options)
    if options.scale is not None:
        try:
            comparison_scale(data["image_size_px"], options)
        except RealVsRenderedError:
            W, H = data["image_size_px"]
            raise CliError("--scale", f"{options.scale} does not divide the calibration's {W}x{H} images into "
                                      "whole pixels") from None


def _real_vs_rendered_options(args):
    """`tiltfit report`'s real-against-rendered options from the command line (one-line errors naming the flag)."""
    from tiltfit.report.real_vs_rendered import DEFAULT_SPP, MAX_SPP, RealVsRenderedOptions

    views = None
    if args.views is not None:
        try:
            views = tuple(int(v) for v in args.views.split(",") if v.strip())
        except ValueError:
            raise CliError("--views", f"expected view indices separated by commas (0,3,7), got {args.views!r}") from None
    for flag, value, low in (("--max-views", args.max_views, 0), ("--spp", args.spp, 1), ("--scale", args.scale, 1)):
        if value is not None and value < low:
            raise CliError(flag, f"expected an integer >= {low}, got {value}")
    if args.spp is not None and args.spp > MAX_SPP:
        raise CliError("--spp", f"expected at most {MAX_SPP} samples per pixel, got {args.spp}")
    for folder in args.photos or []:
        if not os.path.isdir(folder):
            raise CliError(folder, "--photos: not a folder")
    say = progress_printer(args.quiet)
    return RealVsRenderedOptions(views=views, max_views=args.max_views, photos_dirs=tuple(args.photos or ()),
                                 spp=DEFAULT_SPP if args.spp is None else args.spp, scale=args.scale,
                                 encoding=args.encoding, say=say)


def cmd_compare(args) -> int:
    """`tiltfit compare A.json B.json [-o DIR]`."""
    from tiltfit.files.calib import read_calib

    if args.output and os.path.exists(args.output) and not os.path.isdir(args.output):
        raise CliError(args.output, "not a folder")
    for path in (args.a, args.b):
        if not os.path.isfile(path):  # both refused before a calibration's checks load torch
            raise CliError(path, "is a folder" if os.path.isdir(path) else "no such file")
    data = []
    for path in (args.a, args.b):
        try:
            data.append(read_calib(path))
        except ValueError as e:
            raise as_cli_error(path, e) from None
    from tiltfit.uncertainty.compare import CompareError, compare, summary_lines, write_compare  # after the checks: loads torch

    try:
        res = compare(*data, rotation=not args.no_rotation)
    except CompareError as e:
        raise CliError(args.b, str(e)) from None
    if res.get("warning"):
        print(f"tiltfit: warning: {args.a}, {args.b}: {res['warning']}", file=sys.stderr, flush=True)
    print("\n".join(summary_lines(res, args.a, args.b)))
    if args.output:
        try:
            files = write_compare(res, args.output, args.a, args.b)
        except OSError as e:
            raise CliError(args.output, f"cannot write ({os_reason(e)})") from None
        for f in files:
            progress_printer(args.quiet)(f"wrote {f}")
    return 0
