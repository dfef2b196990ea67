"""Find a ChArUco board's corners, with their ids, in partial and blurred views.

Pipeline (`detect_charuco`):
1. Ids. Where the markers can be read, OpenCV's `cv2.aruco.CharucoDetector` names the corners it sees (corner
   id k is feature point k of the `CharucoTarget`); it stops where blur is wider than a marker bit (about a
   tenth of a square). The checker corners stay saddles under any blur: independently, the saddle lattice of
   `tiltfit.detect.chessboard` (grid growth, no ids) is placed on the board by matching the image, resampled in lattice
   coordinates, against the board's own picture (markers included) blurred by discs of 0 to 0.8 of a square,
   over every placement (4 turns × shifts) that keeps the lattice on the board (`place_lattice`). The best
   placement must explain the image clearly better than the next (`MIN_PLACEMENT_RATIO`), else it names
   nothing. The two are merged; where both name a corner they must agree (`_merge`). OpenCV reads the markers
   first at two of its three threshold windows (FIRST_READ_WINDOWS), then with its defaults; neither the fuller
   read nor the lattice is searched once OpenCV's corners, refined and completed (steps 2 and 3), reach every
   corner of the board: they could name none more, and the lattice is the costliest step (saddle maps of the
   whole image at 7 scales).
2. Sub-pixel refinement: the point-symmetry refinement of the checkerboard path (`refine_symmetric`): at a
   ChArUco corner the two markers touching it have black borders that are point images of each other, so the
   neighbourhood is point-symmetric out to the markers' data bits, √2 (clear + bit) from the corner; the
   window radius is that (`symmetric_radius`), at most 0.4 of the local square.
3. Completion: corners neither step found, predicted by local homographies and refined the same way
   (`tiltfit.detect.chessboard.complete_corners` with the ChArUco window).
4. Blur per corner (`tiltfit.detect.blur.measure_blur`, its bands stopping at the markers' borders); when the
   widths are not asked for, its first, coarse pass alone, for step 5's decision, and not even that where the
   edges' steepness (`edge_spread_blur`) puts the blur far below the decision's limit.
5. Blur beyond CANCEL_BITS_BLUR of a square reaches the data bits from inside the window: each corner is
   fitted again by the board's own picture around it, markers' bits included (`refine_model`: the exact
   picture through the local homography, with an affine correction, convolved with a disc in the image whose
   diameter is fitted too, gain and offset; Gauss–Newton), twice (the second from the local homographies of the
   refined corners); then corners nearer the image's edge than their blur diameter, and corners their
   neighbours place HEAVY_BLUR_TOLERANCE square away, are dropped.

Images are (H, W) or (H, W, C) linear float arrays; outputs in pixels (x = column, y = row, (0, 0) the centre of
the top-left pixel), NaN where a corner was not found.
"""
from __future__ import annotations

import math
import time

import numpy as np

from tiltfit.detect.charuco_lattice import MIRROR_IMAGE, _local_square_px, _placed_lattice
from tiltfit.detect.charuco_model import MODEL_ROUNDS, board_texture, refine_model
from tiltfit.detect.detection import Detection
from tiltfit.detect.imaging import build_pyramid, homography_dlt_batch, to_gray, torch_threads
from tiltfit.detect.refine import complete_corners, refine_symmetric
from tiltfit.target.layout import CharucoTarget

# Above this median blur (diameter, squares) the corners are fitted again by the board's own blurred picture
# (`refine_model`): below it the point-symmetry window sees none of the markers' data bits (on renders, 0.1 square
# changes nothing; at 0.25 square the model fit halves the largest error).
CANCEL_BITS_BLUR = 0.15
# ... and then dropped when their neighbours' homography puts them this many squares away (0.2 otherwise).
HEAVY_BLUR_TOLERANCE = 0.05
# Rounds of completion (each reaches two corners further from the found ones; it stops when none is added).
COMPLETION_ROUNDS = 20
# Refined corners whose point-symmetry residual exceeds this (relative, as in `tiltfit.detect.chessboard`) are dropped.
MAX_ASYMMETRY = 0.35
# When no board is found, the photo is read again for a hint: inverted, mirrored, and for markers of other
# dictionaries (the largest of each family; its smaller ones are its first ids). A hint needs this many markers.
MIN_HINT_MARKERS = 2
HINT_DICTIONARIES = ("DICT_4X4_1000", "DICT_5X5_1000", "DICT_6X6_1000", "DICT_7X7_1000", "DICT_ARUCO_ORIGINAL",
                     "DICT_APRILTAG_16h5", "DICT_APRILTAG_25h9", "DICT_APRILTAG_36h10", "DICT_APRILTAG_36h11",
                     "DICT_ARUCO_MIP_36h12")


