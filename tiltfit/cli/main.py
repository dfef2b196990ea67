"""Command line: `tiltfit detect`, `tiltfit calibrate`, `tiltfit reproduce`, `tiltfit stability`.

    tiltfit detect IMAGE --target T.json [--encoding srgb|linear] -o DET.json
    tiltfit calibrate IMAGE... --target T.json --pixel-pitch-mm P [--fit unified|tilt|joint]
                      [--init CALIB.json] [--encoding srgb|linear] -o CALIB.json
                      [--distortion auto|none|k1|k1k2|opencv5|rational5|rational] [--held-out K]
                      [--free-principal-point | --fixed-principal-point]
    tiltfit export CALIB.json --to opencv|mrcal -o camera.yml|camera.cameramodel
    tiltfit report CALIB.json -o DIR
    tiltfit compare A.json B.json [-o DIR]        (projection difference against the two σ' prediction)
    tiltfit reproduce [--quick] [--scale N] [--target-scale N] [--device cpu|cuda] [-o DIR]
    tiltfit stability [--quick] [-o DIR]
    tiltfit target design|print ...   (tiltfit.cli.target: the target designer and the printable)

`calibrate` also accepts DET.json files (written by `tiltfit detect`) in place of images; an image where no
board is found is skipped with a warning (listed under `skipped` in CALIB.json). `--init` accepts a CALIB.json
or an OpenCV camera file (`tiltfit export`'s, or any FileStorage with camera_matrix and image size), or an
mrcal .cameramodel (LENSMODEL_PINHOLE or OPENCV4/5/8).
Errors (bad or missing file, missing key, no board found, truncated image, a fit that does not converge)
print one line `tiltfit: <file>: <problem>` on stderr and exit with status 2, leaving no output file; an
interrupt (Ctrl-C, SIGTERM) prints `tiltfit: interrupted` and exits with 130. Input files are checked by
`camio.checks` (encoding, depth, numbers), `tiltfit.target.layout`, `tiltfit.files.det` and `tiltfit.files.calib`.
Progress goes to stderr; nothing but results goes to stdout.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import re
import signal
import sys
import time
import warnings

from camio.interrupts import interrupt_on_sigterm
from camio.files import output_problem
from camio.files import quiet_c_stderr as _quiet_c_stderr

EXIT_ERROR = 2
MIN_VIEWS_AFTER_SKIPPING = 3  # when images without a board were skipped, at least this many must remain
EXIT_INTERRUPTED = 130
# Stated ranges of the command-line numbers (mm); beyond them the value is a unit mistake.
MAX_PIXEL_PITCH_MM = 10.0
MAX_FOCAL_MM = 10000.0
MAX_ITERATIONS = 100000
MAX_HELD_OUT = 1000


class CliError(Exception):
    """A user-facing failure: `tiltfit: <file>: <problem>`."""

    def __init__(self, file: str, problem: str):
        super().__init__(f"{file}: {problem}")
        self.file, self.problem = file, problem


#: The library's names for what the command line calls an option (library messages speak in API terms).
_API_TO_OPTION = {"as the pixel_pitch_mm argument": "as --pixel-pitch-mm"}


def _in_cli_terms(msg: str) -> str:
    """A library message with its API names replaced by the command-line options they come from."""
    for api, option in _API_TO_OPTION.items():
        msg = msg.replace(api, option)
    return msg


def _as_cli_error(file: str, err: Exception) -> CliError:
    """Wrap an exception whose message may already start with the file name (one line, in command-line
    terms)."""
    msg = _in_cli_terms("; ".join(line.strip() for line in str(err).strip().splitlines()) or type(err).__name__)
    prefix = f"{file}: "
    if msg.startswith(prefix):
        return CliError(file, msg[len(prefix):])
    located = re.match(rf"{re.escape(file)}(:\d+:\d+): (.*)", msg)
    if located:  # a parser's `FILE:LINE:COL: problem`, named once as the renderer writes it
        return CliError(file + located[1], located[2])
    return CliError(file, msg)


def _say(quiet: bool):
    def say(line: str):
        if not quiet:
            print(line, file=sys.stderr, flush=True)

    return say


# --- detection ---------------------------------------------------------------------------------------------

def _load_target(path: str):
    from tiltfit.target.layout import load_target

    try:
        return load_target(path)
    except (ValueError, OSError) as e:
        raise _as_cli_error(path, e) from None


def _detect_image(path: str, target, encoding: str | None, keep: dict | None = None) -> dict:
    """Read an image, detect the board; returns the DET.json dict. Raises CliError naming the image.
    `keep`: where given, the image read is stored there under its path (for `--refine photometric`)."""
    from renderer import read_image

    from tiltfit.files.det import MAX_IMAGE_PIXELS

    try:
        with _quiet_c_stderr():
            image = read_image(path, encoding, MAX_IMAGE_PIXELS)
    except (ValueError, OSError) as e:
        raise _as_cli_error(path, e) from None
    except MemoryError:
        raise CliError(path, "out of memory reading the image") from None
    if keep is not None:
        keep[path] = image
    try:
        from tiltfit.detect.charuco import detect_board as detect
    except ImportError:
        raise CliError(path, "board detection is not available in this installation (tiltfit.detect.chessboard)") from None
    try:
        found = detect(image, target)
    except (ValueError, RuntimeError, ImportError) as e:
        raise _as_cli_error(path, e) from None
    except MemoryError:
        raise CliError(path, f"out of memory detecting the board in this {image.shape[1]}x{image.shape[0]} "
                             "image") from None
    if hasattr(found, "to_json_dict"):
        det = found.to_json_dict()
    else:
        corners, blur = (found.corners_px, found.blur_px) if hasattr(found, "corners_px") else found
        det = _det_dict(image.shape[1], image.shape[0], corners, blur)
    if not det.get("grid_found") or not any(c is not None for c in det["corners_px"]):
        why = getattr(found, "message", "") or ""
        from tiltfit.detect.chessboard import CONTRADICTS

        if why.startswith(CONTRADICTS):  # a board was found, and the target file does not describe it
            raise CliError(path, why)
        raise CliError(path, "no board found" + (f" ({why})" if why else ""))
    return det


def _det_dict(width: int, height: int, corners, blur) -> dict:
    import numpy as np

    c = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
    b = np.asarray(blur, dtype=np.float64).reshape(-1)
    corners_out = [[float(x), float(y)] if np.isfinite(x) and np.isfinite(y) else None for x, y in c]
    blur_out = [float(v) if np.isfinite(v) else None for v in b]
    return {"image_size_px": [int(width), int(height)], "corners_px": corners_out, "blur_px": blur_out,
            "grid_found": any(v is not None for v in corners_out)}


def _write_json_atomic(path: str, data: dict) -> None:
    """Write JSON atomically with umask-respecting permissions (camio.files.atomic_output)."""
    from camio.files import write_text

    write_text(path, json.dumps(data, indent=1, allow_nan=False) + "\n")


def _read_det(path: str, n_points: int) -> dict:
    """Read and validate a DET.json for a target of n_points feature points (tiltfit.files.det)."""
    from tiltfit.files.det import DetFileError, read_det

    try:
        return read_det(path, n_points)
    except DetFileError as e:
        raise _as_cli_error(path, e) from None


def _is_det_file(path: str) -> bool:
    return path.lower().endswith(".json")


# --- commands ----------------------------------------------------------------------------------------------

def _check_output(path: str) -> None:
    """Refuse, before any work, an output path that cannot be written (`camio.files.output_problem`)."""
    problem = output_problem(path)
    if problem:
        raise CliError(path, problem)


def cmd_detect(args) -> int:
    import numpy as np

    say = _say(args.quiet)
    _check_output(args.output)
    target = _load_target(args.target)
    t0 = time.perf_counter()
    det = _detect_image(args.image, target, args.encoding)
    from tiltfit.files.det import MIRRORED, describe_detection, mirrored

    corners = [c if c is not None else [math.nan, math.nan] for c in det["corners_px"]]
    if mirrored(np.array(corners, dtype=np.float64), target.feature_points()):
        raise CliError(args.image, MIRRORED)

    det = describe_detection(det, args.image, args.target, target)
    n = sum(v is not None for v in det["corners_px"])
    say(f"{args.image}: {n} of {len(det['corners_px'])} corners in {time.perf_counter() - t0:.1f} s")
    if det.get("message"):
        say(f"{args.image}: note: {det['message']}")
    try:
        _write_json_atomic(args.output, det)
    except (OSError, ValueError) as e:
        raise CliError(args.output, f"cannot write ({e.strerror or e})") from None
    return 0


def _observations(args, target, say, images: dict | None = None):
    """Observations of all inputs (images are detected, DET.json files read; with `images`, each image read
    is kept there under its path)."""
    import numpy as np

    from tiltfit.files.det import too_few_corners
    from tiltfit.calibrate.model import MIN_CORNERS, Observations

    points = target.feature_points()
    corners, blur, size, names, skipped = [], [], None, [], []
    for path in args.inputs:
        if not os.path.isfile(path):
            raise CliError(path, "no such file")
        if _is_det_file(path):
            det = _read_det(path, len(points))
        else:
            t0 = time.perf_counter()
            try:
                det = _detect_image(path, target, args.encoding, images)
            except CliError as e:
                if not e.problem.startswith("no board found"):
                    raise
                print(f"tiltfit: warning: {path}: {e.problem}; skipped", file=sys.stderr, flush=True)
                skipped.append({"image": path, "reason": e.problem})
                continue
            n = sum(v is not None for v in det["corners_px"])
            say(f"{path}: {n} of {len(points)} corners detected in {time.perf_counter() - t0:.1f} s")
        if size is not None and list(det["image_size_px"]) != size:
            raise CliError(path, f"image size {det['image_size_px']} differs from the first input's {size}")
        view = [c if c is not None else [math.nan, math.nan] for c in det["corners_px"]]
        few = too_few_corners(np.array(view, dtype=np.float64))
        if few:  # a partial view is left out, as a photo without a board is; the others still calibrate
            print(f"tiltfit: warning: {path}: corners_px: {few}; skipped", file=sys.stderr, flush=True)
            skipped.append({"image": path, "reason": few})
            continue
        size = list(det["image_size_px"])
        corners.append(view)
        blur.append([b if b is not None else math.nan for b in det["blur_px"]])
        names.append(path)
    if not corners and all(s["reason"].startswith("no board found") for s in skipped):
        raise CliError(args.inputs[0], f"no board found in any of the {len(args.inputs)} images")
    if skipped and len(corners) < MIN_VIEWS_AFTER_SKIPPING:
        raise CliError(args.inputs[0], f"only {len(corners)} of {len(args.inputs)} images have a board with {MIN_CORNERS} "
                                       f"corners or more (at least {MIN_VIEWS_AFTER_SKIPPING} needed)")
    _check_views(names, np.array(corners, dtype=np.float64), points)
    obs = Observations(points, np.array(corners, dtype=np.float64), np.array(blur, dtype=np.float64),
                       tuple(size), args.pixel_pitch_mm, names=names)
    obs.skipped = skipped
    return obs


def _check_views(names: list[str], corners_px, points) -> None:
    """Refuse views no calibration should use (tiltfit.files.det.check_view / check_views)."""
    from tiltfit.files.det import DetFileError, check_view, check_views

    try:
        for name, c in zip(names, corners_px):
            check_view(name, c, points)
        check_views(names, corners_px)
    except DetFileError as e:
        raise CliError(*str(e).split(": ", 1)) from None


def _check_range(option: str, value, low_exclusive: float, high: float, what: str) -> None:
    if not (math.isfinite(value) and low_exclusive < value <= high):
        raise CliError(option, f"expected {what} in ({low_exclusive:g}, {high:g}], got {value}")


def cmd_calibrate(args) -> int:
    say = _say(args.quiet)
    t0 = time.perf_counter()
    _check_output(args.output)
    _check_range("--pixel-pitch-mm", args.pixel_pitch_mm, 0.0, MAX_PIXEL_PITCH_MM, "a pixel pitch in mm")
    if args.focal_mm is not None:
        _check_range("--focal-mm", args.focal_mm, 0.0, MAX_FOCAL_MM, "a focal length in mm")
    if not 0 <= args.held_out <= MAX_HELD_OUT:
        raise CliError("--held-out", f"expected 0 (off) to {MAX_HELD_OUT} folds, got {args.held_out}")
    if not 1 <= args.max_iterations <= MAX_ITERATIONS:
        raise CliError("--max-iterations", f"expected 1 to {MAX_ITERATIONS}, got {args.max_iterations}")
    if args.fit == "tilt" and not args.init:
        raise CliError("--init", "the tilt fit (stage 2) needs the stage-1 CALIB.json as --init")
    if args.cross_validate is not None and not 2 <= args.cross_validate <= MAX_HELD_OUT:
        raise CliError("--cross-validate", f"expected 2 to {MAX_HELD_OUT} groups, got {args.cross_validate}")
    for path in args.inputs + ([args.init] if args.init else []):
        if not os.path.isfile(path):  # refused before the fit's modules load (seconds: torch)
            raise CliError(path, "no such file")
    target = _load_target(args.target)
    from tiltfit.files.calib import calib_dict, camera_from_calib, read_calib, sigma_from_calib, validate_calib, write_calib
    from tiltfit.calibrate.fit import FitError, FitOptions
    from tiltfit.calibrate.photos import fit_with_held_out

    init = init_sigma = None
    if args.init:
        from tiltfit.files.export import is_mrcal_file, is_opencv_file, read_mrcal, read_opencv

        try:
            if is_mrcal_file(args.init):
                data = validate_calib(args.init, read_mrcal(args.init, args.pixel_pitch_mm))
            elif is_opencv_file(args.init):
                with _quiet_c_stderr():  # OpenCV's parser prints its complaints before raising
                    data = validate_calib(args.init, read_opencv(args.init, args.pixel_pitch_mm))
            else:
                data = read_calib(args.init)
            init = camera_from_calib(data, args.blur_model)
        except ValueError as e:
            raise _as_cli_error(args.init, e) from None
        init_sigma = sigma_from_calib(data)
        if args.fit == "tilt" and (data.get("U_mm") is None or data.get("d_mm") is None):
            raise CliError(args.init, "U_mm, d_mm: undetermined in this calibration; the tilt fit needs them")
    if args.refine == "photometric":  # what the refinement cannot take is known before any image is read
        _check_photometric_inputs(args, target)
    images = {} if args.refine == "photometric" else None  # read once, for detection and the refinement
    obs = _observations(args, target, say, images)
    if init is not None and tuple(init.image_size_px) != tuple(obs.image_size_px):
        raise CliError(args.init, f"image_size_px {list(init.image_size_px)} differs from the images' "
                                  f"{list(obs.image_size_px)}")
    blur_model = args.blur_model or (init.blur_model if init is not None else "ellipse")
    options = FitOptions(robust=args.robust, free_principal_point=args.principal_point,
                         held_out_folds=args.held_out or FitOptions.held_out_folds,
                         blur_model=blur_model, nominal_focal_mm=args.focal_mm,
                         max_iterations=args.max_iterations, model_selection=not args.no_model_selection,
                         progress=say, distortion=args.distortion, distortion_centre=args.distortion_centre,
                         board=args.board)
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
    photometric = _refine_photometric(result, used, target, args, say, images, held_out) \
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
        raise CliError(args.output, f"cannot write ({e.strerror or e})") from None
    say(f"wrote {args.output}")
    return 0


def _check_photometric_inputs(args, target) -> None:
    """Refuse `--refine photometric` up front where it cannot run: a target with markers (the photometric model
    renders checkerboards) or DET files instead of photographs."""
    if target.dark_rectangles():
        raise CliError(args.target, "--refine photometric: the photometric model renders checkerboards; a ChArUco "
                                    "board's markers are not modelled (calibrate without --refine)")
    for path in args.inputs:
        if _is_det_file(path):
            raise CliError(path, "--refine photometric needs the photographs, not DET files")


def _refine_photometric(result, obs, target, args, say, photos: dict | None = None, held_out: dict | None = None) -> dict:
    """`--refine photometric`: refit lens and poses to the photos' pixels.

    The refined values are written into `result` (its camera, values, σ and views, so every key CALIB.json
    derives from them, residuals and f included, follows); returns the CALIB.json `photometric` block, which
    keeps the corner fit beside the refinement. `photos`: the photographs already read, by path. The refinement
    moves only what the corner fit determined, within its trust region, and is kept only where held-out pixels
    and the corners (held out of it; against the corner fit's k-fold `held_out` RMS) do not reject it.
    """
    import numpy as np
    import torch

    from renderer import read_image
    from camio.files import ImageIOError

    from tiltfit.calibrate.model import residuals
    from tiltfit.photometric import PhotometricError, PhotometricOptions, refine_photometric

    images = []
    for view in result.views:
        path = view["image"]
        if _is_det_file(path):
            raise CliError(path, "--refine photometric needs the photographs, not DET files")
        try:
            img = (photos or {}).get(path)
            img = np.asarray(read_image(path, args.encoding) if img is None else img, dtype=np.float64)
        except (ImageIOError, OSError, ValueError) as e:
            raise _as_cli_error(path, e) from None
        images.append(img.mean(-1) if img.ndim == 3 else img)
    keys = ("w_mm", "U_mm", "d_mm", "theta_F_deg", "theta_L_deg")
    block = {"corner_fit": {k: result.values.get(k) for k in keys},
             "corner_fit_sigma": {k: result.sigma.get(k) for k in keys}}
    try:
        res = refine_photometric(images, target, result.camera,
                                 # 0 lens samples: from the blur; photographs of a megapixel or more fit 1,000
                                 # pixels a view (about 2 s a view on 2 cores; 2,000 doubles it)
                                 PhotometricOptions(kernel=args.psf, lens_samples=0,
                                                    max_pixels=1000 if images[0].size >= 1 << 20 else 2000),
                                 say=say, start_sigma=result.sigma, corners=obs,
                                 corner_held_out_px=(held_out or {}).get("rms_px"),
                                 start_covariance=result.intrinsics_covariance)
    except PhotometricError as e:
        raise CliError(args.inputs[0], f"photometric refinement: {e}") from None
    for e in res.left_out:
        if getattr(args, "quiet", False):   # without -q the refinement said so as it happened
            print(f"tiltfit: note: photometric refinement: {result.views[e['view']]['image']} left out of the fit "
                  f"(its pose stays the corner fit's): {e['reason']}", file=sys.stderr, flush=True)
    v, sg, cam = res.values, res.sigma, result.camera
    block.update(left_out=[{"view": e["view"], "image": result.views[e["view"]]["image"], "reason": e["reason"]}
                           for e in res.left_out])
    block.update(kept=res.kept, held_out=res.held_out, refined={k: v[k] for k in keys},
                 refined_sigma={k: sg[k] for k in keys}, corner_check=res.corner_check, free=res.free, at_bound=res.at_bound,
                 rejected_because=res.rejected_because, sigma_model=res.sigma_model, bounds=res.bounds)
    exposure = {"vignetting": v["vignetting"],
                "levels": [None if "left_out" in x else {k: x[k] for k in ("white", "black", "gain_x", "gain_y") if k in x}
                           for x in res.views]}
    if res.kept != "photometric":
        # Not progress: the user asked for a refinement and gets the corner fit, so this line shows even with -q.
        print(f"tiltfit: note: photometric refinement not kept ({res.rejected_because}); CALIB.json keeps the "
              "corner fit", file=sys.stderr, flush=True)
        # The refinement's exposure too: `tiltfit report` draws the residual image through the corner fit with its
        # vignetting and illumination gradient (the levels refitted there, as the held-out check refits them).
        block.update(rms_linear=res.rms, iterations=res.iterations, runtime_s=res.runtime_s, **exposure)
        return block
    with torch.no_grad():
        cam.load_state_dict(res.camera.state_dict())   # the refined lens and poses, in the fit's own module
        r = residuals(cam, obs)
        rms_corners, rms_blur = r.rms_per_view()
    result.values.update({k: x for k, x in cam.summary().items() if k in result.values})
    # σ of the refined keys from the photometric covariance; f and the paper's θL are not propagated.
    result.sigma.update({k: sg[k] for k in keys}, f_mm=None, theta_L_paper_deg=None)
    if "inv_U_per_m" in res.free:
        # U fitted: the pixels determined it and d with it. Where the corners could not tell U the refinement holds
        # it at the start's placeholder and fits d beside it, a blur scale with no focus distance: both stay
        # undetermined (null), not the placeholder U with σ 0.
        result.undetermined = [k for k in result.undetermined if k not in ("U_mm", "d_mm")]
    result.rss = dict(result.rss, corners=float((r.corners_px**2).sum()))
    for k, (view, fitted) in enumerate(zip(result.views, res.views)):
        view.update(R=cam.R[k].tolist(), T_mm=cam.T_mm[k].tolist(), rms_reprojection_px=float(rms_corners[k]),
                    rms_blur_px=float(rms_blur[k]))
        if "rms" in fitted:   # not for a view left out of the fit
            view["rms_photometric"] = fitted["rms"]
    block.update(rms_linear=res.rms, iterations=res.iterations, runtime_s=res.runtime_s, **exposure,
                 kernel=v["kernel"],
                 psf_sigma_px=v["psf_sigma_px"], psf_sigma_px_sigma=sg["psf_sigma_px"],
                 aperture=v["aperture"], closed_form_pixels=v["closed_form_pixels"],
                 lens_samples=v["lens_samples"])
    if res.kernel_selection is not None:
        block["kernel_selection"] = res.kernel_selection
    say(f"photometric refinement: RMS {res.rms:.4g} (linear), θL {v['theta_L_deg']:+.4f} ± {sg['theta_L_deg']:.4f}°, "
        f"U {v['U_mm']:.2f} mm, d {v['d_mm']:.3f} mm ({res.iterations} iterations, {res.runtime_s:.1f} s)")
    return block


def cmd_export(args) -> int:
    from tiltfit.files.calib import read_calib
    from tiltfit.files.export import MRCAL_EXTENSION, ExportError, check_exportable, write_mrcal, write_opencv

    _check_output(args.output)
    if (args.to == "mrcal") != args.output.lower().endswith(MRCAL_EXTENSION):
        raise CliError(args.output, f"--to {args.to}: expected "
                       + (f"a {MRCAL_EXTENSION} file" if args.to == "mrcal" else "a .yml, .xml or .json file"))
    try:
        data = read_calib(args.calib)
        if args.to == "opencv":
            check_exportable(data)
    except ValueError as e:
        raise _as_cli_error(args.calib, e) from None
    try:
        (write_mrcal if args.to == "mrcal" else write_opencv)(data, args.output)
    except (ExportError, OSError) as e:
        raise _as_cli_error(args.output, e) from None
    _say(args.quiet)(f"wrote {args.output}")
    return 0


def cmd_report(args) -> int:
    from tiltfit.files.calib import read_calib
    from tiltfit.report.plots import write_report

    if os.path.exists(args.output) and not os.path.isdir(args.output):
        raise CliError(args.output, "not a folder")
    try:
        data = read_calib(args.calib)
    except ValueError as e:
        raise _as_cli_error(args.calib, e) from None
    options = _real_vs_rendered_options(args)
    _check_report_options(options, data)
    try:
        files = write_report(data, args.output, args.calib, options)
    except OSError as e:
        raise CliError(args.output, f"cannot write ({e.strerror or e})") from None
    except ValueError as e:
        raise _as_cli_error(args.calib, e) from None
    say = _say(args.quiet)
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
    say = _say(args.quiet)
    return RealVsRenderedOptions(views=views, max_views=args.max_views, photos_dirs=tuple(args.photos or ()),
                                 spp=DEFAULT_SPP if args.spp is None else args.spp, scale=args.scale,
                                 encoding=args.encoding, say=say)


def cmd_compare(args) -> int:
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
            raise _as_cli_error(path, e) from None
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
            raise CliError(args.output, f"cannot write ({e.strerror or e})") from None
        for f in files:
            _say(args.quiet)(f"wrote {f}")
    return 0


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


def cmd_reproduce(argv) -> int:
    """`tiltfit reproduce ...` is `tiltfit.experiments.reproduce.main` (its own options and help)."""
    from tiltfit.experiments import reproduce

    return int(reproduce.main(list(argv)) or 0)


def cmd_stability(argv) -> int:
    """`tiltfit stability ...` is `tiltfit.experiments.stability.main` (its own options and help)."""
    from tiltfit.experiments import stability

    return int(stability.main(list(argv)) or 0)


# --- parser ------------------------------------------------------------------------------------------------

def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="tiltfit", description="Tilt-lens calibration (Baba, Nakane, Hiura 2017).")
    sub = ap.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("detect", help="find the target's corners and blur widths in one image")
    p.add_argument("image", metavar="IMAGE")
    p.add_argument("--target", required=True, metavar="T.json", help="target file")
    p.add_argument("--encoding", choices=("srgb", "linear"), help="override the file's encoding")
    p.add_argument("-o", "--output", required=True, metavar="DET.json")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress on stderr")
    p.set_defaults(func=cmd_detect)

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

    p = sub.add_parser("export", help="write a calibration for another library (OpenCV FileStorage, mrcal)")
    p.add_argument("calib", metavar="CALIB.json")
    p.add_argument("--to", choices=("opencv", "mrcal"), default="opencv",
                   help="format: opencv (FileStorage .yml/.xml/.json) or mrcal (.cameramodel) [opencv]")
    p.add_argument("-o", "--output", required=True, metavar="camera.yml|camera.cameramodel")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress on stderr")
    p.set_defaults(func=cmd_export)

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

    # Listed for --help; its arguments are parsed by tiltfit.experiments.reproduce itself (see main).
    sub.add_parser("reproduce", help="the paper's experiment end to end on a simulated camera", add_help=False)
    sub.add_parser("stability", help="where each method fails, and how ours behaves there", add_help=False)
    sub.add_parser("target", help="design a target (design) or print it at true size (print)", add_help=False)
    return ap


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else [str(a) for a in argv]
    previous = interrupt_on_sigterm()
    try:
        if argv and argv[0] == "reproduce":
            return cmd_reproduce(argv[1:])
        if argv and argv[0] == "stability":
            return cmd_stability(argv[1:])
        if argv and argv[0] == "target":
            from tiltfit.cli import target as target_cli

            return target_cli.main(argv[1:])
        args = build_parser().parse_args(argv)
        with warnings.catch_warnings():
            # numpy's floating-point warnings would print before the one-line error; failures are reported once.
            warnings.simplefilter("ignore", RuntimeWarning)
            return args.func(args)
    except CliError as e:
        print(f"tiltfit: {e.file}: {' '.join(e.problem.split())}", file=sys.stderr)
        return EXIT_ERROR
    except MemoryError:
        print("tiltfit: out of memory", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        print("tiltfit: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":
    sys.exit(main())
