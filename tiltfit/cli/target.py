"""`tiltfit target design|print`: the target designer and the printable on the command line.

    tiltfit target design --cols N --rows M (--square-mm S | --square-px P --pixel-pitch-mm p)
                          --w-mm W --distance-mm D [--inclination-deg PHI] [--margin-mm 25] -o T.json
    tiltfit target design --charuco DICT_5X5_100 --cols N --rows M --square-mm S [--marker-mm M]
                          [--margin-mm 25] -o T.json
    tiltfit target print T.json [--png OUT.png] [--pdf OUT.pdf] [--dpi 300] [--scale-bar-mm L]

`design` writes a target whose rows project equally spaced in the design view (`tiltfit.target.design.design_target`:
a camera with lens-to-sensor distance W looking at the board D away, the board inclined by PHI about its X
axis); with `--charuco` a ChArUco board (`tiltfit.target.layout.CharucoTarget`, OpenCV's CharucoBoard: uniform
squares, markers of the dictionary in the white cells). `print` writes the board at true size with a labelled
scale bar (`tiltfit.target.printable.write_printable`).
Errors print one line `tiltfit: <file or option>: <problem>` on stderr and exit with status 2.
"""
from __future__ import annotations

import argparse
import math
import os
import sys

from camio.errors import one_line, os_reason

EXIT_ERROR = 2


class _OneLineParser(argparse.ArgumentParser):
    """argparse with its usage errors as one line `tiltfit: <option>: <problem>` (exit 2)."""

    def error(self, message):
        msg = one_line(message)
        if msg.startswith("argument "):
            where, _, problem = msg[len("argument "):].partition(": ")
            msg = f"{where.split('/')[-1]}: {problem}"
        self.exit(EXIT_ERROR, f"tiltfit: {msg} (see tiltfit target {self.prog.split()[-1]} --help)\n"
                  if self.prog.split()[-1] in ("design", "print") else f"tiltfit: {msg}\n")


def build_parser() -> argparse.ArgumentParser:
    ap = _OneLineParser(prog="tiltfit target", description="Design a target and print it at true size.")
    sub = ap.add_subparsers(dest="action", required=True, metavar="ACTION")

    p = sub.add_parser("design", help="a target whose rows project equally spaced for a design view")
    p.add_argument("--cols", type=int, required=True, help="number of cell columns")
    p.add_argument("--rows", type=int, required=True, help="number of cell rows (cols + rows odd: no 180° twin)")
    p.add_argument("--square-mm", type=float, help="column width and central row height, mm")
    p.add_argument("--square-px", type=float, help="projected size of the central square, pixels (with "
                                                   "--pixel-pitch-mm)")
    p.add_argument("--pixel-pitch-mm", type=float, help="sensor pixel pitch, mm")
    p.add_argument("--w-mm", type=float, help="lens-to-sensor distance of the design view, mm (checkerboards)")
    p.add_argument("--distance-mm", type=float, help="distance to the board's design centre, mm (checkerboards)")
    p.add_argument("--inclination-deg", type=float, default=0.0, help="board inclination about its X axis [0]")
    p.add_argument("--margin-mm", type=float, default=25.0, help="white margin around the checkered area [25]")
    p.add_argument("--charuco", metavar="DICT", help="a ChArUco board with markers of this OpenCV dictionary, e.g. "
                                                     "DICT_5X5_100 (uniform squares; no design view)")
    p.add_argument("--marker-mm", type=float, help="ChArUco marker side incl. its border, mm [0.75 × --square-mm]")
    p.add_argument("-o", "--output", required=True, metavar="T.json")
    p.add_argument("-q", "--quiet", action="store_true", help="no notes on stderr")

    p = sub.add_parser("print", help="the board at true size with a labelled scale bar (PNG and/or PDF)")
    p.add_argument("target", metavar="T.json")
    p.add_argument("--png", metavar="OUT.png", help="raster at --dpi")
    p.add_argument("--pdf", metavar="OUT.pdf", help="vector PDF, page = board + scale bar")
    p.add_argument("--dpi", type=float, default=300.0, help="PNG resolution [300]")
    p.add_argument("--scale-bar-mm", type=float, help="length of the scale bar [largest of 10/20/50/100/200 that "
                                                      "fits]")
    p.add_argument("-q", "--quiet", action="store_true", help="no notes on stderr")
    return ap


