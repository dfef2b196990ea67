"""Stage 4 and 6 of the checkerboard detector (`tiltfit.detect.chessboard`): sub-pixel refinement by point symmetry
(`refine_symmetric`, batched Levenberg–Marquardt over all corners) and completion of the corners the grid growth
missed, predicted by local homographies (`complete_corners`). Also used by the ChArUco detector.
"""
from __future__ import annotations

import functools
import math

import numpy as np
import torch

from tiltfit.detect.imaging import apply_homography, homography_dlt
from tiltfit.solve.batched import BatchedOptions, batched_levenberg_marquardt, normal_from_residuals
from tiltfit.target.layout import Target


def _keys(x: np.ndarray) -> np.ndarray:
    """Keys' cubic convolution kernel with a = −1/2 (reproduces quadratics: third-order accurate)."""
    ax = np.abs(x)
    return np.where(ax <= 1, (1.5 * ax - 2.5) * ax * ax + 1,
                    np.where(ax < 2, ((-0.5 * ax + 2.5) * ax - 4) * ax + 2, np.zeros_like(ax)))


def _dkeys(x: np.ndarray) -> np.ndarray:
    ax = np.abs(x)
    return np.sign(x) * np.where(ax <= 1, (4.5 * ax - 5) * ax,
                                 np.where(ax < 2, (-1.5 * ax + 5) * ax - 4, np.zeros_like(ax)))


def _shift_patches(patches: np.ndarray, frac: np.ndarray):
    """Cubic interpolant of (N, S, S) float32 patches at every pixel + frac (N, 2), and its x and y derivatives.

    Every sample p ± v (v integer) of one corner has the same fractional part, so interpolation is one
    separable 4-tap filter per corner. Entry [n, y, x] of the outputs holds the value at (x + 1 + fx,
    y + 1 + fy) in patch coordinates, for x, y in [0, S − 4] (views of `_shifted_rows`' outputs).
    """
    S = patches.shape[-1]
    return tuple(a[:, :, :S - 3] for a in _shifted_rows(patches, frac))


def _shifted_rows(patches: np.ndarray, frac: np.ndarray):
    """`_shift_patches`' three outputs with rows S long, (N, S − 3, S) each: entries [n, y, x] for x in [0, S − 4]
    are the interpolant's; the last three of each row are not (the passes run along the flattened patch, across the
    rows' ends, so that each tap is one long slice).

    The weights of both axes are computed at once, and the filters that share a pass run together (the x pass with
    the kernel and its derivative, the y pass of the first with both): the same products and sums, in the same
    order, as one filter at a time, float32 throughout (each rounded as torch rounds it: the same values). In
    numpy, on whole rows: at these sizes an operation costs more to launch than to compute.
    """
    taps = frac.T - np.arange(-1, 3, dtype=np.float32)[:, None, None]  # (4, 2, N): offsets of tap k along x, y
    w, dw = _keys(taps)[..., None], _dkeys(taps)[..., None]  # (4, 2, N, 1): weights of tap k
    N, S = patches.shape[0], patches.shape[-1]

    def taps_along(img, wk, step, n):  # img (N, l), wk (4, F, N, 1) -> (F, N, n): Σ_k wk[k] img[i + k step], i < n
        out = wk[0] * img[:, 0:n]
        term = np.empty_like(out)
        for k in range(1, 4):
            out += np.multiply(wk[k], img[:, k * step:k * step + n], out=term)
        return out

    tx = np.zeros((2, N, S * S), np.float32)  # the x pass, the last 3 entries (never read by a kept entry) zero
    tx[:, :, :S * S - 3] = taps_along(patches.reshape(N, S * S), np.concatenate([w[:, :1], dw[:, :1]], 1), 1,
                                      S * S - 3)
    n = (S - 3) * S
    v, dy = taps_along(tx[0], np.concatenate([w[:, 1:], dw[:, 1:]], 1), S, n).reshape(2, N, S - 3, S)
    return v, taps_along(tx[1], w[:, 1:], S, n).reshape(N, S - 3, S), dy


def _patches(gray: np.ndarray, c0: np.ndarray, P: int, presmooth: float, ks: int) -> torch.Tensor:
    """(N, S, S) float32 patches of half-size P around the integer pixels c0 (N, 2), edge pixels repeated beyond
    the image, smoothed by a Gaussian of `presmooth` px (support ks). float32: the patches, weights and normal
    equations (errors ~1e-5 px); the positions accumulate in float64."""
    H, W = gray.shape
    ys = np.clip(c0[:, 1, None] + np.arange(-P, P + 1)[None], 0, H - 1)
    xs = np.clip(c0[:, 0, None] + np.arange(-P, P + 1)[None], 0, W - 1)
    t = torch.from_numpy(gray[ys[:, :, None], xs[:, None, :]].astype(np.float32))[:, None]  # (N, 1, S, S)
    if presmooth > 0:
        import kornia

        taps = _gaussian_taps(2 * ks + 1, presmooth)
        t = kornia.filters.filter2d_separable(t, taps, taps, border_type="replicate")
    return t[:, 0]


