"""Find the target's feature points in an image: saddle candidates, grid growth, indexing, sub-pixel refinement.

Pipeline (`detect`):
1. Grey linear image (`imaging`), and a pyramid of 2×2 box averages (level factor f: pixel x_f ↔ full-resolution
   (x_f + 0.5) f − 0.5).
2. At a coarse level (coarsest first, finer on failure): saddle candidates (`saddles`), the local minima of the Hessian
   determinant det H = Ixx Iyy − Ixy² of the Gaussian-smoothed image (kornia), below a threshold set from the
   measured noise, where the saddle is well formed (−det H / (½(Ixx² + Iyy²) + Ixy²) > 0.3) and the
   gradient is small (a saddle's centre is flat, a point on an edge is not). A checker corner stays a
   saddle under any symmetric blur, even when the blur is as wide as the square and the pattern is nearly
   a sinusoid, so this works where edge-based detectors give up. The two zero directions of the quadratic
   form vᵀHv are the edges through the corner.
3. Grid growth (`grid`): a seed corner with neighbours along both edge directions, then predict-and-verify over the
   lattice (local affine prediction from known neighbours, the strongest candidate near the prediction or
   a local saddle search). Each accepted corner must look like an X-junction: the four cell centres around
   it alternate (diagonal pairs equal, pairs different), which rejects the board's outer L-corners.
4. Sub-pixel refinement at full resolution (`refine`): a checker corner under any point-symmetric blur (disc, pixel
   box, Gaussian) is a centre of point symmetry, I(p + v) = I(p − v). Levenberg–Marquardt on p minimises
   Σ_v w(v) [I(p + v) − I(p − v)]² over a window of 0.4 of the local square (at most 20 px), on patches
   smoothed by a 1.4 px Gaussian (symmetric, so the optimum stays put; it damps aliasing of sharp edges)
   and interpolated with Keys' cubic, all corners batched. No edge or blur model, so no bias from the blur
   size, its shape or the contrast; measured bias < 0.015 px for blur ≥ 1 px, < 0.035 px for sharp edges.
5. Indexing (`indexing`): which target corner (i, j) each lattice node is. A checkerboard is ambiguous under 90°
   turns, 180° turns and shifts; each hypothesis (4 turns × shifts that keep the nodes on the board) is
   scored by the colours it predicts: the cells between detected corners (the parity of the dark cell),
   one ring of cells beyond them (board cells) and a second ring (board or white margin). A tie is broken
   by the fit of a homography from the target coordinates (non-uniform rows tell the turns apart). A tie
   left between exactly the two placements related by the board's 180° turn (n_cols + n_rows even,
   symmetric edges: the image cannot tell them apart, and either is a valid pose) is settled by image
   geometry, consistently across views: corner 0 is the one nearer the image's top-left (the labelling
   OpenCV's findChessboardCorners gives); the detection's message says so. Any other tie (a partial view
   that fits several places on the board) is reported (grid_found False) rather than guessed.
6. Completion (`refine`): corners the growth missed, predicted by a local homography from the indexed ones within two
   indices (local, so curved rows under lens distortion are followed), refined coarse to fine and kept when
   they are clean X-junctions (`complete_corners`).
7. Blur per feature point (`tiltfit.detect.blur.measure_blur`).

Images are (H, W) or (H, W, C) linear float arrays (decode sRGB first: `camio.files.read_image` does).
Outputs are numpy float64 in pixels: x = column, y = row, (0, 0) the centre of the top-left pixel.
"""
from __future__ import annotations

import time

import numpy as np

from tiltfit.detect.blur import measure_blur as _measure_blur
from tiltfit.detect.checks import (CONTRADICTS, check_target_size, colour_problem, invert_photo, labelling_note,
                                   labelling_problem)
from tiltfit.detect.detection import Detection, DetectionError, read_detection_json, write_detection_json
from tiltfit.detect.grid import _median_spacing, _min_neighbour_distance, find_grid
from tiltfit.detect.imaging import build_pyramid, estimate_noise, to_full, to_gray, torch_threads
from tiltfit.detect.indexing import HALF_TURN_NOTE, resolve_indices
from tiltfit.detect.refine import complete_corners, refine_symmetric
from tiltfit.detect.saddles import saddle_map
from tiltfit.files.det import MAX_IMAGE_PIXELS  # the largest photo detection reads (named there: no torch)
from tiltfit.target.layout import Target

# The detector's public names, whichever module of tiltfit/detect owns them (callers import them from here).
__all__ = ["CONTRADICTS", "Detection", "DetectionError", "HALF_TURN_NOTE", "check_target_size", "complete_corners",
           "detect", "detect_corners", "detect_file", "detect_files", "estimate_noise", "find_grid", "invert_photo",
           "labelling_note", "labelling_problem", "read_detection_json", "refine_symmetric", "saddle_map", "to_gray",
           "write_detection_json"]