def symmetric_radius(target: CharucoTarget) -> float:
    """Window radius for the point-symmetry refinement, in squares: up to the markers' data bits."""
    n_bits = target.opencv_board().getDictionary().markerSize + 2
    clear = target.white_cell_clear_mm / target.square_mm
    bit = target.marker_mm / n_bits / target.square_mm
    return min(0.4, math.sqrt(2.0) * (clear + bit))


# A photo whose 99.9th percentile lies below this (linear) is scaled up to it before OpenCV reads its markers (as is
# one above 1, which would clip); others are encoded as they are: stretching a photo already near the full range
# reads the same markers, and costs OpenCV's marker detection up to twice the time (webcam frames at 0.82: more
# contours of noise and clipped highlights).
DARK_PHOTO = 0.5


def _srgb8(gray: np.ndarray) -> np.ndarray:
    """8-bit sRGB-encoded copy of a linear image (what OpenCV's detectors expect), scaled to its 99.9th percentile
    where that is below DARK_PHOTO or above 1."""
    from camio.files import encode_srgb8

    if _top_within(gray, DARK_PHOTO, 1.0):
        return encode_srgb8(gray)
    top = float(np.percentile(gray, 99.9)) or 1.0
    return encode_srgb8(gray / top if top < DARK_PHOTO or top > 1.0 else gray)


def _top_within(gray: np.ndarray, lo: float, hi: float) -> bool:
    """Whether the 99.9th percentile of `gray` (numpy's, linear between two adjacent order statistics) lies in
    [lo, hi], from two counts where the order statistics around it do (False where one does not: then it is
    computed whole). A count is a pass over the pixels; the percentile, a partition of a copy, costs several."""
    n = gray.size
    i = int(0.999 * (n - 1))  # order statistics i − 1 .. i + 2 (0-based): numpy's pair, whatever its rounding
    if i < 1 or i + 2 >= n:
        return False
    below = int(np.count_nonzero(gray < lo))  # order statistics 0 .. below − 1 are < lo
    within = int(np.count_nonzero(gray <= hi))  # 0 .. within − 1 are <= hi (NaN counts in neither)
    return below <= i - 1 and within >= i + 3


# OpenCV's marker reading thresholds the photo at several window sizes (by default 3, 13 and 23 px), each a pass
# over the photo. A first read thresholds at FIRST_READ_WINDOWS alone; OpenCV's default reading runs only when
# the corners named by the first read, refined and completed, leave one of the board's corners unnamed (more
# markers could then name more). On the 48 frames of the webcam video both read the same markers
# (`benchmarks/results/detect_speed_charuco.md` for the time).
FIRST_READ_WINDOWS = (3, 13)


def opencv_corners(gray: np.ndarray, target: CharucoTarget, refine: bool = True,
                   windows: tuple[int, ...] | None = None, img8: np.ndarray | None = None) -> np.ndarray:
    """(N, 2) corners named by OpenCV's `CharucoDetector` (its own sub-pixel step), NaN where none. `gray` is the
    photo as taken: for an `inverted` target its 8-bit encoding is inverted (what `detectInvertedMarker` reads).
    `windows`: the adaptive-threshold window sizes of the marker reading (px, evenly spaced; None: OpenCV's
    default); `img8`: `_srgb8(gray)` if already made."""
    import cv2

    detector = cv2.aruco.CharucoDetector(target.opencv_board())
    if not refine or windows is not None:
        params = detector.getDetectorParameters()
        if not refine:
            params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_NONE
        if windows is not None:
            params.adaptiveThreshWinSizeMin, params.adaptiveThreshWinSizeMax = min(windows), max(windows)
            if len(windows) > 1:
                params.adaptiveThreshWinSizeStep = windows[1] - windows[0]
        detector.setDetectorParameters(params)
    img8 = _srgb8(gray) if img8 is None else img8
    cc, ids, _, _ = detector.detectBoard(255 - img8 if target.inverted else img8)
    corners = np.full((target.n_points, 2), np.nan)
    if ids is not None and len(ids):
        corners[ids.ravel()] = cc.reshape(-1, 2)
    return corners


