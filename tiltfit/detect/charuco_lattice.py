"""A ChArUco board's corners named without reading a marker: the saddle lattice of the checkerboard detector (grid
growth over several smoothing scales, no ids) placed on the board by matching the image, resampled in lattice
coordinates, against the board's own picture (markers included) blurred by discs of 0 to 0.8 of a square, over
every placement that keeps the lattice on the board (`place_lattice`). Works where blur is wider than a marker bit
and OpenCV reads no marker. Step 1 of `tiltfit.detect.charuco`.
"""
from __future__ import annotations

import math

import numpy as np

from tiltfit.detect.grid import _median_spacing, _min_neighbour_distance, find_grid
from tiltfit.detect.imaging import estimate_noise, homography_dlt_batch, to_full
from tiltfit.detect.indexing import _rot
from tiltfit.detect.refine import refine_symmetric
from tiltfit.detect.saddles import saddle_map
from tiltfit.target.layout import CharucoTarget
from tiltfit.target.raster import rasterise


# A placement is accepted when the next best one leaves this many times its residual (sum of squares after a
# fitted gain and offset): the markers' pattern must tell the placements apart, not noise.
MIN_PLACEMENT_RATIO = 1.5


# Disc blurs (diameters, squares) the board's picture is compared at when placing a lattice.
PLACEMENT_BLURS = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.65, 0.8)


# Samples per square and axis when resampling the image in lattice coordinates (a marker bit is ~0.1 square).
SAMPLES_PER_SQUARE = 12


# A view whose markers or corners fit the board only read backwards (no lens maps a printed board like that).
MIRROR_IMAGE = "a mirror image of the board: a mirrored photo or stream"


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