class _Fail(Exception):
    def __init__(self, where: str, problem: str):
        super().__init__(f"{where}: {problem}")


def _design(args, say) -> None:
    from tiltfit.files.det import MIN_CORNERS
    from tiltfit.target.design import design_target
    from tiltfit.target.layout import MAX_EDGES, MAX_FEATURE_POINTS, MAX_MM, TargetError, target_from_dict

    for name in ("cols", "rows"):
        v = getattr(args, name)
        if v < 2:
            raise _Fail(f"--{name}", f"expected at least 2 cells, got {v}")
    if (args.cols - 1) * (args.rows - 1) < MIN_CORNERS:
        raise _Fail("--cols", f"{args.cols} × {args.rows} cells have {(args.cols - 1) * (args.rows - 1)} inner "
                              f"corners; a view needs at least {MIN_CORNERS} to calibrate (more cells)")
    if (args.cols - 1) * (args.rows - 1) > MAX_FEATURE_POINTS:
        raise _Fail("--cols", f"{args.cols} × {args.rows} cells have more corners than the detector handles "
                              f"({MAX_FEATURE_POINTS})")
    for name in ("square_mm", "square_px", "pixel_pitch_mm", "w_mm", "distance_mm", "margin_mm"):
        v = getattr(args, name)
        if v is not None and not (math.isfinite(v) and (v > 0 or (name == "margin_mm" and v == 0))):
            raise _Fail("--" + name.replace("_", "-"), f"expected a positive number, got {v}")
    if args.charuco is not None:
        # uniform squares: the design view's options would change nothing, so they are refused, not ignored
        for name in ("w_mm", "distance_mm", "square_px", "pixel_pitch_mm"):
            if getattr(args, name) is not None:
                raise _Fail("--" + name.replace("_", "-"), "a ChArUco board has uniform squares and no design view")
        if args.inclination_deg != 0:
            raise _Fail("--inclination-deg", "a ChArUco board has uniform squares and no design view")
        return _design_charuco(args, say)
    if args.marker_mm is not None:
        raise _Fail("--marker-mm", "markers belong to a ChArUco board (--charuco DICT)")
    for name in ("w_mm", "distance_mm"):
        if getattr(args, name) is None:
            raise _Fail("--" + name.replace("_", "-"), "required for a checkerboard design (the design view)")
    if (args.square_mm is None) == (args.square_px is None):
        raise _Fail("--square-mm", "give --square-mm, or --square-px with --pixel-pitch-mm")
    if args.square_px is not None and args.pixel_pitch_mm is None:
        raise _Fail("--pixel-pitch-mm", "--square-px needs the sensor's pixel pitch")
    for name in ("cols", "rows"):
        if getattr(args, name) + 1 > MAX_EDGES:
            raise _Fail(f"--{name}", f"expected at most {MAX_EDGES - 1} cells (the target format's limit), got "
                                     f"{getattr(args, name)}")
    if args.margin_mm > MAX_MM:
        raise _Fail("--margin-mm", f"expected at most {MAX_MM:g} mm, got {args.margin_mm:g}")
    try:
        target = design_target(args.cols, args.rows, args.square_mm, w_mm=args.w_mm, distance_mm=args.distance_mm,
                               inclination_deg=args.inclination_deg, pixel_pitch_mm=args.pixel_pitch_mm,
                               square_px=args.square_px, margin_mm=args.margin_mm)
        target_from_dict(target.to_dict(), args.output)  # what the target format reads back
    except TargetError as e:
        raise _Fail(args.output, str(e).removeprefix(f"{args.output}: ")) from None
    if (args.cols + args.rows) % 2 == 0:
        say(f"{args.output}: note: {args.cols} + {args.rows} cells is even, so the board looks alike turned by "
            f"180° unless its rows differ; detection then labels it by image geometry (any labelling is a "
            f"valid pose). An odd sum avoids the ambiguity.")
    try:
        folder = os.path.dirname(os.path.abspath(args.output))
        os.makedirs(folder, exist_ok=True)
        target.save(args.output)
    except OSError as e:
        raise _Fail(args.output, f"cannot write ({os_reason(e)})") from None
    x, y = target.x_edges[-1] - target.x_edges[0], target.y_edges[-1] - target.y_edges[0]
    say(f"wrote {args.output}: {args.cols} × {args.rows} cells, {x:.1f} × {y:.1f} mm, "
        f"{target.grid_shape[1]} × {target.grid_shape[0]} corners")


