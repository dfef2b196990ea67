"""Calibrating a camera from photographs of a target, from Python: detection, the fit with its model selection,
the held-out error, and the CALIB.json content, as `tiltfit calibrate` does them.

    calib = tiltfit.calibrate_photos(sorted(glob.glob("photos/*.jpg")), "target.json", pixel_pitch_mm=0.005)
    calib.focal_px, calib.principal_point_px, calib.rms_px      # px; RMS per corner, as OpenCV's
    calib.save("calib.json")
"""
from __future__ import annotations

import os
import time
from dataclasses import replace

import numpy as np

from tiltfit.files.calib import calib_dict
from tiltfit.files.calibrated import Calibration
from tiltfit.calibrate.flow import calibrate
from tiltfit.calibrate.fit import FitOptions, FitResult, per_corner_rms_px
from tiltfit.calibrate.model import Observations
from tiltfit.target.layout import Target, load_target


def fit_with_held_out(obs: Observations, mode: str = "unified", init=None, options: FitOptions | None = None,
                      init_sigma: dict | None = None, held_out_folds: int = 5, say=None):
    """`tiltfit.calibrate.flow.calibrate`, then the k-fold held-out reprojection error of the views it used.

    Returns (result, views used: Observations, held_out dict or None). The held-out error is skipped (None)
    with fewer than max(3, folds) views, and where a fold's fit fails (then with a line in `result.notes`).
    Raises:
        FitError: the calibration itself failed.
    """
    from tiltfit.calibrate.fit import FitError
    from tiltfit.detect.imaging import torch_threads
    from tiltfit.select.held_out import held_out_rms

    options = options or FitOptions()
    result = calibrate(obs, mode, init=init, options=options, init_sigma=init_sigma)
    used = obs.subset([obs.names.index(v["image"]) for v in result.views])
    held_out = None
    if held_out_folds and used.n_views >= max(3, held_out_folds):
        try:
            with torch_threads(1):  # small tensors, as in `calibrate`
                held_out = result.held_out if (result.held_out or {}).get("folds") == held_out_folds else \
                    held_out_rms(used, replace(options, free_principal_point=result.free_principal_point),
                                 folds=held_out_folds, distortion=result.distortion_model, start=result.camera,
                                 board=result.board.model if result.board is not None else None)
            if say:
                fit_rms = per_corner_rms_px(result.rss)
                say(f"reprojection RMS {fit_rms:.4f} px per corner (fit), {held_out['rms_px']:.4f} px (held out, "
                    f"{held_out['folds']}-fold)")
        except FitError as e:  # a note, not progress: CALIB.json then has no held-out error, and the user is told
            result.notes.append(f"held-out error not computed: {e}")
    return result, used, held_out


def observations_from_photos(photos, target: Target, pixel_pitch_mm: float, encoding: str | None = None,
                             say=None) -> Observations:
    """Detect the board in each photo; photos without one are left out and listed in the result's `skipped`.

    Raises:
        ValueError: a photo cannot be read, sizes differ, or no photo shows the board (message names the file).
    """
    from renderer import read_image

    from tiltfit.detect.charuco import detect_board as detect

    points = target.feature_points()
    corners, blur, names, skipped, size = [], [], [], [], None
    for path in photos:
        t0 = time.perf_counter()
        image = read_image(path, encoding)
        found = detect(image, target)
        if not found.grid_found or np.isnan(found.corners_px).all():
            skipped.append({"image": path, "reason": "no board found" + (f" ({found.message})" if found.message else "")})
            continue
        if size is not None and tuple(image.shape[1::-1]) != size:
            raise ValueError(f"{path}: image size {list(image.shape[1::-1])} differs from the first photo's {list(size)}")
        size = tuple(image.shape[1::-1])
        corners.append(found.corners_px)
        blur.append(found.blur_px)
        names.append(path)
        if say:
            say(f"{path}: {int(np.isfinite(found.corners_px[:, 0]).sum())} of {len(points)} corners detected in "
                f"{time.perf_counter() - t0:.1f} s")
    if not corners:
        raise ValueError(f"{photos[0] if photos else 'photos'}: no board found in any of the {len(photos)} photos")
    obs = Observations(points, np.stack(corners).astype(np.float64), np.stack(blur).astype(np.float64), size,
                       pixel_pitch_mm, names=names)
    obs.skipped = skipped
    return obs


def calibrate_photos(photos, target, pixel_pitch_mm: float, mode: str = "unified",
                     options: FitOptions | None = None, held_out_folds: int = 5, encoding: str | None = None,
                     say=None) -> Calibration:
    """Calibrate from photographs of a target with `tiltfit calibrate`'s defaults.

    Args:
        photos: image paths (8-bit files are read as sRGB unless `encoding` says otherwise).
        target: a `Target` or the path of a target file.
        pixel_pitch_mm: the sensor's pixel pitch (mm).
        mode: "unified" (the paper's stage 1: w, U, d and the poses) or "joint" (θF free as well).
        options: `FitOptions` [`tiltfit calibrate`'s: principal point and distortion ("auto") chosen on the data].
        held_out_folds: k of the k-fold held-out error (0: none) [5].
        say: progress callback (one line a call), e.g. `print` [None: quiet].
    Returns:
        a `Calibration`.
    Raises:
        ValueError: unreadable photos or target, no board found; `tiltfit.calibrate.fit.FitError`: the fit failed.
    """
    t0 = time.perf_counter()
    if not isinstance(target, Target):
        target = load_target(os.fspath(target))
    obs = observations_from_photos(list(photos), target, pixel_pitch_mm, encoding, say)
    options = options or FitOptions(distortion="auto", board="auto", progress=say)  # `tiltfit calibrate`'s defaults
    result, used, held_out = fit_with_held_out(obs, mode, options=options, held_out_folds=held_out_folds, say=say)
    result.skipped = list(obs.skipped) + list(result.skipped)
    data = calib_dict(result, runtime_s=time.perf_counter() - t0, obs=used, target=target.to_dict(),
                      held_out=held_out)
    return Calibration.from_dict(data, "<calibrate_photos>", result, held_out)
