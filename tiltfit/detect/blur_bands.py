"""The pixel bands a corner's blur is fitted on (`tiltfit.detect.blur`): per found corner a local homography of the
board (`_local_homographies`), and along each of the up-to-four half-edges leaving it the band of pixels, with their
weights and distances to the edge and the cells it crosses (`_half_edges`, one band: `_band`).

A band's pixels lie along the half of the edge nearest the point, away from it by more than the blur radius; their
weights taper to 0 inside every limit of the band, so the pixel set moves smoothly with the corners.
"""
from __future__ import annotations

import math

import numpy as np

from tiltfit.detect.imaging import homography_dlt_batch
from tiltfit.target.layout import Target

def _local_homographies(target: Target, corners_px: np.ndarray, found: np.ndarray):
    """Per found corner, the homography target (X, Y) -> pixels fitted on found corners within 2 indices."""
    ny, nx = target.grid_shape
    pts = target.feature_points()[:, :2]
    ks = np.nonzero(found)[0]
    if ks.size == 0:
        return {}
    dj, di = np.meshgrid(np.arange(-2, 3), np.arange(-2, 3), indexing="ij")
    jj = ks[:, None] // nx + dj.ravel()[None]
    ii = ks[:, None] % nx + di.ravel()[None]
    inside = (jj >= 0) & (jj < ny) & (ii >= 0) & (ii < nx)
    kk = np.where(inside, jj * nx + ii, 0)
    valid = inside & found[kk]
    Hs = homography_dlt_batch(pts[kk], np.where(valid[..., None], corners_px[kk], 0.0), valid)
    return {int(k): Hm for k, Hm in zip(ks, Hs) if np.isfinite(Hm).all()}


# The four half-edges at a corner, in the order (horizontal, vertical) towards +, then towards −.
_HORIZONTAL = np.array([True, False, True, False])
_SIGN = np.array([1, 1, -1, -1])


def _edge_cells(target: Target, j: np.ndarray, i: np.ndarray):
    """Target-plane geometry of the four half-edges at the corners (j, i) (each (K, 1)), in the order of _HORIZONTAL:
    (K, 4) the edge line's coordinate, the along-edge coordinates of its near and far ends, the parallel lines
    that close the band before and after it, and (K, 4, 4) kappa, white (1) or dark (0), of the cells crossed.

    A horizontal edge Y = ye[j+1] leaving the corner towards +X borders cell column i+1, towards −X column i.
    """
    horizontal, sgn = _HORIZONTAL, _SIGN
    xe, ye = np.asarray(target.x_edges), np.asarray(target.y_edges)
    value = np.where(horizontal, ye[j + 1], xe[i + 1])  # (K, 4) the edge line's coordinate
    a_near = np.where(horizontal, xe[i + 1], ye[j + 1])
    a_far = np.where(horizontal, xe[i + 1 + sgn], ye[j + 1 + sgn])
    lane = np.where(horizontal, np.where(sgn > 0, i + 1, i), np.where(sgn > 0, j + 1, j))
    idx = np.where(horizontal, j, i)  # the cell index across the edge just before it
    far_lo = np.where(horizontal, ye[j], xe[i])  # the parallel edges before and after (always inside)
    far_hi = np.where(horizontal, ye[j + 2], xe[i + 2])
    cells = idx[..., None] + np.arange(-1, 3)  # (K, 4, 4) cells across the edge
    dark = np.where(horizontal[:, None], target.is_dark(lane[..., None], cells), target.is_dark(cells, lane[..., None]))
    kappa = np.where(dark, 0.0, 1.0)
    clear = target.white_cell_clear_mm
    if clear is not None:
        # a white cell holding a marker (ChArUco) is white only within `clear` of its edges: the band's far
        # line on that side is the marker's dark border
        before_white, after_white = ~dark[..., 1], ~dark[..., 2]
        far_lo = np.where(before_white, value - clear, far_lo)
        far_hi = np.where(after_white, value + clear, far_hi)
        kappa[..., 0] = np.where(before_white, 0.0, kappa[..., 0])
        kappa[..., 3] = np.where(after_white, 0.0, kappa[..., 3])
    return value, a_near, a_far, far_lo, far_hi, kappa


