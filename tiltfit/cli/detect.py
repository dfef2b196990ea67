"""`tiltfit detect`, and the observations `tiltfit calibrate` gathers: each image read and its board detected
(DET.json dict), or a DET.json file read, then checked view by view (`tiltfit.files.det`)."""
from __future__ import annotations

import math
import os
import sys
import time

from camio.errors import os_reason
from camio.files import quiet_c_stderr

from .errors import CliError, as_cli_error, check_output, progress_printer

MIN_VIEWS_AFTER_SKIPPING = 3  # when images without a board were skipped, at least this many must remain


def load_target_file(path: str):
    """The target file at `path` (`tiltfit.target.layout.load_target`); CliError naming it."""
    from tiltfit.target.layout import load_target

    try:
        return load_target(path)
    except (ValueError, OSError) as e:
        raise as_cli_error(path, e) from None


def detect_image(path: str, target, encoding: str | None, keep: dict | None = None) -> dict:
    """Read an image, detect the board; returns the DET.json dict. Raises CliError naming the image.
    `keep`: where given, the image read is stored there under its path (for `--refine photometric`)."""
    from renderer import read_image

    from tiltfit.files.det import MAX_IMAGE_PIXELS

    try:
        with quiet_c_stderr():
            image = read_image(path, encoding, MAX_IMAGE_PIXELS)
    except (ValueError, OSError) as e:
        raise as_cli_error(path, e) from None
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
        raise as_cli_error(path, e) from None
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
    """The DET.json dict of corners (N, 2) and blur (N,) px found by a detector without `to_json_dict` (rounded as
    `Detection.to_json_dict` rounds: `det_number`)."""
    import numpy as np

    from tiltfit.detect.detection import det_number

    c = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
    b = np.asarray(blur, dtype=np.float64).reshape(-1)
    corners_out = [[det_number(x), det_number(y)] if np.isfinite(x) and np.isfinite(y) else None for x, y in c]
    blur_out = [det_number(v) for v in b]
    return {"image_size_px": [int(width), int(height)], "corners_px": corners_out, "blur_px": blur_out,
            "grid_found": any(v is not None for v in corners_out)}


def read_det_file(path: str, n_points: int) -> dict:
    """Read and validate a DET.json for a target of n_points feature points (tiltfit.files.det)."""
    from tiltfit.files.det import DetFileError, read_det

    try:
        return read_det(path, n_points)
    except DetFileError as e:
        raise as_cli_error(path, e) from None


def is_det_file(path: str) -> bool:
    """Whether an input is a DET.json file (else an image)."""
    return path.lower().endswith(".json")


def cmd_detect(args) -> int:
    """`tiltfit detect IMAGE --target T.json -o DET.json`."""
    import numpy as np

    say = progress_printer(args.quiet)
    check_output(args.output)
    target = load_target_file(args.target)
    t0 = time.perf_counter()
    det = detect_image(args.image, target, args.encoding)
    from tiltfit.detect.detection import write_det_json
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
        write_det_json(det, args.output)
    except (OSError, ValueError) as e:
        raise CliError(args.output, f"cannot write ({os_reason(e)})") from None
    return 0


def observations(args, target, say, images: dict | None = None):
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
        if is_det_file(path):
            det = read_det_file(path, len(points))
        else:
            t0 = time.perf_counter()
            try:
                det = detect_image(path, target, args.encoding, images)
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
