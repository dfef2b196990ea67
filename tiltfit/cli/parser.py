"""The `tiltfit` argument parser: one function a command (`tiltfit.cli.main.main` runs what it parses)."""
from __future__ import annotations

import argparse

from .calibrate import cmd_calibrate
from .detect import cmd_detect
from .export import cmd_export
from .report import cmd_compare, cmd_report


def build_parser() -> argparse.ArgumentParser:
    """The parser of `tiltfit COMMAND ...`; reproduce, stability and target are listed for --help only: they parse
    their own arguments (see `tiltfit.cli.main.main`)."""
    ap = argparse.ArgumentParser(prog="tiltfit", description="Tilt-lens calibration (Baba, Nakane, Hiura 2017).")
    sub = ap.add_subparsers(dest="command", required=True, metavar="COMMAND")
    _add_detect(sub)
    _add_calibrate(sub)
    _add_export(sub)
    _add_report(sub)
    _add_compare(sub)

    # Listed for --help; its arguments are parsed by tiltfit.experiments.reproduce itself (see main).
    sub.add_parser("reproduce", help="the paper's experiment end to end on a simulated camera", add_help=False)
    sub.add_parser("stability", help="where each method fails, and how ours behaves there", add_help=False)
    sub.add_parser("target", help="design a target (design) or print it at true size (print)", add_help=False)
    return ap


def _add_detect(sub) -> None:
    """`tiltfit detect`: one image to a DET.json."""
    p = sub.add_parser("detect", help="find the target's corners and blur widths in one image")
    p.add_argument("image", metavar="IMAGE")
    p.add_argument("--target", required=True, metavar="T.json", help="target file")
    p.add_argument("--encoding", choices=("srgb", "linear"), help="override the file's encoding")
    p.add_argument("-o", "--output", required=True, metavar="DET.json")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress on stderr")
    p.set_defaults(func=cmd_detect)


def _add_calibrate(sub) -> None:
    """`tiltfit calibrate`: images (or DET.json files) to a CALIB.json."""
    p = sub.add_parser("calibrate", help="calibrate w, U, d, θF and the poses from target images")
    p.add_argument("inputs", nargs="+", metavar="IMAGE", help="target images (or DET.json files)")
    p.add_argument("--target", required=True, metavar="T.json", help="target file")
    p.add_argument("--pixel-pitch-mm", required=True, type=float, metavar="P", help="sensor pixel pitch, mm")
    p.add_argument("--fit", choices=("unified", "tilt", "joint"), default="unified",
                   help="unified: stage 1 (θF = 0); tilt: stage 2 (w, U, d from --init held); joint: all free "
                        "[unified]")
    p.add_argument("--init", metavar="CALIB.json", help="starting (tilt: held) lens parameters")
    p.add_argument("--encoding", choices=("srgb", "linear"), help="override the images' encoding")
    p.add_argument("--focal-mm", type=float, help="nominal focal length to start w from (default: estimated "
                                                  "from the views)")
    p.add_argument("--robust", choices=("huber", "cauchy"), help="robust loss (threshold 3σ)")
    pp = p.add_mutually_exclusive_group()
    pp.add_argument("--free-principal-point", dest="principal_point", action="store_const", const=True,
                    help="always fit the principal point (default: fitted where a likelihood-ratio test on the "
                         "corners justifies it)")
    pp.add_argument("--fixed-principal-point", dest="principal_point", action="store_const", const=False,
                    help="hold the principal point at the image centre (or --init's)")
    p.add_argument("--blur-model", choices=("ellipse", "first_order", "paper"),
                   help="blur model: exact spot (ellipse, default), first order, or the paper's eq (4)")
    p.add_argument("--max-iterations", type=int, default=200, help="Levenberg–Marquardt iterations [200]")
    p.add_argument("--no-model-selection", action="store_true",
                   help="skip the θF / principal-point tests (the principal point is then held unless "
                        "--free-principal-point)")
    p.add_argument("--distortion", choices=("auto", "none", "k1", "k1k2", "opencv5", "rational5", "rational"), default="auto",
                   help="lens distortion terms (OpenCV's order); auto: the model with the smallest K-fold "
                        "held-out error (--held-out K, 5 if 0) whose radial mapping is one-to-one over the image "
                        "[auto]")
    p.add_argument("--distortion-centre", choices=("auto", "sensor"), default="auto",
                   help="where a tilted lens's distortion is centred: auto tests its own axis against the "
                        "principal point in the joint fit (CALIB.json distortion_centre); sensor holds it at the "
                        "principal point [auto]")
    p.add_argument("--board", choices=("auto", "flat", "warp", "free"), default="auto",
                   help="the target's shape: flat (the target file's points), warp (sag along X and Y and the "
                        "print scale along Y), free (every point, as OpenCV's calibrateCameraRO), or auto (the "
                        "simplest the K-fold held-out error supports) [auto]")
    p.add_argument("--refine", choices=("none", "photometric"), default="none",
                   help="photometric: after the corner-and-blur fit, fit the photos' pixels by rendering the "
                        "target (analysis by synthesis; needs the images, not DET files) [none]")
    p.add_argument("--psf", choices=("disc", "disc_gaussian", "auto"), default="disc",
                   help="blur kernel of --refine photometric: the lens's disc, the disc convolved with a fitted "
                        "Gaussian, or auto (the Gaussian where a likelihood-ratio test justifies it) [disc]")
    p.add_argument("--held-out", type=int, default=5, metavar="K",
                   help="K-fold held-out reprojection error (RMS per corner) beside the fit RMS (0: skip) [5]")
    p.add_argument("--cross-validate", type=int, metavar="K",
                   help="also split the views into K groups, calibrate each alone and compare every pair's "
                        "projection with what their σ predict (stderr and cross_validation in CALIB.json)")
    p.add_argument("-o", "--output", required=True, metavar="CALIB.json")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress on stderr")
    p.set_defaults(func=cmd_calibrate)