def _marker_ids(img8: np.ndarray, dictionary: str) -> list[int]:
    """Ids of the ArUco markers of `dictionary` OpenCV reads in an 8-bit grey image."""
    import cv2

    from tiltfit.target.layout import aruco_dictionary

    _, ids, _ = cv2.aruco.ArucoDetector(aruco_dictionary(dictionary)).detectMarkers(img8)
    return [] if ids is None else sorted(int(i) for i in ids.ravel())


def _family(name: str) -> str:
    """A dictionary's family (DICT_4X4_50 → DICT_4X4): its sizes share their first ids."""
    return name.rsplit("_", 1)[0] if name.rsplit("_", 1)[-1].isdigit() else name.upper()


def no_board_hint(gray: np.ndarray, target: CharucoTarget) -> str:
    """Why a photo shows no board of the target's although it shows markers: the colours inverted (a white-on-black
    print), a mirror image, or markers of another dictionary; '' when none of these reads more markers.

    Args:
        gray: (H, W) linear photo as taken (not inverted).
    """
    img8 = _srgb8(gray)
    shown = 255 - img8 if target.inverted else img8
    n_own = len(_marker_ids(shown, target.dictionary))
    n_inverted = len(_marker_ids(255 - shown, target.dictionary))
    if n_inverted >= MIN_HINT_MARKERS and n_inverted > n_own:
        if target.inverted:
            return (f"the photo shows {n_inverted} of its markers dark on white, and the target file says "
                    "\"inverted\": true (remove the key)")
        return (f"the inverted photo shows {n_inverted} of its markers: a board printed white on black (add "
                "\"inverted\": true to the target file) or a colour-inverted photo")
    n_mirror = len(_marker_ids(np.ascontiguousarray(shown[:, ::-1]), target.dictionary))
    if n_mirror >= MIN_HINT_MARKERS and n_mirror > n_own:
        return f"{MIRROR_IMAGE}: its mirror image shows {n_mirror} markers"
    if n_own >= MIN_HINT_MARKERS:
        return ""
    for name in HINT_DICTIONARIES:
        ids = _marker_ids(shown, name) or _marker_ids(255 - shown, name)
        if len(ids) < MIN_HINT_MARKERS:
            continue
        if _family(name) == _family(target.dictionary):
            return (f"its markers have ids {ids[:5]}{'…' if len(ids) > 5 else ''} of {name}, beyond the target's "
                    f"{target.dictionary}: another board of the family")
        return (f"the markers are not of the target's dictionary {target.dictionary}: {len(ids)} read as {name} "
                f"(ids {ids[:5]}{'…' if len(ids) > 5 else ''})")
    return ""


# --- refining, checking and merging named corners ------------------------------------------------------------


def refine_charuco(gray: np.ndarray, target: CharucoTarget, corners: np.ndarray,
                   refine_radius_max: float = 20.0) -> np.ndarray:
    """Point-symmetry refinement of the found corners with the ChArUco window; failed ones become NaN."""
    found = np.isfinite(corners).all(1)
    out = np.full_like(corners, np.nan)
    if not found.any():
        return out
    square = _local_square_px(target, corners)[found]
    radius = np.clip(symmetric_radius(target) * square, 3.0, refine_radius_max)
    xy, asym, ok = refine_symmetric(gray, corners[found], radius)
    ok &= (asym < MAX_ASYMMETRY) & (np.hypot(*(xy - corners[found]).T) < 0.25 * square)
    k = np.nonzero(found)[0]
    out[k[ok]] = xy[ok]
    return out