@functools.lru_cache(maxsize=8)
def _gaussian_taps(size: int, sigma: float) -> torch.Tensor:
    """(1, size) float32 taps of the Gaussian kornia's `gaussian_blur2d` makes for a float32 image, made once: with
    `filter2d_separable` they give its result to the bit, without remaking the kernels at every call."""
    import kornia

    return kornia.filters.get_gaussian_kernel1d(size, torch.tensor([[sigma]], dtype=torch.float32))


class _Samples:
    """The cubic interpolant of N smoothed patches (N, S, S) and its x and y derivatives at p + v and p − v, for the
    half-disc offsets v (M, 2) (integers, |v| ≤ Rmax) and each corner's position p (in patch pixels).

    Every p ± v of a corner lies in the L × L box of shifted values around p (L = 2 Rmax + 1): while the boxes stay
    inside the patches (the corners have moved less than ~4 + the smoothing's support from their starts), the
    interpolant is computed on each box alone, from the (L + 3)² pixels it reads; the same products and sums as on
    the whole patch (the same bits), on about half of it. Else the whole patches, indices clamped.
    """

    def __init__(self, t: np.ndarray, off: np.ndarray, Rmax: int):
        self.t, self.off, self.Rmax = t, off, Rmax
        self.S, self.L = t.shape[-1], 2 * Rmax + 1
        L, S = self.L, self.S
        self.box = np.concatenate([(Rmax + off[:, 1]) * (L + 3) + (Rmax + off[:, 0]),  # in `_shifted_rows`' layout
                                   (Rmax - off[:, 1]) * (L + 3) + (Rmax - off[:, 0])])
        span = np.arange(L + 3)
        self.box_pixels = span[:, None] * S + span[None, :]  # a box's pixels, as flat offsets from its first

    def __call__(self, loc: np.ndarray, idx: np.ndarray):
        """(v, gx, gy), (k, 2M) each: at p + v (first M) and p − v (last M) of the patches idx (k,) at loc (k, 2)."""
        S, L, Rmax = self.S, self.L, self.Rmax
        base = np.floor(loc)
        frac = (loc - base).astype(np.float32)
        # shifted entry [y, x] is the interpolant at (x + 1 + fx, y + 1 + fy): p + v sits at base + v − 1
        with np.errstate(invalid="ignore"):  # a non-finite trial point: its indices are clamped below
            b = base.astype(np.int64) - 1
        k = idx.size
        first = b - Rmax  # (k, 2) the box's first column and row in the patch
        if _box_fits(first, S, L):
            start = idx * (S * S) + first[:, 1] * S + first[:, 0]
            window = np.take(self.t, start[:, None, None] + self.box_pixels)
            return tuple(np.take(s.reshape(k, -1), self.box, axis=1) for s in _shifted_rows(window, frac))
        v, gx, gy = _shift_patches(self.t[idx], frac)  # a corner far from its start: the whole patch
        Sr, off = S - 3, self.off
        ip = (b[:, None, 1] + off[None, :, 1]) * Sr + (b[:, None, 0] + off[None, :, 0])
        im = (b[:, None, 1] - off[None, :, 1]) * Sr + (b[:, None, 0] - off[None, :, 0])
        ix = np.clip(np.concatenate([ip, im], 1), 0, Sr * Sr - 1)
        return tuple(np.take_along_axis(s.reshape(k, -1), ix, 1) for s in (v, gx, gy))


def _box_fits(first: np.ndarray, S: int, L: int) -> bool:
    """Whether every corner's L × L box of shifted values, from `first` ((k, 2) column and row in its patch), reads
    only its S × S patch ((L + 3)² pixels from `first`)."""
    return bool(((first >= 0) & (first <= S - L - 3)).all())


def _asymmetry(v: torch.Tensor, wgt: torch.Tensor) -> torch.Tensor:
    """(N,) weighted RMS of I(p + v) − I(p − v) over that of I − mean, from the values v (N, 2M) at p + v (first
    M) and p − v (last M) and the weights wgt (N, M): 0 for a perfect X-junction."""
    M = wgt.shape[1]
    r = v[:, :M] - v[:, M:]
    wt2 = torch.cat([wgt, wgt], 1)
    mean = (v * wt2).sum(1, keepdim=True) / wt2.sum(1, keepdim=True)
    return torch.sqrt((wgt * r * r).sum(1) / ((wt2 * (v - mean) ** 2).sum(1) + 1e-30))