def _design_charuco(args, say) -> None:
    from tiltfit.target.layout import TargetError, target_from_dict

    if args.square_mm is None:
        raise _Fail("--square-mm", "a ChArUco board needs --square-mm")
    marker = 0.75 * args.square_mm if args.marker_mm is None else args.marker_mm
    if not (math.isfinite(marker) and 0 < marker < args.square_mm):
        raise _Fail("--marker-mm", f"expected a length between 0 and --square-mm ({args.square_mm:g}), got {marker:g}")
    data = {"type": "charuco", "units": "mm", "dictionary": args.charuco, "squares": [args.cols, args.rows],
            "square_mm": args.square_mm, "marker_mm": marker, "margin": args.margin_mm}
    try:
        target = target_from_dict(data, args.output)
    except TargetError as e:
        field = str(e).removeprefix(f"{args.output}: ").split(":", 1)
        option = {"dictionary": "--charuco", "squares": "--cols", "square_mm": "--square-mm",
                  "marker_mm": "--marker-mm", "margin": "--margin-mm"}.get(field[0])
        raise _Fail(option or args.output, field[-1].strip()) from None
    try:
        os.makedirs(os.path.dirname(os.path.abspath(args.output)), exist_ok=True)
        target.save(args.output)
    except OSError as e:
        raise _Fail(args.output, f"cannot write ({os_reason(e)})") from None
    say(f"wrote {args.output}: ChArUco {args.cols} × {args.rows} squares of {args.square_mm:g} mm, markers "
        f"{marker:g} mm ({args.charuco}), {target.grid_shape[1]} × {target.grid_shape[0]} corners")


def _print(args, say) -> None:
    from tiltfit.target.layout import TargetError, load_target
    from tiltfit.target.printable import MAX_PRINT_DPI, MIN_PRINT_DPI, write_printable

    if not args.png and not args.pdf:
        raise _Fail("--png", "give --png OUT.png and/or --pdf OUT.pdf")
    if not (math.isfinite(args.dpi) and MIN_PRINT_DPI <= args.dpi <= MAX_PRINT_DPI):
        raise _Fail("--dpi", f"expected {MIN_PRINT_DPI:g} to {MAX_PRINT_DPI:g} dots per inch, got {args.dpi:g}")
    if args.scale_bar_mm is not None and not (math.isfinite(args.scale_bar_mm) and args.scale_bar_mm > 0):
        raise _Fail("--scale-bar-mm", f"expected a positive length, got {args.scale_bar_mm}")
    try:
        target = load_target(args.target)
    except TargetError as e:
        raise _Fail(args.target, str(e).removeprefix(f"{args.target}: ")) from None
    try:
        write_printable(target, args.png, args.pdf, dpi=args.dpi, scale_bar_mm=args.scale_bar_mm)
    except TargetError as e:
        field = str(e).split(":", 1)[0]
        if field in ("dpi", "scale_bar_mm"):
            raise _Fail("--" + field.replace("_", "-"), str(e).split(": ", 1)[1]) from None
        raise _Fail(args.target, str(e)) from None
    except OSError as e:
        raise _Fail(args.png or args.pdf, f"cannot write ({os_reason(e)})") from None
    for path in (args.png, args.pdf):
        if path:
            say(f"wrote {path}: print at 100 % and check the scale bar with a ruler")


def main(argv=None) -> int:
    args = build_parser().parse_args(sys.argv[1:] if argv is None else [str(a) for a in argv])

    def say(line: str):
        if not args.quiet:
            print(line, file=sys.stderr, flush=True)

    try:
        (_design if args.action == "design" else _print)(args, say)
    except _Fail as e:
        print(f"tiltfit: {e}", file=sys.stderr)
        return EXIT_ERROR
    return 0