# Band weights fall from 1 to 0 over this distance (pixels of the level) inside each limit of the band, so the
# pixel set, and with it the fitted width, moves smoothly with the corner (a pixel entering at full weight
# moved some widths by many σ for a 1e-6 px change of a corner)
_TAPER_PX = 1.0
# Weight a band needs to be kept; it fades in over as much again, so a band does not appear at full weight
_MIN_BAND_WEIGHT = 12.0
# Thinning keeps a pixel (x, y) when frac(x φ₁ + y φ₂) < 2^−k (the R2 low-discrepancy sequence, Roberts 2018): a
# fixed, evenly spread subset of the image, so a pixel entering or leaving the band does not reshuffle the rest
_R2 = (0.7548776662466927, 0.5698402909980532)


def _ramp(x: np.ndarray) -> np.ndarray:
    """0 for x <= 0, 1 for x >= _TAPER_PX, linear between."""
    return np.minimum(np.maximum(x / _TAPER_PX, 0.0), 1.0)  # np.clip's values, without its per-call overhead


def _band(lo, hi, lines, margin, reach, s_max, max_pixels) -> dict | None:
    """One band's pixels within the box lo..hi (x, y): px (n, 2), their weights w (n,) in (0, 1] and their signed
    distances d0 to the edge, d_lo and d_hi to the next parallel edges, from the image lines (5, 3) (edge, near
    and far closing lines, lines before and after); None below _MIN_BAND_WEIGHT (`_bands` of one band)."""
    return _bands(np.asarray([lo]), np.asarray([hi]), np.asarray([lines]), np.asarray([margin]), np.asarray([reach]),
                  np.asarray([s_max]), max_pixels)[0]


def _bands(lo, hi, lines, margin, reach, s_max, max_pixels) -> list[dict | None]:
    """The pixels of m bands at once, each within its box lo..hi (m, 2) (x, y), from its image lines (m, 5, 3) (edge,
    near and far closing lines, lines before and after) and its limits margin, reach, s_max (m,): per band px (n, 2),
    weights w (n,) in (0, 1], signed distances d0 to the edge, d_lo and d_hi to the next parallel edges; None for a
    band below _MIN_BAND_WEIGHT.

    A pixel's weight tapers to 0 inside every limit of the band (`_TAPER_PX`), so it is a continuous function
    of the corners; beyond max_pixels a band keeps a fixed 2^−k share of the image's pixels (`_R2`)."""
    lo, hi = np.asarray(lo, dtype=np.int64), np.asarray(hi, dtype=np.int64)
    m = len(lo)
    if m == 0:
        return []
    # the box of a slanted band is mostly outside it: on each of its rows, only the run of pixels within s_max
    # (and a pixel more) of the edge line a x + b y + c = 0 is listed
    height = hi[:, 1] - lo[:, 1] + 1
    row_band = np.repeat(np.arange(m), height)
    row_y = lo[row_band, 1] + np.arange(row_band.size) - np.repeat(np.cumsum(height) - height, height)
    a, b, c = (lines[row_band, 0, j] for j in range(3))
    steep = np.abs(a) > 1e-6  # else the edge is nearly along the row: the whole row
    a_safe = np.where(steep, a, 1.0)
    x_mid, half = -(b * row_y + c) / a_safe, s_max[row_band] / np.abs(a_safe)
    x_lo, x_hi = lo[row_band, 0], hi[row_band, 0]
    first = np.where(steep, np.clip(np.floor(x_mid - half) - 1, x_lo, x_hi + 1), x_lo).astype(np.int64)
    last = np.where(steep, np.clip(np.ceil(x_mid + half) + 1, x_lo - 1, x_hi), x_hi).astype(np.int64)
    count = np.maximum(last - first + 1, 0)
    # those runs' pixels, row by row, in one list
    row = np.repeat(np.arange(row_band.size), count)
    band = row_band[row]
    x = (first[row] + np.arange(row.size) - np.repeat(np.cumsum(count) - count, count)).astype(np.float64)
    y = row_y[row].astype(np.float64)
    # signed distances to the edge, the two lines closing the band, and the next parallel edges; the pixels
    # beyond s_max of the edge (weight 0) are dropped first
    coef = np.ascontiguousarray(lines.transpose(1, 2, 0))  # (5, 3, m): each line's a, b, c by band
    d0 = x * coef[0, 0].take(band) + y * coef[0, 1].take(band) + coef[0, 2].take(band)
    near = np.nonzero(np.abs(d0) < s_max.take(band))[0]
    band, x, y, d0 = band[near], x[near], y[near], d0[near]
    dn, dfar, d_lo, d_hi = (x * coef[j, 0].take(band) + y * coef[j, 1].take(band) + coef[j, 2].take(band)
                            for j in range(1, 5))
    mg = margin.take(band)
    w = (_ramp(s_max.take(band) - np.abs(d0)) * _ramp(dn - mg) * _ramp(dfar - mg) * _ramp(reach.take(band) - dn)
         * _ramp(d_lo) * _ramp(d_hi))
    keep = w > 0
    n_keep = np.bincount(band[keep], minlength=m)
    thin = n_keep > max_pixels
    if thin.any():
        share = np.where(thin, 0.5 ** np.ceil(np.log2(np.maximum(n_keep, 1) / max_pixels)), 2.0)
        u = np.modf(x * _R2[0] + y * _R2[1])[0]
        keep &= u < share[band]
    band, w = band[keep], w[keep]
    px = np.stack([x[keep], y[keep]], -1).astype(int)
    d0, d_lo, d_hi = d0[keep], d_lo[keep], d_hi[keep]
    total = np.bincount(band, weights=w, minlength=m).tolist()
    ends = np.cumsum(np.bincount(band, minlength=m)).tolist()
    out = []
    for weight, i, j in zip(total, [0] + ends[:-1], ends):  # band by band: its total weight and its pixels i:j
        if weight <= _MIN_BAND_WEIGHT:
            out.append(None)
            continue
        fade = min(1.0, (weight - _MIN_BAND_WEIGHT) / _MIN_BAND_WEIGHT)
        out.append(dict(px=px[i:j], w=w[i:j] * fade, d0=d0[i:j], d_lo=d_lo[i:j], d_hi=-d_hi[i:j]))
    return out