def detect_corners(gray: np.ndarray, target: Target, *, coarse_max_size: int = 400, sigma: float = 1.5,
                   refine_radius_max: float = 20.0, timings: dict | None = None, levels: dict | None = None):
    """Corners only (stages 1–5). Returns (corners_px (N, 2) with NaN, grid_found, message, level)."""
    timings = {} if timings is None else timings
    t0 = time.perf_counter()
    N = target.n_points
    corners = np.full((N, 2), np.nan)
    levels = build_pyramid(gray) if levels is None else levels
    timings["pyramid"] = time.perf_counter() - t0
    factors = sorted(levels)
    start = [f for f in factors if max(levels[f].shape) <= coarse_max_size]
    start_f = start[0] if start else factors[-1]
    message = "no checkerboard found"
    for f in [x for x in sorted(factors, reverse=True) if x <= start_f]:
        t1 = time.perf_counter()
        img = levels[f]
        noise = estimate_noise(img)
        sm = saddle_map(img, sigma, noise)
        grid = find_grid(sm, noise)
        timings[f"grid@{f}"] = time.perf_counter() - t1
        if len(grid) < 4:
            continue
        nodes = np.array(list(grid.keys()))
        xy_l = np.array([grid[tuple(n)] for n in nodes.tolist()])
        spacing = _median_spacing(nodes, xy_l)
        if spacing < 6 and f > 1:
            continue  # too small at this level: look finer
        t2 = time.perf_counter()
        xy_f = to_full(xy_l, f)
        radius = np.clip(0.4 * _min_neighbour_distance(nodes, xy_f), 3.0, refine_radius_max)
        xy_r, asym, ok = refine_symmetric(gray, xy_f, radius)
        ok &= asym < 0.35
        timings["refine"] = time.perf_counter() - t2
        if ok.sum() < 4:
            message = "corners found at a coarse level could not be refined"
            continue
        t3 = time.perf_counter()
        res = resolve_indices(nodes[ok], xy_l[ok], xy_r[ok], sm.smooth, target)
        timings["index"] = time.perf_counter() - t3
        if res.ij is None:
            return corners, False, res.message, f
        k = target.feature_index(res.ij[:, 0], res.ij[:, 1])
        corners[k] = xy_r[ok]
        t4 = time.perf_counter()
        complete_corners(gray, target, corners, refine_radius_max)
        timings["complete"] = time.perf_counter() - t4
        return corners, True, res.message, f
    return corners, False, message, 0


def detect_file(path: str, target: Target, encoding: str | None = None, **options) -> Detection:
    """`detect` on an image file read through `camio.files.read_image` (8-bit files decoded from sRGB; at
    most MAX_IMAGE_PIXELS)."""
    from camio.files import read_image

    return detect(read_image(path, encoding, MAX_IMAGE_PIXELS), target, **options)


def detect_files(paths, target: Target, *, encoding: str | None = None, measure_blur: bool = True,
                 progress=None, **options) -> list[Detection | None]:
    """`detect` on several image files: one entry per path, None where the image shows no usable board.

    Args:
        paths: image files (read by `camio.files.read_image`; 8-bit files are decoded from sRGB).
        target: the Target.
        encoding: override the files' encoding ("srgb" or "linear").
        measure_blur: also measure the blur per point.
        progress: optional callable taking one line per file (e.g. `print` to stderr): the number of corners
            found and the time, or why the view has no board, plus the detection's note if it has one.
        options: passed to `detect_corners`.
    Returns:
        list of Detection (grid_found True) or None, in the order of `paths`.
    Raises:
        DetectionError: a target too large to detect; ValueError / OSError from `read_image` for a file
        that cannot be read (bad input is an error, not a view without a board).
    """
    from camio.files import read_image

    check_target_size(target)
    out: list[Detection | None] = []
    for path in paths:
        t0 = time.perf_counter()
        det = detect(read_image(path, encoding), target, measure_blur=measure_blur, **options)
        ok = det.grid_found and bool(det.found.any())
        out.append(det if ok else None)
        if progress is not None:
            if ok:
                line = (f"{path}: {int(det.found.sum())} of {target.n_points} corners in "
                        f"{time.perf_counter() - t0:.1f} s")
                progress(line + (f" ({det.message})" if det.message else ""))
            else:
                progress(f"{path}: no board ({det.message or 'no checkerboard found'}); skipped")
    return out


def detect(image, target: Target, *, measure_blur: bool = True, **options) -> Detection:
    """Find the target's feature points and their blur in a linear image.

    Args:
        image: (H, W) or (H, W, C) linear float image (decode sRGB first).
        target: the Target.
        measure_blur: also measure the blur diameter per point (`tiltfit.detect.blur.measure_blur`).
        options: passed to `detect_corners`.
    Returns:
        Detection; grid_found False (and all NaN) when no board was found or its placement is ambiguous.
    """
    if target.dark_rectangles():
        raise DetectionError("target: a ChArUco board; its corners are found by tiltfit.detect.charuco.detect_board")
    with torch_threads(1):
        return _detect(image, target, measure_blur, options)


def _detect(image, target, measure_blur, options) -> Detection:
    check_target_size(target)
    timings: dict = {}
    t0 = time.perf_counter()
    gray = to_gray(image)
    if target.inverted:
        gray = invert_photo(gray)
    H, W = gray.shape
    levels = build_pyramid(gray)
    corners, found, message, level = detect_corners(gray, target, timings=timings, levels=levels, **options)
    problem = (colour_problem(gray, corners, target) or labelling_problem(corners, target, (W, H))) if found else ""
    if problem:
        corners, found, message = np.full_like(corners, np.nan), False, problem
    elif found:
        message = "; ".join(m for m in (message, labelling_note(corners, target)) if m)
    N = target.n_points
    blur, sigma = np.full(N, np.nan), np.full(N, np.nan)
    if found and measure_blur:
        t1 = time.perf_counter()
        blur, sigma = _measure_blur(gray, target, corners, levels=levels)
        timings["blur"] = time.perf_counter() - t1
    timings["total"] = time.perf_counter() - t0
    return Detection((W, H), corners, blur, sigma, found, message, level, timings)
