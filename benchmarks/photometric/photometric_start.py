"""What the photometric benchmarks on real photos start from: the corner fit of a set of views (as `tiltfit
calibrate --refine photometric` runs it: unified, free principal point, a named distortion), its K-fold held-out
corner error, the peer's time (OpenCV's `calibrateCamera` on the same corners, the same distortion terms) and the
photos in grey."""
from __future__ import annotations

import os
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def corner_start(obs, target, distortion: str, opencv_repeats: int = 5) -> dict:
    """{corner (FitResult), corner_s, kfold (`held_out_rms`), options, opencv_s (median of `opencv_repeats`),
    opencv_s_all}."""
    import cv2

    from tiltfit.calibrate.flow import calibrate
    from tiltfit.calibrate.fit import FitOptions
    from tiltfit.select.held_out import held_out_rms

    options = FitOptions(free_principal_point=True, distortion=distortion, model_selection=False)
    t = time.perf_counter()
    corner = calibrate(obs, "unified", options=options)
    corner_s = time.perf_counter() - t
    kfold = held_out_rms(obs, options, folds=5, distortion=distortion, start=corner.camera)
    pts = [target.feature_points()[np.isfinite(c[:, 0])].astype(np.float32) for c in obs.corners_px.numpy()]
    img = [c[np.isfinite(c[:, 0])].astype(np.float32) for c in obs.corners_px.numpy()]
    flags = cv2.CALIB_RATIONAL_MODEL if distortion == "rational" else 0
    times = []
    for _ in range(max(opencv_repeats, 1)):
        t = time.perf_counter()
        cv2.calibrateCamera(pts, img, tuple(obs.image_size_px), None, None, flags=flags)
        times.append(time.perf_counter() - t)
    return {"corner": corner, "corner_s": corner_s, "kfold": kfold, "options": options,
            "opencv_s": float(np.median(times)), "opencv_s_all": times}


def grey_photos(folder: str, names) -> list:
    """The photos `names` in `folder`, as float64 grey images (the mean of the channels)."""
    from renderer import read_image

    images = []
    for n in names:
        im = np.asarray(read_image(os.path.join(folder, n)), dtype=np.float64)
        images.append(im.mean(-1) if im.ndim == 3 else im)
    return images


def calibrate_refined_cached(name: str, pitch_mm: float, n_views: int, out: str) -> tuple[list, list, int, float]:
    """`tiltfit calibrate --refine photometric` of the first `n_views` photos (with a board) of the shipped set
    data/real/NAME into `out`, the command's detection replaced by tiltfit's cached detections of the same photos
    (`real_detections`; the photos themselves are still read for the refinement). Returns (image names, argv,
    exit status, wall seconds)."""
    from tests.real_detections import read_cache

    from tiltfit.cli import detect as cli_detect
    from tiltfit.cli import main as cli

    folder = os.path.join(ROOT, "data", "real", name)
    cache = read_cache(folder)
    names = [n for n in sorted(cache) if cache[n] and "no_board" not in cache[n]][:n_views]
    photos = [os.path.join(folder, n) for n in names]
    detect = cli_detect.detect_image

    def cached(path, target, encoding, keep=None):
        from renderer import read_image

        if keep is not None:   # the photo as the command reads it, for the refinement
            keep[path] = read_image(path, encoding)
        return cache[os.path.basename(path)]

    argv = ["calibrate", *photos, "--target", os.path.join(folder, "target.json"), "--pixel-pitch-mm", str(pitch_mm),
            "--refine", "photometric", "-o", out, "-q"]
    cli_detect.detect_image = cached
    t0 = time.perf_counter()
    try:
        status = cli.main(argv)
    finally:
        cli_detect.detect_image = detect
    return names, argv, status, time.perf_counter() - t0