def _add_export(sub) -> None:
    """`tiltfit export`: a CALIB.json for OpenCV or mrcal."""
    p = sub.add_parser("export", help="write a calibration for another library (OpenCV FileStorage, mrcal)")
    p.add_argument("calib", metavar="CALIB.json")
    p.add_argument("--to", choices=("opencv", "mrcal"), default="opencv",
                   help="format: opencv (FileStorage .yml/.xml/.json) or mrcal (.cameramodel) [opencv]")
    p.add_argument("-o", "--output", required=True, metavar="camera.yml|camera.cameramodel")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress on stderr")
    p.set_defaults(func=cmd_export)


def _add_report(sub) -> None:
    """`tiltfit report`: plots of a calibration, and its photos against renderings through it."""
    p = sub.add_parser("report", help="residual, blur and coverage plots of a calibration, and its photos against "
                                      "the target rendered through it")
    p.add_argument("calib", metavar="CALIB.json")
    p.add_argument("-o", "--output", required=True, metavar="DIR")
    p.add_argument("--photos", action="append", metavar="DIR",
                   help="folder where the views' photos are looked for by name when their stored path is not there "
                        "(repeatable)")
    p.add_argument("--views", metavar="K,K,...", help="views compared with renderings (indices) [--max-views of them, "
                                                      "spread over the views]")
    p.add_argument("--max-views", type=int, default=6, metavar="N",
                   help="views compared with renderings when --views is not given; 0: none [6]")
    p.add_argument("--spp", type=int, default=None, help="samples per pixel of the renderings [8; at most 1024]")
    p.add_argument("--scale", type=int, default=None, metavar="K",
                   help="compare at 1/K of the photos' resolution [the smallest K giving at most 640 px across]")
    p.add_argument("--encoding", choices=("srgb", "linear"), default=None,
                   help="the photos' encoding [as the file says; 8-bit: srgb]")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress on stderr")
    p.set_defaults(func=cmd_report)


def _add_compare(sub) -> None:
    """`tiltfit compare`: two calibrations against what their σ predict."""
    p = sub.add_parser("compare", help="cross-validate two calibrations: projection difference against what "
                                       "their σ predict")
    p.add_argument("a", metavar="A.json")
    p.add_argument("b", metavar="B.json")
    p.add_argument("-o", "--output", metavar="DIR", help="write compare.png (difference and predicted maps) and "
                                                          "compare.json")
    p.add_argument("--no-rotation", action="store_true",
                   help="compare without the best-fitting rotation between the camera frames (which absorbs a "
                        "common shift of the principal point): such a shift then counts in full")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress on stderr")
    p.set_defaults(func=cmd_compare)