def drop_inconsistent(corners: np.ndarray, target: CharucoTarget, tolerance: float = 0.2) -> int:
    """Drop corners that their neighbours (within two indices, at least 5) place elsewhere: further than
    `tolerance` squares from the local homography of the others. Modifies `corners`; returns how many.
    The homographies of all corners in one batch (`homography_dlt_batch`)."""

    ny, nx = target.grid_shape
    pts = target.feature_points()[:, :2]
    found = np.isfinite(corners).all(1)
    ks = np.nonzero(found)[0]
    if not ks.size:
        return 0
    square = _local_square_px(target, corners)
    j, i = np.divmod(ks, nx)
    steps = np.arange(-2, 3)
    jj, ii = j[:, None, None] + steps[None, :, None], i[:, None, None] + steps[None, None, :]
    inside = ((jj >= 0) & (jj < ny) & (ii >= 0) & (ii < nx)).reshape(len(ks), -1)
    near_k = np.where(inside, (jj * nx + ii).reshape(len(ks), -1), 0)
    near = inside & found[near_k] & (near_k != ks[:, None])  # (K, 25): the neighbours each corner is placed by
    src = np.where(near[..., None], pts[near_k], 0.0)
    n = np.maximum(near.sum(1), 1)[:, None]
    spread = np.where(near[..., None], src - src.sum(1, keepdims=True) / n[..., None], 0.0)
    placed = (near.sum(1) >= 5) & (np.linalg.matrix_rank(spread) >= 2)  # not all on one line
    if not placed.any():
        return 0
    Hs = homography_dlt_batch(src[placed], np.where(near[placed, :, None], corners[near_k[placed]], 0.0), near[placed])
    k = ks[placed]
    q = np.einsum("kij,kj->ki", Hs, np.c_[pts[k], np.ones(len(k))])
    with np.errstate(divide="ignore", invalid="ignore"):  # a point sent to infinity is far off: dropped
        off = np.hypot(*(q[:, :2] / q[:, 2:] - corners[k]).T)
    bad = k[np.isfinite(Hs).all((1, 2)) & (off > tolerance * square[k])]
    corners[bad] = np.nan
    return len(bad)


def _merge(opencv: np.ndarray, placed: np.ndarray, target: CharucoTarget):
    """Union of OpenCV's named corners and the placed lattice's, and which named them (None: neither found 4).
    Where they disagree (a corner both name more than a quarter of a square apart) OpenCV's alone are kept."""
    fo, fp = np.isfinite(opencv).all(1), np.isfinite(placed).all(1)
    if fo.sum() < 4 and fp.sum() < 4:
        return np.full_like(opencv, np.nan), None
    if fo.sum() < 4:
        return placed, "lattice placed by the markers' pattern"
    if fp.sum() < 4:
        return opencv, "markers read by OpenCV"
    both = fo & fp
    square = np.median(_local_square_px(target, placed))
    if both.any() and np.hypot(*(opencv[both] - placed[both]).T).max() > 0.25 * square:
        return opencv, "markers read by OpenCV (the lattice placement disagreed and was dropped)"
    return np.where(fo[:, None], opencv, placed), "markers read by OpenCV and the lattice placed by them"


# --- the whole pipeline ------------------------------------------------------------------------------------


def detect_board(image, target, *, measure_blur: bool = True) -> Detection:
    """Corners and blur of any target in a linear image: `detect_charuco` for a ChArUco board, else the
    checkerboard detector (`tiltfit.detect.chessboard.detect`)."""
    from tiltfit.detect.chessboard import detect

    if isinstance(target, CharucoTarget):
        return detect_charuco(image, target, measure_blur=measure_blur)
    return detect(image, target, measure_blur=measure_blur)


