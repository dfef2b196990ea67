"""Find a ChArUco board's corners, with their ids, in partial and blurred views.

Pipeline (`detect_charuco`):
1. Ids. Where the markers can be read, OpenCV's `cv2.aruco.CharucoDetector` names the corners it sees (corner
   id k is feature point k of the `CharucoTarget`); it stops where blur is wider than a marker bit (about a
   tenth of a square). The checker corners stay saddles under any blur: independently, the saddle lattice of
   `tiltfit.detect.chessboard` (grid growth, no ids) is placed on the board by matching the image, resampled in lattice
   coordinates, against the board's own picture (markers included) blurred by discs of 0 to 0.8 of a square,
   over every placement (4 turns × shifts) that keeps the lattice on the board (`place_lattice`). The best
   placement must explain the image clearly better than the next (`MIN_PLACEMENT_RATIO`), else it names
   nothing. The two are merged; where both name a corner they must agree (`_merge`).
2. Sub-pixel refinement: the point-symmetry refinement of the checkerboard path (`refine_symmetric`): at a
   ChArUco corner the two markers touching it have black borders that are point images of each other, so the
   neighbourhood is point-symmetric out to the markers' data bits, √2 (clear + bit) from the corner; the
   window radius is that (`symmetric_radius`), at most 0.4 of the local square.
3. Completion: corners neither step found, predicted by local homographies and refined the same way
   (`tiltfit.detect.chessboard.complete_corners` with the ChArUco window).
4. Blur per corner (`tiltfit.detect.blur.measure_blur`, its bands stopping at the markers' borders).
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

from tiltfit.detect.chessboard import (Detection, complete_corners, estimate_noise, find_grid, refine_symmetric, saddle_map,
                     to_gray, _median_spacing, _min_neighbour_distance, _rot)
from tiltfit.detect.imaging import build_pyramid, homography_dlt, homography_dlt_batch, to_full, torch_threads
from tiltfit.target.layout import CharucoTarget, rasterise

# A placement is accepted when the next best one leaves this many times its residual (sum of squares after a
# fitted gain and offset): the markers' pattern must tell the placements apart, not noise.
MIN_PLACEMENT_RATIO = 1.5
# Disc blurs (diameters, squares) the board's picture is compared at when placing a lattice.
PLACEMENT_BLURS = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.65, 0.8)
# Samples per square and axis when resampling the image in lattice coordinates (a marker bit is ~0.1 square).
SAMPLES_PER_SQUARE = 12
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
# A view whose markers or corners fit the board only read backwards (no lens maps a printed board like that).
MIRROR_IMAGE = "a mirror image of the board: a mirrored photo or stream"
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


def _srgb8(gray: np.ndarray) -> np.ndarray:
    """8-bit sRGB-encoded copy of a linear image (what OpenCV's detectors expect), scaled to its 99.9th percentile."""
    from camio.files import linear_to_srgb

    top = float(np.percentile(gray, 99.9)) or 1.0
    return np.clip(np.round(255 * linear_to_srgb(np.clip(gray / top, 0, 1))), 0, 255).astype(np.uint8)


def opencv_corners(gray: np.ndarray, target: CharucoTarget, refine: bool = True) -> np.ndarray:
    """(N, 2) corners named by OpenCV's `CharucoDetector` (its own sub-pixel step), NaN where none. `gray` is the
    photo as taken: for an `inverted` target its 8-bit encoding is inverted (what `detectInvertedMarker` reads)."""
    import cv2

    detector = cv2.aruco.CharucoDetector(target.opencv_board())
    if not refine:
        params = detector.getDetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_NONE
        detector.setDetectorParameters(params)
    img8 = _srgb8(gray)
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


# --- placing a lattice on the board ------------------------------------------------------------------------
def _board_pictures(target: CharucoTarget, n: int) -> list[np.ndarray]:
    """The board (checkered area) at n px per square, blurred by each of PLACEMENT_BLURS (discs), 1 px margin."""
    import cv2

    sx, sy = target.squares
    s = target.square_mm
    pad = 1
    img = rasterise(target, (-pad * s / n, (sx * n + pad) * s / n), (-pad * s / n, (sy * n + pad) * s / n),
                    sx * n + 2 * pad, sy * n + 2 * pad)
    out = []
    for b in PLACEMENT_BLURS:
        r = 0.5 * b * n
        if r < 0.5:
            out.append(img)
            continue
        k = int(math.ceil(r))
        yy, xx = np.mgrid[-k:k + 1, -k:k + 1]
        disc = (xx * xx + yy * yy <= r * r).astype(np.float32)
        out.append(cv2.filter2D(img, -1, disc / disc.sum(), borderType=cv2.BORDER_REPLICATE))
    return out


def place_lattice(gray: np.ndarray, nodes: np.ndarray, xy: np.ndarray, target: CharucoTarget):
    """Which board corner (i, j) each lattice node (a, b) is, from the markers' pattern.

    The cells whose four corners are nodes are resampled (SAMPLES_PER_SQUARE² points each, through a
    homography fitted on the nodes within two cells) and compared with the board's picture, blurred by each
    of PLACEMENT_BLURS, under every orientation-preserving placement (i, j) = rot_k(a, b) + shift that keeps
    the nodes on the board: residual sum of squares after a least-squares gain and offset, best blur.

    Args:
        gray: (H, W) linear image; nodes: (n, 2) integer lattice coordinates; xy: (n, 2) positions, pixels.
    Returns:
        (ij (n, 2) or None, message).
    """
    import cv2

    ny, nx = target.grid_shape
    n = SAMPLES_PER_SQUARE
    lut = {tuple(p): k for k, p in enumerate(nodes.tolist())}
    cells = np.array([(a, b) for (a, b) in lut if (a + 1, b) in lut and (a, b + 1) in lut and (a + 1, b + 1) in lut])
    if len(cells) < 2:
        return None, "too few whole cells seen to read the markers"
    # sample positions (u, v) in lattice units within each cell, then to pixels by local homographies
    f = (np.arange(n) + 0.5) / n
    fu, fv = np.meshgrid(f, f)
    uv = cells[:, None, :] + np.stack([fu.ravel(), fv.ravel()], -1)[None]  # (C, n², 2)
    off = np.arange(-1, 3)
    oa, ob = np.meshgrid(off, off, indexing="ij")
    near = cells[:, None, :] + np.stack([oa.ravel(), ob.ravel()], -1)[None]  # (C, 16, 2)
    idx = np.array([[lut.get(tuple(p), -1) for p in row] for row in near.tolist()])
    valid = idx >= 0
    Hs = homography_dlt_batch(near.astype(np.float64), np.where(valid[..., None], xy[np.maximum(idx, 0)], 0.0), valid)
    q = np.einsum("cij,csj->csi", Hs, np.concatenate([uv, np.ones(uv.shape[:2] + (1,))], -1))
    px = (q[..., :2] / q[..., 2:]).astype(np.float32)
    obs = cv2.remap(gray.astype(np.float32), px[..., 0], px[..., 1], cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE).astype(np.float64)  # (C, n²)
    H_img, W_img = gray.shape
    inside = ((px[..., 0] >= 0) & (px[..., 0] <= W_img - 1) & (px[..., 1] >= 0) & (px[..., 1] <= H_img - 1)).all(1)
    if inside.sum() < 2:
        return None, "too few whole cells inside the image to read the markers"
    uv, obs = uv[inside], obs[inside]
    pictures = _board_pictures(target, n)
    o = obs.ravel()
    o_c = o - o.mean()
    scores = []
    # orientation-preserving placements (k < 4), and their mirror images (k ≥ 4: the lattice's a axis reversed
    # first), which only a mirrored photo can show: markers read backwards
    for k in range(8):
        mirror = np.array([-1, 1]) if k >= 4 else np.array([1, 1])
        rn = _rot(k, nodes * mirror)
        lo, hi = rn.min(0), rn.max(0)
        # corner (i, j) = rot + shift, 0 <= i < nx, 0 <= j < ny; corner (i, j) sits at board (i + 1, j + 1) squares
        for di in range(-lo[0], nx - hi[0]):
            for dj in range(-lo[1], ny - hi[1]):
                b_uv = _rot(k, uv * mirror) + np.array([di + 1, dj + 1])  # board position in squares
                mx = (b_uv[..., 0] * n + 0.5).astype(np.float32)  # picture pixel (1 px pad, centres at +0.5)
                my = (b_uv[..., 1] * n + 0.5).astype(np.float32)
                best = math.inf
                for pic in pictures:
                    m = cv2.remap(pic, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).ravel()
                    m_c = m - m.mean()
                    denom = float(m_c @ m_c)
                    if denom <= 0:
                        continue
                    rss = float(o_c @ o_c) - float(o_c @ m_c) ** 2 / denom
                    if (o_c @ m_c) < 0:  # dark and light swapped: not this placement
                        rss = float(o_c @ o_c)
                    best = min(best, rss)
                scores.append((best, k, di, dj))
    scores.sort()
    if not scores:
        return None, "the lattice does not fit on the board"
    best, k, di, dj = scores[0]
    second = scores[1][0] if len(scores) > 1 else math.inf
    if not second > MIN_PLACEMENT_RATIO * max(best, 1e-30):
        return None, (f"the markers do not tell the board's placements apart (residuals {best:.3g} and {second:.3g}); "
                      "the view is too blurred or too small")
    if k >= 4:
        return None, f"{MIRROR_IMAGE} (the markers' pattern fits the board read backwards)"
    return _rot(k, nodes) + np.array([di, dj]), ""


# Smoothing scales (full-resolution pixels) the saddle lattice is looked for at: the markers' bits are saddles
# too, so the scale must reach a fifth of a square or so, which is not known beforehand.
LATTICE_SCALES_PX = (1.5, 3.0, 4.5, 6.0, 8.0, 12.0, 16.0)


def _lattice(gray: np.ndarray, levels: dict):
    """The largest saddle lattice of `tiltfit.detect.chessboard` (no ids) over LATTICE_SCALES_PX: (nodes (n, 2), positions
    (n, 2) full-resolution pixels) or None. A scale counts when the lattice's spacing is at least 2.5 × its sigma."""
    best = None
    for scale in LATTICE_SCALES_PX:
        f = max([f for f in levels if scale / f >= 1.5 and min(levels[f].shape) >= 32] or [1])
        img, sigma = levels[f], scale / f
        noise = estimate_noise(img)
        grid = find_grid(saddle_map(img, sigma, noise), noise)
        if len(grid) < 4:
            continue
        nodes = np.array(list(grid.keys()))
        xy_l = np.array([grid[tuple(p)] for p in nodes.tolist()])
        if _median_spacing(nodes, xy_l) < 2.5 * sigma:
            continue
        if best is None or len(nodes) > len(best[0]):
            best = nodes, to_full(xy_l, f)
    return best


def _local_square_px(target: CharucoTarget, corners: np.ndarray) -> np.ndarray:
    """(N,) image size of a square at each found corner (distance to the nearest found grid neighbour)."""
    ny, nx = target.grid_shape
    g = corners.reshape(ny, nx, 2)
    d = np.full((ny, nx), np.inf)
    dx = np.hypot(*np.diff(g, axis=1).transpose(2, 0, 1))
    dy = np.hypot(*np.diff(g, axis=0).transpose(2, 0, 1))
    for a, sl in ((dx, (slice(None), slice(None, -1))), (dx, (slice(None), slice(1, None))),
                  (dy, (slice(None, -1), slice(None))), (dy, (slice(1, None), slice(None)))):
        d[sl] = np.fmin(d[sl], np.where(np.isfinite(a), a, np.inf))
    d = d.ravel()
    fallback = np.median(d[np.isfinite(d)]) if np.isfinite(d).any() else 10.0
    return np.where(np.isfinite(d), d, fallback)


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


def _placed_lattice(gray, levels, target, refine_radius_max):
    """(N, 2) corners from the saddle lattice placed by the markers' pattern (NaN elsewhere), and a message."""
    N = target.n_points
    corners = np.full((N, 2), np.nan)
    lat = _lattice(gray, levels)
    if lat is None:
        return corners, "no checker corners found"
    nodes, xy = lat
    radius = np.clip(0.4 * _min_neighbour_distance(nodes, xy), 3.0, refine_radius_max)
    xy_r, _, ok = refine_symmetric(gray, xy, radius)
    xy = np.where(ok[:, None], xy_r, xy)
    ij, message = place_lattice(gray, nodes, xy, target)
    if ij is not None:
        corners[target.feature_index(ij[:, 0], ij[:, 1])] = xy
    return corners, message


def drop_inconsistent(corners: np.ndarray, target: CharucoTarget, tolerance: float = 0.2) -> int:
    """Drop corners that their neighbours (within two indices, at least 5) place elsewhere: further than
    `tolerance` squares from the local homography of the others. Modifies `corners`; returns how many."""
    ny, nx = target.grid_shape
    pts = target.feature_points()[:, :2]
    found = np.isfinite(corners).all(1)
    square = _local_square_px(target, corners)
    bad = []
    for k in np.nonzero(found)[0]:
        j, i = divmod(int(k), nx)
        near = [jj * nx + ii for jj in range(max(0, j - 2), min(ny, j + 3))
                for ii in range(max(0, i - 2), min(nx, i + 3))
                if found[jj * nx + ii] and jj * nx + ii != k]
        if len(near) < 5 or np.linalg.matrix_rank(pts[near] - pts[near].mean(0)) < 2:
            continue
        Hm = homography_dlt(pts[near], corners[near])
        if Hm is None or not np.isfinite(Hm).all():
            continue
        q = Hm @ np.array([pts[k, 0], pts[k, 1], 1.0])
        if np.hypot(*(q[:2] / q[2] - corners[k])) > tolerance * square[k]:
            bad.append(k)
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


# Points per pixel side where `refine_model` looks the board's picture up before blurring it.
SUPERSAMPLE = 3


def _disc_kernel(r: float) -> np.ndarray:
    """Normalised kernel of a disc of radius r (in taps), each tap weighted by its area inside (4 × 4 points)."""
    k = int(math.ceil(r)) + 1
    o = (np.arange(4) + 0.5) / 4 - 0.5
    yy, xx = np.mgrid[-k:k + 1, -k:k + 1].astype(np.float64)
    ker = sum(((xx + a) ** 2 + (yy + b) ** 2 <= r * r) for a in o for b in o).astype(np.float32)
    return ker / ker.sum()


# --- model-based refinement: the board's own picture, blurred, fitted around each corner ------------------
# Half-width (squares, target plane) of the window around a corner whose pixels `refine_model` fits.
MODEL_WINDOW = 0.6
# Iterations at most per corner and round, and rounds (the local homographies refitted on the refined corners).
MODEL_ITERATIONS = 20
MODEL_ROUNDS = 2
# Converged when a Gauss-Newton step would still gain less than 0.01 (the parameters within about 0.15 of their σ;
# residuals in units of the noise) or a step gains less than 1e-4 of the cost (the Jacobian's blur-and-warp
# approximation makes the last steps creep; tighter changes no corner by more than 0.001 px on the renders).
MODEL_DECREMENT_TOL, MODEL_FTOL = 1e-2, 1e-4
# Texels per marker bit of the board's picture the model looks up (bilinearly, SUPERSAMPLE² points a pixel).
MODEL_TEXELS_PER_BIT = 8


def board_texture(target: CharucoTarget):
    """The board's exact area-averaged picture (dark fraction 0..1, markers included) over its extent plus a
    square of blank margin, and the mm → texel map (origin mm, texels per mm)."""
    n_bits = target.opencv_board().getDictionary().markerSize + 2
    ppm = MODEL_TEXELS_PER_BIT * n_bits / target.marker_mm
    x0, y0, x1, y1 = target.extent_mm
    pad = target.square_mm
    x0, y0 = x0 - pad, y0 - pad
    nw, nh = int(math.ceil((x1 + pad - x0) * ppm)), int(math.ceil((y1 + pad - y0) * ppm))
    tex = 1.0 - rasterise(target, (x0, x0 + nw / ppm), (y0, y0 + nh / ppm), nw, nh)
    return tex.astype(np.float32), np.array([x0, y0]), ppm


def _render_patch(tex, origin, ppm, Hm, r0, c0, h, w, radius_px, d_radius=None):
    """Model of pixels rows r0..r0+h−1, columns c0..c0+w−1: the board's dark fraction through homography Hm
    (mm → px), looked up at SUPERSAMPLE² points a pixel, convolved with a disc of `radius_px` there and
    box-averaged; its derivatives along x and y (per pixel); and, given `d_radius`, the same picture under a
    disc of radius_px + d_radius."""
    import cv2

    S = SUPERSAMPLE
    pad = int(math.ceil(radius_px + (d_radius or 0.0))) + 2  # pixels beyond the patch so that its blur is whole
    sub = (np.arange(S) + 0.5) / S - 0.5
    v = (np.arange(r0 - pad, r0 + h + pad)[:, None] + sub[None]).ravel()
    u = (np.arange(c0 - pad, c0 + w + pad)[:, None] + sub[None]).ravel()
    V, U = np.meshgrid(v, u, indexing="ij")
    p = np.stack([U, V, np.ones_like(U)], -1) @ np.linalg.inv(Hm).T
    mx = ((p[..., 0] / p[..., 2] - origin[0]) * ppm - 0.5).astype(np.float32)
    my = ((p[..., 1] / p[..., 2] - origin[1]) * ppm - 0.5).astype(np.float32)
    sharp = cv2.remap(tex, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    def blurred(r):
        return cv2.filter2D(sharp, -1, _disc_kernel(r), borderType=cv2.BORDER_REPLICATE) if r > 0.5 else sharp

    fine = blurred(radius_px * S).astype(np.float64)
    gy, gx = np.gradient(fine, 1.0 / S)
    out = [fine, gx, gy] + ([] if d_radius is None else [blurred((radius_px + d_radius) * S)])
    m = pad * S
    return [a[m:m + h * S, m:m + w * S].reshape(h, S, w, S).mean((1, 3), dtype=np.float64) for a in out]


def refine_model(gray: np.ndarray, target: CharucoTarget, corners: np.ndarray, blur_px: np.ndarray,
                 texture=None) -> tuple[np.ndarray, np.ndarray]:
    """Corners fitted by the board's own picture around each: (N, 2), NaN where the fit failed, and the noise's
    floor on each corner's error: (N,) √(trace of the 2 × 2 Cramér–Rao covariance of its position), pixels, with
    the noise from the fit's residual (the RMS distance an unbiased fit can reach at this noise, not less).

    Per found corner with a measured blur: the pixels whose target-plane position (by the local homography of
    the corners around, `tiltfit.detect.blur._local_homographies`) lies within MODEL_WINDOW square of it are fitted by
    gain × (the board's exact picture, markers' bits included, through the homography, convolved with a disc
    in the image) + offset, by `tiltfit.solve.least_squares` over an affine correction of the homography about
    the corner (6), the disc's radius, the gain and the offset (`_fit_corner`). Nothing is painted out or
    assumed symmetric: the bits are part of the model. The corner is the corrected homography's image of the
    board corner.
    """
    from tiltfit.detect.blur import _local_homographies
    from tiltfit.detect.chessboard import estimate_noise

    texture = texture or board_texture(target)
    found = np.isfinite(corners).all(1) & np.isfinite(blur_px)
    Hs = _local_homographies(target, corners, np.isfinite(corners).all(1))
    pts = target.feature_points()[:, :2]
    square = _local_square_px(target, corners)
    noise = estimate_noise(gray)
    out = np.full_like(corners, np.nan)
    floor = np.full(len(corners), np.nan)
    for k in np.nonzero(found)[0]:
        if k in Hs:
            fit = _fit_corner(gray, target, texture, Hs[k], pts[k], 0.5 * float(blur_px[k]), noise)
            if fit is not None and np.hypot(*(fit[0] - corners[k])) < 0.25 * square[k]:
                out[k], floor[k] = fit
    return out, floor


def _fit_corner(gray, target, texture, Hm, P, radius, noise):
    """One corner of `refine_model`: (position (2,), floor) or None. Hm: homography board mm → px from the
    corners around; P: the corner on the board, mm; radius: the blur disc's, px; noise: the pixels' σ.

    Parameters x = (t (2), a (2 × 2), disc radius, gain, offset); the image is modelled as
    gain · R(p) + offset, R the board's dark fraction through W ∘ Hm blurred by the disc, with
    W(q) = q + a (q − c) + t about the start c. Derivatives: ∂R/∂t = −∇R, ∂R/∂a_ij = −∂_i R · (q − c)_j with
    q = W⁻¹(p) (exact for a warp of the blurred picture), less ½ radius ∂R/∂radius on the diagonal (the disc does
    not scale with the picture); ∂R/∂radius by a forward difference. The disc's change of shape under the warp
    is left out of the derivatives (their affine columns are 30–50 % off): the solver only takes steps that
    lower the true cost, so it costs iterations, not accuracy (the corners' errors are at the Cramér–Rao floor).
    """
    import torch

    from tiltfit.solve import LMOptions, SolverError, covariance, least_squares

    tex, origin, ppm = texture
    H_img, W_img = gray.shape
    q = Hm @ np.array([P[0], P[1], 1.0])
    c = q[:2] / q[2]
    win = MODEL_WINDOW * target.square_mm
    box = np.array([[P[0] - win, P[1] - win, 1], [P[0] + win, P[1] - win, 1], [P[0] + win, P[1] + win, 1],
                    [P[0] - win, P[1] + win, 1]]) @ Hm.T
    box = box[:, :2] / box[:, 2:]
    lo = np.maximum(np.floor(box.min(0)).astype(int) - 1, 0)
    hi = np.minimum(np.ceil(box.max(0)).astype(int) + 1, [W_img - 1, H_img - 1])
    if np.any(hi - lo < 4):
        return None
    c0, r0 = lo
    w, h = hi - lo + 1
    yy, xx = np.mgrid[r0:r0 + h, c0:c0 + w].astype(np.float64)
    pb = np.stack([xx, yy, np.ones_like(xx)], -1) @ np.linalg.inv(Hm).T
    X, Y = pb[..., 0] / pb[..., 2], pb[..., 1] / pb[..., 2]
    # pixels nearer the image's edge than the blur's reach see the scene beyond it: left out
    reach = radius + 1.0
    use = ((np.abs(X - P[0]) <= win) & (np.abs(Y - P[1]) <= win) & (xx >= reach) & (xx <= W_img - 1 - reach)
           & (yy >= reach) & (yy <= H_img - 1 - reach))
    if use.sum() < 50:
        return None
    y = gray[r0:r0 + h, c0:c0 + w][use].astype(np.float64)
    p = np.stack([xx[use], yy[use]], 1)
    cache = {}

    def warp(v):
        """(homography W ∘ Hm, q − c per pixel) of the parameters v."""
        a = np.array([[1 + v[2], v[3]], [v[4], 1 + v[5]]])
        Wm = np.eye(3)
        Wm[:2, :2], Wm[:2, 2] = a, v[:2] + c - a @ c
        det = a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0]
        a_inv = np.array([[a[1, 1], -a[0, 1]], [-a[1, 0], a[0, 0]]]) / det
        return Wm @ Hm, (p - c - v[:2]) @ a_inv.T

    def render(v):
        """Picture, its x and y derivatives, and the picture under a disc larger by `d_radius(v)`: at v's warp and
        disc (one render for the residuals and the Jacobian at the same point)."""
        key = v[:7].tobytes()
        if key not in cache:
            cache.clear()
            cache[key] = [a[use] for a in _render_patch(tex, origin, ppm, warp(v)[0], r0, c0, h, w, max(v[6], 0.0),
                                                        d_radius(v))]
        return cache[key]

    def d_radius(v):
        return max(0.05 * v[6], 0.1)

    def residuals(x):
        v = x.numpy()
        B = render(v)[0]
        return torch.from_numpy((y - v[7] * B - v[8]) / noise)

    def jacobian(x):
        v = x.numpy()
        B, gx, gy, B2 = render(v)
        dr = d_radius(v)
        d = warp(v)[1]
        g = v[7]
        dB_dr = (B2 - B) / dr
        iso = 0.5 * max(v[6], 0.0) * dB_dr  # the disc keeps its size while the picture scales
        dmodel = np.stack([-g * gx, -g * gy, -g * (gx * d[:, 0] + iso), -g * gx * d[:, 1], -g * gy * d[:, 0],
                           -g * (gy * d[:, 1] + iso), g * dB_dr, B, np.ones_like(B)], 1)
        return torch.from_numpy(-dmodel / noise)

    B0 = render(np.r_[np.zeros(6), radius, 0.0, 0.0])[0]
    gain = float(np.mean((B0 - B0.mean()) * (y - y.mean())) / max(np.var(B0), 1e-12))
    x0 = torch.tensor(np.r_[np.zeros(6), radius, gain, y.mean() - gain * B0.mean()], dtype=torch.float64)
    try:
        options = LMOptions(max_iterations=MODEL_ITERATIONS, decrement_tol=MODEL_DECREMENT_TOL, ftol=MODEL_FTOL)
        fit = least_squares(residuals, x0, options, jacobian_fn=jacobian)
        cov = covariance(fit, 2 * fit.cost / max(len(y) - len(x0), 1)).dense().numpy()
    except SolverError:
        return None
    v = fit.x.numpy()
    if v[7] >= 0:  # dark squares came out light
        return None
    q = warp(v)[0] @ np.array([P[0], P[1], 1.0])
    return q[:2] / q[2], float(np.sqrt(cov[0, 0] + cov[1, 1]))


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
    from tiltfit.detect.blur import measure_blur as _measure_blur

    from tiltfit.detect.chessboard import invert_photo
    from tiltfit.files.det import mirrored

    timings: dict = {}
    t0 = time.perf_counter()
    photo = to_gray(image)
    gray = invert_photo(photo) if target.inverted else photo
    H, W = gray.shape
    levels = build_pyramid(gray)
    N = target.n_points
    corners = opencv_corners(photo, target) if use_opencv else np.full((N, 2), np.nan)
    timings["opencv"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    placed, message = _placed_lattice(gray, levels, target, refine_radius_max)
    timings["lattice"] = time.perf_counter() - t1
    corners, source = _merge(corners, placed, target)
    if source is not None and mirrored(corners, target.feature_points()):
        corners, source, message = np.full_like(corners, np.nan), None, MIRROR_IMAGE
    if source is None:
        if not message.startswith(MIRROR_IMAGE):
            hint = no_board_hint(photo, target)
            message = hint or message
        return Detection((W, H), corners, np.full(N, np.nan), np.full(N, np.nan), False, message, 0, timings)
    t2 = time.perf_counter()
    corners = refine_charuco(gray, target, corners, refine_radius_max)
    drop_inconsistent(corners, target)
    if np.isfinite(corners).all(1).sum() >= 4:
        complete_corners(gray, target, corners, refine_radius_max, rounds=COMPLETION_ROUNDS,
                         window=symmetric_radius(target))
    timings["refine"] = time.perf_counter() - t2
    found = np.isfinite(corners).all(1)
    blur, sigma = np.full(N, np.nan), np.full(N, np.nan)
    if found.any():
        t3 = time.perf_counter()
        blur, sigma = _measure_blur(gray, target, corners, levels=levels)
        timings["blur"] = time.perf_counter() - t3
        if np.nanmedian(blur / _local_square_px(target, corners)) > CANCEL_BITS_BLUR:
            # blur reaching the markers' data bits: fit the board's own blurred picture, bits included
            t4 = time.perf_counter()
            tex = board_texture(target)
            for _ in range(MODEL_ROUNDS):  # better corners give better local homographies to start from
                again, _ = refine_model(gray, target, corners, blur, tex)
                corners = np.where(np.isfinite(again), again, corners)
            # a corner nearer the image's edge than its blur diameter has its blurred neighbourhood cut by the
            # edge (the symmetry window with it), and one its neighbours place elsewhere is dropped
            edge = np.minimum.reduce([corners[:, 0], W - 1 - corners[:, 0], corners[:, 1], H - 1 - corners[:, 1]])
            corners[edge < blur] = np.nan
            drop_inconsistent(corners, target, tolerance=HEAVY_BLUR_TOLERANCE)
            timings["model"] = time.perf_counter() - t4
        if not measure_blur:
            blur, sigma = np.full(N, np.nan), np.full(N, np.nan)
    timings["total"] = time.perf_counter() - t0
    found = np.isfinite(corners).all(1)
    blur[~found], sigma[~found] = np.nan, np.nan
    ok = bool(found.sum() >= 4)
    return Detection((W, H), corners, blur, sigma, ok, f"{int(found.sum())} of {N} corners ({source})", 1, timings)
