"""`tiltfit calibrate`: the arguments checked before any work, the `--init` calibration read, the corner-and-blur
fit with its held-out error (`tiltfit.calibrate.photos.fit_with_held_out`), then `--refine photometric`
(`tiltfit.cli.photometric`) and `--cross-validate`, and CALIB.json written."""
from __future__ import annotations

import math
import os
import sys
import time

from camio.errors import os_reason
from camio.files import quiet_c_stderr

from .detect import is_det_file, load_target_file, observations
from .errors import CliError, as_cli_error, check_output, check_range, progress_printer
from .photometric import refine_calibration

# Stated ranges of the command-line numbers (mm); beyond them the value is a unit mistake.
MAX_PIXEL_PITCH_MM = 10.0
MAX_FOCAL_MM = 10000.0
MAX_ITERATIONS = 100000
MAX_HELD_OUT = 1000


def cmd_calibrate(args) -> int:
    """`tiltfit calibrate IMAGE... --target T.json --pixel-pitch-mm P -o CALIB.json` (see `tiltfit.cli.main`)."""
    say = progress_printer(args.quiet)
    t0 = time.perf_counter()
    _check_arguments(args)
    target = load_target_file(args.target)
    from tiltfit.calibrate.fit import FitError
    from tiltfit.calibrate.photos import fit_with_held_out
    from tiltfit.files.calib import calib_dict, write_calib

    init, init_sigma = _read_init(args)
    if args.refine == "photometric":  # what the refinement cannot take is known before any image is read
        _check_photometric_inputs(args, target)
    images = {} if args.refine == "photometric" else None  # read once, for detection and the refinement
    obs = observations(args, target, say, images)
    if init is not None and tuple(init.image_size_px) != tuple(obs.image_size_px):
        raise CliError(args.init, f"image_size_px {list(init.image_size_px)} differs from the images' "
                                  f"{list(obs.image_size_px)}")
    options = _fit_options(args, init, say)
    label = args.inputs[0] if len(args.inputs) == 1 else f"{args.inputs[0]} (+{len(args.inputs) - 1} more)"
    if args.cross_validate is not None and obs.n_views < 2 * args.cross_validate:
        raise CliError("--cross-validate", f"{args.cross_validate} groups need at least {2 * args.cross_validate} "
                                           f"views with a board (two a group); there are {obs.n_views}")
    try:
        result, used, held_out = fit_with_held_out(obs, args.fit, init=init, options=options, init_sigma=init_sigma,
                                                   held_out_folds=args.held_out, say=say)
    except FitError as e:
        raise CliError(label, str(e)) from None
    result.skipped = list(obs.skipped) + list(result.skipped)
    _say_notes(result, say)
    photometric = refine_calibration(result, used, target, args, say, images, held_out) \
        if args.refine == "photometric" else None
    cross = _cross_validate(result, used, options, args.cross_validate, say) if args.cross_validate else None
    data = calib_dict(result, runtime_s=time.perf_counter() - t0, obs=used, target=target.to_dict(),
                      held_out=held_out)
    if cross is not None:
        data["cross_validation"] = cross
    if photometric is not None:
        data["refinement"], data["photometric"] = "photometric", photometric
    try:
        write_calib(args.output, data)
    except OSError as e:
        raise CliError(args.output, f"cannot write ({os_reason(e)})") from None
    say(f"wrote {args.output}")
    return 0


def _check_arguments(args) -> None:
    """Refuse, before the fit's modules load (seconds: torch), options out of range and missing inputs."""
    check_output(args.output)
    check_range("--pixel-pitch-mm", args.pixel_pitch_mm, 0.0, MAX_PIXEL_PITCH_MM, "a pixel pitch in mm")
    if args.focal_mm is not None:
        check_range("--focal-mm", args.focal_mm, 0.0, MAX_FOCAL_MM, "a focal length in mm")
    if not 0 <= args.held_out <= MAX_HELD_OUT:
        raise CliError("--held-out", f"expected 0 (off) to {MAX_HELD_OUT} folds, got {args.held_out}")
    if not 1 <= args.max_iterations <= MAX_ITERATIONS:
        raise CliError("--max-iterations", f"expected 1 to {MAX_ITERATIONS}, got {args.max_iterations}")
    if args.fit == "tilt" and not args.init:
        raise CliError("--init", "the tilt fit (stage 2) needs the stage-1 CALIB.json as --init")
    if args.cross_validate is not None and not 2 <= args.cross_validate <= MAX_HELD_OUT:
        raise CliError("--cross-validate", f"expected 2 to {MAX_HELD_OUT} groups, got {args.cross_validate}")
    for path in args.inputs + ([args.init] if args.init else []):
        if not os.path.isfile(path):
            raise CliError(path, "no such file")