def refine_symmetric(gray: np.ndarray, xy: np.ndarray, radius: np.ndarray, iterations: int = 20,
                     presmooth: float = 1.4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Point-symmetry refinement of corners at full resolution.

    Minimises Σ_v w(v) [I(p + v) − I(p − v)]² over p (`tiltfit.solve.batched_levenberg_marquardt`, all
    corners at once), v over a half-disc of `radius` (integer offsets, weights (1 − |v|²/R²)²). I is the patch smoothed by a Gaussian of `presmooth` px
    (symmetric, so the optimum is unchanged; it damps the aliasing of sharp edges) and interpolated with
    Keys' cubic (a = −1/2), whose exact derivative gives the Jacobian. On synthetic disc-blurred corners
    the bias is under 0.015 px for blur ≥ 1 px and under 0.035 px for perfectly sharp edges.

    Args:
        gray: (H, W) linear image.
        xy: (N, 2) initial positions, pixels.
        radius: (N,) window radii, pixels (clipped so the window stays inside the image; < 2 fails).
    Returns:
        xy (N, 2), asymmetry (N,) = weighted RMS of I(p+v) − I(p−v) over that of I − mean (0 for a perfect
        X-junction), ok (N,) bool.
    """
    H, W = gray.shape
    N = xy.shape[0]
    if N == 0:
        return xy.copy(), np.zeros(0), np.zeros(0, bool)
    xy = xy.astype(np.float64).copy()
    ks = int(math.ceil(3 * presmooth)) if presmooth > 0 else 0
    border = np.minimum.reduce([xy[:, 0], W - 1 - xy[:, 0], xy[:, 1], H - 1 - xy[:, 1]]) - 4.0 - ks
    R = np.minimum(radius, border)
    ok = R >= 2.0
    R = np.maximum(R, 2.0)
    Rmax = int(math.ceil(R.max()))
    P = Rmax + 4 + ks  # patch half-size: window + room to move + cubic support + smoothing support
    S = 2 * P + 1
    oy, ox = np.mgrid[0:Rmax + 1, -Rmax:Rmax + 1]
    half = (oy > 0) | ((oy == 0) & (ox > 0))
    off = np.stack([ox[half], oy[half]], -1).astype(np.int64)  # (M, 2) half-disc offsets
    rr = np.hypot(off[:, 0], off[:, 1])
    c0 = np.round(xy).astype(int)
    c0[:, 0] = np.clip(c0[:, 0], 0, W - 1)
    c0[:, 1] = np.clip(c0[:, 1], 0, H - 1)
    t = _patches(gray, c0, P, presmooth, ks).numpy()
    wgt = (torch.clamp(1 - (torch.from_numpy(rr)[None] / torch.from_numpy(R)[:, None]) ** 2, min=0.0) ** 2).float()
    loc = torch.from_numpy(xy - c0 + P)
    M = off.shape[0]
    samples = _Samples(t, off, Rmax)

    def residuals(loc, idx, with_jacobian=True):
        """Values at p ± v of the patches idx (k, 2M) and, with_jacobian, the derivatives of
        I(p + v) − I(p − v) by p (k, M, 2); torch tensors (loc, idx: torch, as the solver passes them)."""
        vv, gxx, gyy = samples(loc.numpy(), idx.numpy())
        # C order, as torch lays out its own results: its sums over other layouts add in another order
        vv = torch.from_numpy(np.ascontiguousarray(vv))
        if not with_jacobian:
            return vv, None
        J = np.stack([gxx[:, :M] - gxx[:, M:], gyy[:, :M] - gyy[:, M:]], -1)  # (k, M, 2)
        return vv, torch.from_numpy(np.ascontiguousarray(J))

    # each corner's samples at its cheapest point so far: where the solver ends (it moves only to lower the cost)
    best_cost, best_loc, best_vv = np.full(N, np.inf), np.full((N, 2), np.nan), np.empty((N, 2 * M), np.float32)

    def evaluate(loc, idx):
        vv, J = residuals(loc, idx)
        normal = normal_from_residuals(vv[:, :M] - vv[:, M:], J, wgt[idx])
        cost = normal.cost.numpy()
        better = cost < best_cost[idx.numpy()]
        k = idx.numpy()[better]
        best_cost[k], best_loc[k], best_vv[k] = cost[better], loc.numpy()[better], vv.numpy()[better]
        return normal

    # Levenberg–Marquardt (Gauss–Newton's steps once the damping has fallen), steps capped at 1 px so a corner
    # cannot jump to a neighbouring junction; done when a corner moves by < 1e-4 px
    sol = batched_levenberg_marquardt(
        evaluate, loc, BatchedOptions(max_iterations=iterations, max_step=1.0),
        small_step=lambda step, x, idx: torch.linalg.vector_norm(step, dim=1) < 1e-4)
    loc = sol.x
    at_end = torch.from_numpy(best_vv) if np.array_equal(best_loc, loc.numpy()) else \
        residuals(loc, torch.arange(N), with_jacobian=False)[0]
    asym = _asymmetry(at_end, wgt)
    out = loc.numpy() + c0 - P
    moved = np.hypot(*(out - xy).T)
    ok &= np.isfinite(out).all(1) & (moved < np.maximum(2.0, 1.2 * R))
    return out, asym.numpy(), ok


def complete_corners(gray: np.ndarray, target: Target, corners: np.ndarray, refine_radius_max: float = 20.0,
                     rounds: int = 2, max_asymmetry: float = 0.35, window: float = 0.4) -> int:
    """Look for the target's corners that the grid growth missed, where the found ones predict them.

    Once the corners are indexed, a local homography (target plane -> image) from found corners within two
    indices predicts each missing one; it is refined like the others and kept when it is a clean point-
    symmetric X-junction near the prediction. Recovers corners whose coarse saddle was too weak (very
    heavy blur, the board's outer ring). `window` is the refinement window's radius in squares (0.4; a
    ChArUco board's markers ask for less). Modifies `corners` in place; returns the number added.
    """
    H, W = gray.shape
    ny, nx = target.grid_shape
    pts = target.feature_points()[:, :2]
    xe, ye = target.x_edges, target.y_edges
    added = 0
    for _ in range(rounds):
        found = np.isfinite(corners).all(1)
        if found.all() or found.sum() < 4:
            break
        # only corners within two indices of a found one can be predicted: the work grows with the corners
        # seen, not with the size of the target
        grid = np.pad(found.reshape(ny, nx), 2)
        near_found = np.zeros((ny, nx), bool)
        for dj in range(5):
            for di in range(5):
                near_found |= grid[dj:dj + ny, di:di + nx]
        missing = np.nonzero(~found & near_found.ravel())[0]
        cand, pred, spacing = [], [], []
        for k in missing:
            j, i = divmod(int(k), nx)
            near = [jj * nx + ii for jj in range(max(0, j - 2), min(ny, j + 3))
                    for ii in range(max(0, i - 2), min(nx, i + 3)) if found[jj * nx + ii]]
            if len(near) < 4 or np.linalg.matrix_rank(pts[near] - pts[near].mean(0)) < 2:
                continue
            Hm = homography_dlt(pts[near], corners[near])
            if Hm is None or not np.isfinite(Hm).all():
                continue
            q = apply_homography(Hm, np.array([[xe[i + 1], ye[j + 1]], [xe[i], ye[j + 1]], [xe[i + 2], ye[j + 1]],
                                     [xe[i + 1], ye[j]], [xe[i + 1], ye[j + 2]]]))
            sp = float(np.min(np.hypot(*(q[1:] - q[0]).T)))
            if not (3 <= q[0, 0] <= W - 4 and 3 <= q[0, 1] <= H - 4) or sp < 6:
                continue
            cand.append(int(k))
            pred.append(q[0])
            spacing.append(sp)
        if not cand:
            break
        pred, spacing = np.array(pred), np.array(spacing)
        # coarse to fine: under strong lens distortion a local homography misses by up to ~0.1 of a square,
        # beyond the reach of the final window when squares are large; a first pass with a window of half
        # the square pulls the start in, the second uses the usual window
        start, _, ok0 = refine_symmetric(gray, pred, np.clip(1.125 * window * spacing, 3.0, 2.5 * refine_radius_max))
        start = np.where(ok0[:, None] & (np.hypot(*(start - pred).T) < 0.25 * spacing)[:, None], start, pred)
        xy, asym, ok = refine_symmetric(gray, start, np.clip(window * spacing, 3.0, refine_radius_max))
        keep = ok & (asym < max_asymmetry) & (np.hypot(*(xy - pred).T) < 0.25 * spacing)
        corners[np.array(cand)[keep]] = xy[keep]
        added += int(keep.sum())
        if not keep.any():
            break
    return added