def detect_charuco(image, target: CharucoTarget, *, measure_blur: bool = True, use_opencv: bool = True,
                   refine_radius_max: float = 20.0) -> Detection:
    """Find a ChArUco board's corners (with ids: the feature-point order) and their blur in a linear image.

    Args:
        image: (H, W) or (H, W, C) linear float image.
        target: the CharucoTarget.
        measure_blur: also measure the blur diameter per corner.
        use_opencv: name the corners with OpenCV's marker reading where it works (else only the lattice
            placement, which also works on sharp views).
    Returns:
        Detection (grid_found False and all NaN when no corner could be named).
    """
    with torch_threads(1):
        return _detect_charuco(image, target, measure_blur, use_opencv, refine_radius_max)


def _detect_charuco(image, target, measure_blur, use_opencv, refine_radius_max) -> Detection:
    from tiltfit.detect.checks import invert_photo

    timings: dict = {}
    t0 = time.perf_counter()
    photo = to_gray(image)
    gray = invert_photo(photo) if target.inverted else photo
    H, W = gray.shape
    levels = build_pyramid(gray)
    N = target.n_points
    timings["opencv"] = time.perf_counter() - t0
    corners, source, message = _named_corners(gray, photo, levels, target, use_opencv, refine_radius_max, timings)
    if source is None:
        return Detection((W, H), corners, np.full(N, np.nan), np.full(N, np.nan), False, message, 0, timings)
    corners, blur, sigma = _blur_and_model(gray, levels, target, corners, measure_blur, timings)
    timings["total"] = time.perf_counter() - t0
    found = np.isfinite(corners).all(1)
    blur[~found], sigma[~found] = np.nan, np.nan
    ok = bool(found.sum() >= 4)
    return Detection((W, H), corners, blur, sigma, ok, f"{int(found.sum())} of {N} corners ({source})", 1, timings)


def _refined_and_completed(gray, target, corners, refine_radius_max) -> np.ndarray:
    """Step 2 and 3: named corners refined (inconsistent ones dropped) and the board completed from them."""
    corners = refine_charuco(gray, target, corners, refine_radius_max)
    drop_inconsistent(corners, target)
    if np.isfinite(corners).all(1).sum() >= 4:
        complete_corners(gray, target, corners, refine_radius_max, rounds=COMPLETION_ROUNDS,
                         window=symmetric_radius(target))
    return corners


def _add_time(timings, key, t):
    timings[key] = timings.get(key, 0.0) + time.perf_counter() - t


def _named_corners(gray, photo, levels, target, use_opencv, refine_radius_max, timings):
    """Steps 1–3: (corners (N, 2), source, message); source None (corners all NaN) when no corner could be named.

    OpenCV's named corners first, from its first read (FIRST_READ_WINDOWS), then from its default one: when they
    and the completion from them reach every corner of the board, neither a fuller read nor the lattice search
    (the costliest step, several saddle maps of the whole image) could add a corner, and they are skipped.
    """
    from tiltfit.files.det import mirrored

    named = np.full((target.n_points, 2), np.nan)
    if use_opencv:
        t = time.perf_counter()
        img8 = _srgb8(photo)
        _add_time(timings, "opencv", t)
        for windows in (FIRST_READ_WINDOWS, None):
            t = time.perf_counter()
            named = opencv_corners(photo, target, windows=windows, img8=img8)
            _add_time(timings, "opencv", t)
            if np.isfinite(named).all(1).sum() < 4:
                continue
            t = time.perf_counter()
            corners = _refined_and_completed(gray, target, named, refine_radius_max)
            _add_time(timings, "refine", t)
            if np.isfinite(corners).all() and not mirrored(corners, target.feature_points()):
                return corners, "markers read by OpenCV", ""
    t = time.perf_counter()
    placed, message = _placed_lattice(gray, levels, target, refine_radius_max)
    timings["lattice"] = time.perf_counter() - t
    corners, source = _merge(named, placed, target)
    if source is not None and mirrored(corners, target.feature_points()):
        corners, source, message = np.full_like(corners, np.nan), None, MIRROR_IMAGE
    if source is None:
        if not message.startswith(MIRROR_IMAGE):
            message = no_board_hint(photo, target) or message
        return corners, None, message
    t = time.perf_counter()
    corners = _refined_and_completed(gray, target, corners, refine_radius_max)
    _add_time(timings, "refine", t)
    return corners, source, message