def _read_init(args):
    """(the `--init` camera, its σ) from a CALIB.json, an OpenCV camera file or an mrcal .cameramodel; (None,
    None) without --init."""
    if not args.init:
        return None, None
    from tiltfit.files.calib import camera_from_calib, read_calib, sigma_from_calib, validate_calib
    from tiltfit.files.mrcal_file import is_mrcal_file, read_mrcal
    from tiltfit.files.opencv_file import is_opencv_file, read_opencv

    try:
        if is_mrcal_file(args.init):
            data = validate_calib(args.init, read_mrcal(args.init, args.pixel_pitch_mm))
        elif is_opencv_file(args.init):
            with quiet_c_stderr():  # OpenCV's parser prints its complaints before raising
                data = validate_calib(args.init, read_opencv(args.init, args.pixel_pitch_mm))
        else:
            data = read_calib(args.init)
        init = camera_from_calib(data, args.blur_model)
    except ValueError as e:
        raise as_cli_error(args.init, e) from None
    init_sigma = sigma_from_calib(data)
    if args.fit == "tilt" and (data.get("U_mm") is None or data.get("d_mm") is None):
        raise CliError(args.init, "U_mm, d_mm: undetermined in this calibration; the tilt fit needs them")
    return init, init_sigma


def _fit_options(args, init, say):
    """The `FitOptions` the command line asks for (blur model: --blur-model, else --init's, else ellipse)."""
    from tiltfit.calibrate.fit import FitOptions

    blur_model = args.blur_model or (init.blur_model if init is not None else "ellipse")
    return FitOptions(robust=args.robust, free_principal_point=args.principal_point,
                      held_out_folds=args.held_out or FitOptions.held_out_folds,
                      blur_model=blur_model, nominal_focal_mm=args.focal_mm,
                      max_iterations=args.max_iterations, model_selection=not args.no_model_selection,
                      progress=say, distortion=args.distortion, distortion_centre=args.distortion_centre,
                      board=args.board)


def _say_notes(result, say) -> None:
    """The fit's σ model, notes and warnings on stderr (notes other than the distortion choice even with -q)."""
    if result.sigma_model.get("design_effect"):
        say(f"σ error model: per-view ({result.sigma_model['n_views']} views; σ of the lens "
            f"{math.sqrt(result.sigma_model['design_effect']):.2g}× the independent-noise σ on average)")
    for note in result.notes:
        if note.startswith("distortion auto:"):
            say(note)  # the choice is progress; what the data cannot determine is worth a line even with -q
        else:
            print(f"tiltfit: note: {note}", file=sys.stderr, flush=True)
    for warning in result.warnings:
        print(f"tiltfit: warning: {warning}", file=sys.stderr, flush=True)


def _check_photometric_inputs(args, target) -> None:
    """Refuse `--refine photometric` up front where it cannot run: a target with markers (the photometric model
    renders checkerboards) or DET files instead of photographs."""
    if target.dark_rectangles():
        raise CliError(args.target, "--refine photometric: the photometric model renders checkerboards; a ChArUco "
                                    "board's markers are not modelled (calibrate without --refine)")
    for path in args.inputs:
        if is_det_file(path):
            raise CliError(path, "--refine photometric needs the photographs, not DET files")


def _cross_validate(result, obs, options, k: int, say) -> dict:
    """`--cross-validate K`: the views split into K interleaved groups, each calibrated alone (the chosen
    distortion and principal-point state, no model selection), every pair compared (`tiltfit.uncertainty.compare`)."""
    from dataclasses import replace

    from tiltfit.files.calib import calib_dict
    from tiltfit.files.calibrated import Calibration
    from tiltfit.calibrate.flow import calibrate
    from tiltfit.uncertainty.compare import compare, summary_lines
    from tiltfit.calibrate.fit import FitError

    groups = [list(range(g, obs.n_views, k)) for g in range(k)]
    opts = replace(options, distortion=result.distortion_model, free_principal_point=result.free_principal_point,
                   model_selection=False, progress=None)
    calibs = []
    for g, views in enumerate(groups):
        try:
            fit = calibrate(obs.subset(views), result.mode, options=opts)
        except FitError as e:
            raise CliError("--cross-validate", f"group {g + 1} of {k} ({len(views)} views): {e}") from None
        calibs.append(calib_dict(fit))
        say(f"cross-validation: group {g + 1} of {k} calibrated ({len(views)} views)")
    pairs = []
    for a in range(k):
        for b in range(a + 1, k):
            res = compare(calibs[a], calibs[b], nx=24)
            for line in summary_lines(res, f"group {a + 1}", f"group {b + 1}"):
                print(f"tiltfit: cross-validation: {line}", file=sys.stderr, flush=True)
            pairs.append({"groups": [a + 1, b + 1]} | {key: res[key] for key in (
                "median_px", "worst_px", "predicted_median_px", "predicted_worst_px", "rms_ratio", "consistent",
                "verdict", "rotation_deg")})
    return {"k": k, "groups": [[obs.names[v] for v in views] for views in groups], "pairs": pairs,
            "focal_px": [Calibration.from_dict(c).focal_px for c in calibs],
            "sigma_focal_px": [Calibration.from_dict(c).sigma_focal_px for c in calibs],
            "principal_point_px": [c["principal_point_px"] for c in calibs],
            "sigma_principal_point_px": [c["sigma"]["principal_point_px"] for c in calibs]}
