"""Corners of a ChArUco board under blur that reaches the markers' data bits: each corner fitted by the board's own
picture around it, bits included, through the local homography with an affine correction, convolved with a disc
whose diameter is fitted too (`refine_model`). Step 5 of `tiltfit.detect.charuco`.
"""
from __future__ import annotations

import functools
import math

import numpy as np
import torch

from tiltfit.detect.charuco_lattice import _local_square_px
from tiltfit.target.layout import CharucoTarget
from tiltfit.target.raster import rasterise


# Points per pixel side where `refine_model` looks the board's picture up before blurring it.
SUPERSAMPLE = 3


def _disc_kernel(r: float) -> np.ndarray:
    """Normalised kernel of a disc of radius r (in taps), each tap weighted by its area inside (4 × 4 points)."""
    k = int(math.ceil(r)) + 1
    o = (np.arange(4) + 0.5) / 4 - 0.5
    d2 = (np.arange(-k, k + 1)[None] + o[:, None]) ** 2  # (4, taps): squared offsets of the points along an axis
    ker = (d2[None, :, :, None] + d2[:, None, None, :] <= r * r).sum((0, 1)).astype(np.float32)
    return ker / ker.sum()


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


def _fft_length(n: int) -> int:
    """The least multiple of SUPERSAMPLE >= n whose other factors are 2s and 3s: a fast transform that folds evenly."""
    L = -(-n // SUPERSAMPLE) * SUPERSAMPLE
    while True:
        m = L // SUPERSAMPLE
        for p in (2, 3):
            while m % p == 0:
                m //= p
        if m == 1:
            return L
        L += SUPERSAMPLE


@functools.lru_cache(maxsize=64)
def _cosines(L: int, taps: int, real: bool) -> torch.Tensor:
    """cos(ω t) at the angular frequencies ω of a length-L transform (its first L // 2 + 1 for `real`'s rfft)
    and t = 0..taps − 1: (frequencies, taps)."""
    w = 2 * np.pi * (np.fft.rfftfreq(L) if real else np.fft.fftfreq(L))
    return torch.from_numpy(np.cos(w[:, None] * np.arange(taps)).astype(np.float32))


def _disc_spectrum(r: float, L1: int, L2: int) -> torch.Tensor:
    """Fourier transform of `_disc_kernel(r)` at the frequencies of rfft2 over (L1, L2): real, the kernel being even
    along both axes, Σ ker(y, x) cos(ω1 y) cos(ω2 x) summed over a quadrant (weights 2 off the axes)."""
    ker = _disc_kernel(r)
    k = ker.shape[0] // 2
    twice = np.where(np.arange(k + 1) > 0, 2.0, 1.0).astype(np.float32)
    quadrant = torch.from_numpy(ker[k:, k:] * twice[:, None] * twice[None])
    # torch's product (one thread in `refine_model`), not numpy's: numpy's OpenBLAS spreads even these small
    # products over threads that wait for each other (tens of times the CPU time on a loaded machine)
    return _cosines(L1, k + 1, False) @ quadrant @ _cosines(L2, k + 1, True).T


@functools.lru_cache(maxsize=64)
def _patch_factors(L1: int, L2: int):
    """Factors over rfft2's frequencies of an (L1, L2) supersampled picture (complex tensors): the mean of
    SUPERSAMPLE taps (a pixel's box average, anchored at its first tap), and the central differences along rows
    (ω1, (S, L1 // S, 1): grouped as folded) and columns (ω2, (1, L2 // 2 + 1)), in pixels (SUPERSAMPLE taps a
    pixel)."""
    S = SUPERSAMPLE
    w1 = 2 * np.pi * np.fft.fftfreq(L1)[:, None]
    w2 = 2 * np.pi * np.fft.rfftfreq(L2)[None, :]
    taps = np.arange(S)
    box = np.exp(1j * w1 * taps).mean(1, keepdims=True) * np.exp(1j * w2.T * taps).mean(1)[None]
    d_rows, d_cols = (1j * S * np.sin(w1)).reshape(S, L1 // S, 1), 1j * S * np.sin(w2)
    return tuple(torch.from_numpy(a.astype(np.complex64)) for a in (box, d_rows, d_cols))


@functools.lru_cache(maxsize=64)
def _column_fold(N1: int, L2: int):
    """Where `_render_patch` reads the columns' folded frequencies v' = 0..N2 // 2 (N2 = L2 / SUPERSAMPLE) from an
    rfft layout with N1 rows (tensors): (cols (N2 // 2 + 1, S) into the stored half, mirrored (same shape, bool):
    the frequency v' + s N2 lies past the half and is the conjugate of column L2 − (v' + s N2) at the rows
    (−u) mod N1, those rows)."""
    N2 = L2 // SUPERSAMPLE
    j = np.arange(N2 // 2 + 1)[:, None] + N2 * np.arange(SUPERSAMPLE)[None]
    mirrored = j > L2 // 2
    return (torch.from_numpy(np.where(mirrored, L2 - j, j)), torch.from_numpy(mirrored),
            torch.from_numpy((-np.arange(N1)) % N1))


def _render_patch(tex, origin, ppm, Hm, r0, c0, h, w, radius_px, d_radius=None):
    """Model of pixels rows r0..r0+h−1, columns c0..c0+w−1: the board's dark fraction through homography Hm
    (mm → px), looked up at SUPERSAMPLE² points a pixel, convolved with a disc of `radius_px` there and
    box-averaged; its derivatives along x and y (per pixel: the central differences of the supersampled picture,
    box-averaged); and, given `d_radius`, the same picture under a disc of radius_px + d_radius.

    The supersampled picture extends at least `pad` pixels beyond the patch, more than the disc's reach, so
    neither a border rule nor the transforms' wrap-around enters the patch, and the convolutions are products of
    discrete Fourier transforms (the picture sampled to a fast length): the picture is transformed once, each
    disc in closed form (`_disc_spectrum`), the box average and the central differences are factors
    (`_patch_factors`), and the samples a pixel apart are read from the transforms folded SUPERSAMPLE-fold along
    both axes, so no supersampled picture is transformed back. float32 transforms (as the direct convolution
    was): the values within 1e-6 of float64 ones, the fitted corners within 1e-4 px."""
    import cv2

    S = SUPERSAMPLE
    pad = int(math.ceil(radius_px + (d_radius or 0.0))) + 2  # pixels beyond the patch so that its blur is whole
    L1, L2 = _fft_length((h + 2 * pad) * S), _fft_length((w + 2 * pad) * S)
    N1, N2 = L1 // S, L2 // S
    sub = (np.arange(S) + 0.5) / S - 0.5
    v = (np.arange(r0 - pad, r0 - pad + N1)[:, None] + sub[None]).ravel()
    u = (np.arange(c0 - pad, c0 - pad + N2)[:, None] + sub[None]).ravel()
    Hi = np.linalg.inv(Hm)
    px, py, pw = (Hi[i, 0] * u[None] + Hi[i, 1] * v[:, None] + Hi[i, 2] for i in range(3))  # board mm, homogeneous
    mx = ((px / pw - origin[0]) * ppm - 0.5).astype(np.float32)
    my = ((py / pw - origin[1]) * ppm - 0.5).astype(np.float32)
    sharp = cv2.remap(tex, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    box, d_rows, d_cols = _patch_factors(L1, L2)
    F = (torch.fft.rfft2(torch.from_numpy(sharp)) * box).reshape(S, N1, -1)

    def disc(r):
        return _disc_spectrum(r, L1, L2).reshape(S, N1, -1) if r > 0.5 else 1.0

    # folding the rows' frequencies S-fold (their mean) keeps every S-th row; a factor along the columns can wait
    B = F * disc(radius_px * S)
    B_rows = B.mean(0)
    folded = [B_rows, B_rows * d_cols, (B * d_rows).mean(0)]
    if d_radius is not None:
        folded.append((F * disc((radius_px + d_radius) * S)).mean(0))
    folded = torch.stack(folded)
    cols, mirrored, neg_rows = _column_fold(N1, L2)
    both = torch.where(mirrored, folded[:, neg_rows][..., cols].conj(), folded[..., cols]).mean(-1)
    return list(torch.fft.irfft2(both, s=(N1, N2))[:, pad:pad + h, pad:pad + w].double().numpy())


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
    from tiltfit.detect.imaging import torch_threads

    with torch_threads(1):
        return _refine_model(gray, target, corners, blur_px, texture)


def _refine_model(gray, target, corners, blur_px, texture):
    from tiltfit.detect.blur import _local_homographies
    from tiltfit.detect.imaging import estimate_noise

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


def _model_window(gray, target, Hm, P, radius):
    """The pixels `_fit_corner` fits: ((r0, c0, h, w) the bounding box, use (h, w) bool the pixels whose board
    position lies within MODEL_WINDOW square of the corner P (mm) and which the blur disc of `radius` px does not
    carry past the image's edge, y (n,) their values, p (n, 2) their positions, px), or None when too few."""
    H_img, W_img = gray.shape
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
    return (r0, c0, h, w), use, gray[r0:r0 + h, c0:c0 + w][use].astype(np.float64), np.stack([xx[use], yy[use]], 1)


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
    window = _model_window(gray, target, Hm, P, radius)
    if window is None:
        return None
    (r0, c0, h, w), use, y, p = window
    q = Hm @ np.array([P[0], P[1], 1.0])
    c = q[:2] / q[2]
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