def _half_edges(target: Target, ks: np.ndarray, Hms: np.ndarray, r_est: np.ndarray, image_shape, max_pixels: int,
                first_pass: bool = False, grads: np.ndarray | None = None) -> list[list[dict]]:
    """Pixel bands of the up-to-four half-edges at feature points ks, with their profile geometry.

    The geometry (edge lines, band limits, bounding boxes) and the pixels (`_bands`) are computed for all bands at
    once.

    Args:
        ks: (K,) feature-point indices; Hms: (K, 3, 3) homographies target -> pixels of the image the bands
            are cut from; r_est: (K,) blur radius expected at each point, pixels; grads: (K, 2) expected
            gradient of the diameter, per pixel, or None.
        first_pass: allow bands nearer the point (to 0.3 of the edge) when r_est is only an upper bound.
    Returns:
        per point, a list of dicts: px (n, 2) pixel positions, dxy (n, 2) offsets from the point, d0 / d_lo /
        d_hi signed distances to the edge and the next parallel edges (positive towards larger target
        coordinates), kappa (4,) white (1) or dark (0) for the cells crossed, wa, wb the pixel's projected
        widths.
    """
    K = len(ks)
    xe, ye = np.asarray(target.x_edges), np.asarray(target.y_edges)
    H_img, W_img = image_shape
    r_est = np.asarray(r_est, dtype=np.float64)[:, None]  # (K, 1)
    gnorm = np.zeros((K, 1)) if grads is None else np.hypot(grads[:, 0], grads[:, 1])[:, None]
    j, i = (a[:, None] for a in np.divmod(np.asarray(ks), target.grid_shape[1]))
    horizontal = _HORIZONTAL
    value, a_near, a_far, far_lo, far_hi, kappa = _edge_cells(target, j, i)
    HiT = np.linalg.inv(Hms).transpose(0, 2, 1)

    def line(on_x, v):
        """Image lines (K, 4, 3), a² + b² = 1, of the target lines X = v (on_x) or Y = v."""
        lt = np.stack([np.where(on_x, 1.0, 0.0) + 0 * v, np.where(on_x, 0.0, 1.0) + 0 * v, -v], -1)
        li = np.einsum("kij,ksj->ksi", HiT, lt)
        return li / np.hypot(li[..., 0], li[..., 1])[..., None]

    def point(x, y):
        q = np.einsum("kij,ksj->ksi", Hms, np.stack([x, y, np.ones_like(x)], -1))
        return q[..., :2] / q[..., 2:]

    def oriented(L, p):
        """L flipped where needed so that it is positive at the points p (K, 4, 2)."""
        return np.where(((L[..., :2] * p).sum(-1) + L[..., 2] < 0)[..., None], -L, L)

    vertical_line = ~horizontal  # X = const: the edge line of a vertical edge
    L0 = line(vertical_line, value)
    P_near, P_far = line(horizontal, a_near), line(horizontal, a_far)
    L_lo, L_hi = line(vertical_line, far_lo), line(vertical_line, far_hi)
    along_mid = 0.5 * (a_near + a_far)
    after = value + 0.25 * (far_hi - value)
    pa = point(np.where(horizontal, along_mid, after), np.where(horizontal, after, along_mid))
    pm = point(np.where(horizontal, along_mid, value), np.where(horizontal, value, along_mid))
    L0 = oriented(L0, pa)  # positive towards the "after" cells (larger target coordinate)
    P_near, P_far = oriented(P_near, pm), oriented(P_far, pm)
    L_lo, L_hi = oriented(L_lo, pm), oriented(L_hi, pm)  # positive towards the central edge
    centre = point(xe[i + 1] + 0 * value, ye[j + 1] + 0 * value)  # (K, 4, 2), the same for the 4 edges
    seg = 2.0 * np.hypot(*(pm - centre).transpose(2, 0, 1))  # image length of the whole edge segment (approx.)
    r_far = r_est + 0.5 * gnorm * seg  # the blur may grow along the band
    core = np.maximum(r_est, np.minimum(r_far, 0.45 * seg))
    margin = np.minimum(r_est + 1.5, 0.3 * seg) if first_pass else core + 1.5
    reach = np.maximum(0.5 * seg, margin + np.maximum(3.0, 0.1 * seg))  # the near half, or a short band past it
    s_max = 1.3 * core + 4.0
    n_px = L0[..., :2]
    p_end = centre + (pm - centre) * np.minimum(2.0, reach / (0.5 * seg))[..., None]
    ends = np.stack([centre - s_max[..., None] * n_px, centre + s_max[..., None] * n_px,
                     p_end - s_max[..., None] * n_px, p_end + s_max[..., None] * n_px], -2)  # (K, 4, 4, 2)
    lo = np.maximum(np.floor(ends.min(-2)).astype(int), 0)
    hi = np.minimum(np.ceil(ends.max(-2)).astype(int), [W_img - 1, H_img - 1])
    alpha = np.arctan2(L0[..., 1], L0[..., 0])
    wa = np.maximum(np.abs(np.cos(alpha)), np.abs(np.sin(alpha)))
    wb = np.minimum(np.abs(np.cos(alpha)), np.abs(np.sin(alpha)))
    use = (seg - 2 * margin >= 3.0) & (hi > lo).all(-1)
    lines = np.stack([L0, P_near, P_far, L_lo, L_hi], -2)  # (K, 4, 5, 3)

    cs, es = np.nonzero(use)
    bands = _bands(lo[cs, es], hi[cs, es], lines[cs, es], margin[cs, es], reach[cs, es], s_max[cs, es], max_pixels)
    out = [[] for _ in range(K)]
    for c, e, b in zip(cs.tolist(), es.tolist(), bands):
        if b is not None:
            out[c].append(dict(b, dxy=b["px"] - centre[c, e], kappa=kappa[c, e].tolist(), wa=float(wa[c, e]),
                               wb=float(wb[c, e])))
    return out