def _blur_and_model(gray, levels, target, corners, measure_blur, timings):
    """Steps 4 and 5: (corners, blur_px (N,), blur_sigma_px (N,)); the widths NaN unless `measure_blur`.

    Whether the blur reaches the markers' data bits (median width beyond CANCEL_BITS_BLUR of a square) is decided
    on the widths; without `measure_blur` on those of the blur measurement's first, coarse pass alone (within
    about 10 %, `tiltfit.detect.blur.measure_blur` with one pass), which costs a fraction of the full measurement,
    and not even that where the edges' spread (`edge_spread_blur`, a pass over a few pixels) puts the median
    below `sharp_limit`: far below the decision's limit, where no width pass could take it.
    """
    from tiltfit.detect.blur import measure_blur as _measure_blur

    N = target.n_points
    H, W = gray.shape
    blur, sigma = np.full(N, np.nan), np.full(N, np.nan)
    if not np.isfinite(corners).all(1).any():
        return corners, blur, sigma
    t = time.perf_counter()
    if not measure_blur and np.nanmedian(edge_spread_blur(levels, target, corners)) < sharp_limit(target):
        timings["blur"] = time.perf_counter() - t
        return corners, blur, sigma
    passes = {} if measure_blur else {"max_passes": 1}
    blur, sigma = _measure_blur(gray, target, corners, levels=levels, **passes)
    timings["blur"] = time.perf_counter() - t
    if np.nanmedian(blur / _local_square_px(target, corners)) > CANCEL_BITS_BLUR:
        # blur reaching the markers' data bits: fit the board's own blurred picture, bits included
        t = time.perf_counter()
        tex = board_texture(target)
        for _ in range(MODEL_ROUNDS):  # better corners give better local homographies to start from
            again, _ = refine_model(gray, target, corners, blur, tex)
            corners = np.where(np.isfinite(again), again, corners)
        # a corner nearer the image's edge than its blur diameter has its blurred neighbourhood cut by the
        # edge (the symmetry window with it), and one its neighbours place elsewhere is dropped
        edge = np.minimum.reduce([corners[:, 0], W - 1 - corners[:, 0], corners[:, 1], H - 1 - corners[:, 1]])
        corners[edge < blur] = np.nan
        drop_inconsistent(corners, target, tolerance=HEAVY_BLUR_TOLERANCE)
        timings["model"] = time.perf_counter() - t
    if not measure_blur:
        blur, sigma = np.full(N, np.nan), np.full(N, np.nan)
    return corners, blur, sigma


# --- the edges' spread: step 5's decision in a few pixels ------------------------------------------------------
# `edge_spread_blur` looks at each corner within EDGE_WINDOW of a square, on the coarsest pyramid level where a
# square is at least EDGE_LEVEL_SQUARE_PX wide (the full resolution below), after a Gaussian of EDGE_SMOOTH_PX.
EDGE_WINDOW, EDGE_LEVEL_SQUARE_PX, EDGE_SMOOTH_PX = 0.3, 64.0, 1.0
# Its median is trusted to say "sharp" below this fraction of the white cells' clear band (the estimate saturates
# near the band's width once the blur covers the band: 0.12-0.31 of a square on renders blurred by 0.15-0.8, with
# a band of 0.13) and below half of CANCEL_BITS_BLUR.
SHARP_FRACTION_OF_CLEAR = 0.6


def sharp_limit(target: CharucoTarget) -> float:
    """Median edge spread (`edge_spread_blur`, squares) below which the blur is taken to be far from
    CANCEL_BITS_BLUR."""
    return min(0.5 * CANCEL_BITS_BLUR, SHARP_FRACTION_OF_CLEAR * target.white_cell_clear_mm / target.square_mm)


