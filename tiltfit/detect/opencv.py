"""Corners of a checkerboard found by OpenCV's `findChessboardCornersSB`, as tiltfit detections.

Used where tiltfit's own detector is not the subject: the reference corners of the shipped real photo sets
(so that our fit and OpenCV's `calibrateCamera` work on the very same corners), and the benchmarks.

    opencv_detections(paths, target) -> list[dict | None]     DET.json-style dicts, None where no board

The corners are put in the target's feature-point order (row by row, Y outer, X inner) as OpenCV returns
them for the pattern size (n_cols, n_rows) of inner corners. A board that looks the same turned by 180°
has two valid labellings; OpenCV's is kept (it is a rigid motion of the board, so any pose fits it).
"""
from __future__ import annotations

import json
import os

import numpy as np


def sb_corners(gray8: np.ndarray, pattern: tuple[int, int]) -> np.ndarray | None:
    """(n, 2) corners of an 8-bit grey image by findChessboardCornersSB (normalised, exhaustive, accurate)
    refined by cornerSubPix (5 × 5), in OpenCV's order; None when no board is found. `pattern` is (columns,
    rows) of inner corners. The peer the detection benchmarks and tests compare with."""
    import cv2

    flags = cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
    ok, c = cv2.findChessboardCornersSB(gray8, pattern, flags=flags)
    if not ok:
        return None
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 1e-3)
    return cv2.cornerSubPix(gray8, c.astype(np.float32), (5, 5), (-1, -1), crit).reshape(-1, 2).astype(np.float64)


def match_labelling(ours: np.ndarray, theirs: np.ndarray) -> tuple[np.ndarray, bool]:
    """Per-corner distances between two (n, 2) labellings of a board that looks the same turned by 180°:
    in the same order or reversed, whichever fits (smaller median); and whether it was the same order."""
    same = np.hypot(*(ours - theirs).T)
    turned = np.hypot(*(ours - theirs[::-1]).T)
    is_same = bool(np.nanmedian(same) <= np.nanmedian(turned))
    return (same if is_same else turned), is_same


def opencv_detection(path: str, target) -> dict | None:
    """One image's corners by cv2.findChessboardCornersSB (grey levels as stored; no blur widths).

    Args:
        path: image file (any format OpenCV reads).
        target: a `tiltfit.target.layout.Target` (its inner-corner grid sets the pattern size).
    Returns:
        {image_size_px, corners_px, blur_px, grid_found, detector} or None when no board is found.
    """
    import cv2

    grey = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
    if grey is None:
        raise ValueError(f"{path}: cannot read the image")
    nx, ny = len(target.x_edges) - 2, len(target.y_edges) - 2
    ok, c = cv2.findChessboardCornersSB(grey, (nx, ny), flags=cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY)
    if not ok or c is None:
        return None
    c = c.reshape(-1, 2).astype(np.float64)
    h, w = grey.shape
    return {"image_size_px": [int(w), int(h)], "corners_px": c.tolist(), "blur_px": [None] * len(c),
            "grid_found": True, "detector": "cv2.findChessboardCornersSB"}


def opencv_detections(paths, target, cache: str | None = None, say=None) -> list:
    """Detections of several images, read from / written to a JSON cache {basename: detection | null}."""
    cached = {}
    if cache and os.path.isfile(cache):
        with open(cache, encoding="utf-8") as f:
            cached = json.load(f)
    out, changed = [], False
    for p in paths:
        key = os.path.basename(p)
        if key not in cached:
            cached[key] = opencv_detection(p, target)
            changed = True
            if say:
                say(f"{key}: {'board found' if cached[key] else 'no board'}")
        out.append(cached[key])
    if cache and changed:
        with open(cache, "w", encoding="utf-8") as f:  # one image per line: small diffs, readable
            f.write("{\n" + ",\n".join(f"{json.dumps(k)}: {json.dumps(v)}" for k, v in sorted(cached.items()))
                    + "\n}\n")
    return out


def opencv_calibrate(obs, flags: int = 0, focal_px: float = 600.0):
    """The peer on the same corners: `cv2.calibrateCamera` on each view's detected corners of `obs`
    (`tiltfit.calibrate.model.Observations`) with square pixels (CALIB_FIX_ASPECT_RATIO | `flags`), run to convergence
    (`focal_px`: the initial matrix's focal length; without CALIB_USE_INTRINSIC_GUESS OpenCV keeps only its
    fx/fy ratio, for the fixed aspect ratio, and starts from its own estimate). Returns (RMS per corner as OpenCV defines it, K, distortion)."""
    import cv2

    from renderer.cameras import camera_matrix, image_centre_px

    obj, img = [], []
    for v in range(obs.n_views):
        m = obs.corner_mask[v].numpy()
        obj.append(obs.points_mm.numpy()[m].astype(np.float32))
        img.append(obs.corners_px[v].numpy()[m].astype(np.float32))
    W, H = obs.image_size_px
    K0 = camera_matrix(focal_px, image_centre_px(W, H))
    rms, K, dist, _, _ = cv2.calibrateCamera(obj, img, (W, H), K0, None, flags=cv2.CALIB_FIX_ASPECT_RATIO | flags,
                                             criteria=(cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12))
    return float(rms), K, dist.ravel()