def edge_spread_blur(levels: dict, target: CharucoTarget, corners: np.ndarray) -> np.ndarray:
    """(N,) an estimate of the blur-disc diameter at each found corner, squares (NaN elsewhere), from how steep its
    edges are: the diameter of the Gaussian edge of the same contrast and steepest slope, σ = C / (√(2π) g), less the
    pixel's box and the smoothing (b = 4 √(σ² − 1/12 − s²)). A disc's edge is less steep than the Gaussian of its
    σ = b / 4, so a disc is read 25 % wider; noise makes edges look steeper, the smoothing damps it. C: the 2nd to
    98th percentile of the smoothed pixels within EDGE_WINDOW square; g: the steepest slope, taken per edge through
    the corner (pixels whose gradient is nearer the normal of the row or of the column line of the grid), the wider
    of the two kept, so that blur along one direction (motion) is not hidden by the other's sharp edges.

    Args:
        levels: the image's pyramid ({factor: (H, W) linear image}); corners: (N, 2) full-resolution pixels.
    """
    import cv2

    ny, nx = target.grid_shape
    square = _local_square_px(target, corners)
    found = np.isfinite(corners).all(1)
    out = np.full(len(corners), np.nan)
    s = EDGE_SMOOTH_PX
    ks = int(math.ceil(3 * s))
    for k in np.nonzero(found)[0]:
        f = max([f for f in levels if square[k] / f >= EDGE_LEVEL_SQUARE_PX] or [min(levels)])
        img = levels[f]
        x, y = (corners[k] + 0.5) / f - 0.5
        R = max(EDGE_WINDOW * square[k] / f, 3.0)
        r0, r1 = max(int(y - R) - ks - 1, 0), min(int(y + R) + ks + 3, img.shape[0])
        c0, c1 = max(int(x - R) - ks - 1, 0), min(int(x + R) + ks + 3, img.shape[1])
        patch = cv2.GaussianBlur(np.ascontiguousarray(img[r0:r1, c0:c1], dtype=np.float32), (2 * ks + 1, 2 * ks + 1),
                                 s, borderType=cv2.BORDER_REPLICATE)
        # the pixels within R whose smoothing is whole (not cut by the patch's edge): rows and columns ks + 1 in from
        # the patch's edges, so each has both neighbours for np.gradient's central differences
        a, b, c, d = ks + 1, r1 - r0 - ks - 1, ks + 1, c1 - c0 - ks - 1
        use = (np.arange(c0 + c, c0 + d)[None, :] - x) ** 2 + (np.arange(r0 + a, r0 + b)[:, None] - y) ** 2 <= R * R
        if use.sum() < 20:
            continue
        v = patch[a:b, c:d][use]
        gx = ((patch[a:b, c + 1:d + 1] - patch[a:b, c - 1:d - 1]) / 2.0)[use]
        gy = ((patch[a + 1:b + 1, c:d] - patch[a - 1:b - 1, c:d]) / 2.0)[use]
        lo, hi = np.percentile(v, (2, 98))
        slope = np.hypot(gx, gy)
        j, i = divmod(int(k), nx)
        lines = [_grid_direction(corners, found, k, step, lo_ok, hi_ok)
                 for step, lo_ok, hi_ok in ((1, i > 0, i < nx - 1), (nx, j > 0, j < ny - 1))]
        if all(u is not None for u in lines):  # a pixel on the row's edge has its gradient across the row
            across_row = np.abs(gx * lines[0][0] + gy * lines[0][1]) < np.abs(gx * lines[1][0] + gy * lines[1][1])
            groups = [slope[across_row], slope[~across_row]]
            steepest = min(float(g.max()) for g in groups if g.size >= 5) if max(g.size for g in groups) >= 5 else 0.0
        else:
            steepest = float(slope.max())
        if steepest <= 0:
            out[k] = np.inf
            continue
        sigma = (hi - lo) / (math.sqrt(2 * math.pi) * steepest)
        out[k] = 4 * math.sqrt(max(sigma * sigma - 1 / 12 - s * s, 0.0)) * f / square[k]
    return out


def _grid_direction(corners, found, k, step, lo_ok, hi_ok):
    """Unit vector along the grid line through corner k (neighbours k ± step, where found), or None."""
    a = k - step if lo_ok and found[k - step] else k
    b = k + step if hi_ok and found[k + step] else k
    if a == b:
        return None
    d = corners[b] - corners[a]
    return d / np.hypot(*d)
