"""Stage 2 of the checkerboard detector (`tiltfit.detect.chessboard`): saddle candidates of a pyramid level.

Candidates are the local minima of the Hessian determinant det H = Ixx Iyy − Ixy² of the Gaussian-smoothed image
(kornia), below a threshold set from the measured noise, where the saddle is well formed and the gradient small;
the two zero directions of vᵀHv are the edges through the corner (`edge_directions`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from tiltfit.detect.imaging import estimate_noise


@dataclass
class SaddleMap:
    """Hessian fields of the smoothed level image and its candidates.

    Attributes:
        smooth: (H, W) smoothed image; dxx, dxy, dyy: (H, W) second derivatives; det: (H, W) det H.
        xy: (M, 2) candidate positions (level pixels), strength: (M,) −det H, edges: (M, 2, 2) unit
            vectors along the two edges through each candidate.
        threshold: −det H above which a local minimum is a candidate.
    """

    smooth: np.ndarray
    dxx: np.ndarray
    dxy: np.ndarray
    dyy: np.ndarray
    det: np.ndarray
    xy: np.ndarray
    strength: np.ndarray
    edges: np.ndarray
    threshold: float


_NOISE_GAIN: dict[float, float] = {}


def _hessian(img_t: torch.Tensor, sigma: float):
    k = 2 * int(math.ceil(3 * sigma)) + 1
    import kornia

    sm = kornia.filters.gaussian_blur2d(img_t, (k, k), (sigma, sigma), border_type="replicate")
    g = kornia.filters.spatial_gradient(sm, mode="diff", order=2, normalized=False)  # (B, C, 3, H, W)
    return sm, g[:, 0, 0], g[:, 0, 1], g[:, 0, 2]


def _det_noise_gain(sigma: float) -> float:
    """Standard deviation of Ixy for unit white noise after smoothing with `sigma` (measured once)."""
    if sigma not in _NOISE_GAIN:
        gen = torch.Generator().manual_seed(1)
        n = torch.randn(1, 1, 96, 96, generator=gen, dtype=torch.float32)
        _, dxx, dxy, dyy = _hessian(n, sigma)
        c = slice(16, -16)
        _NOISE_GAIN[sigma] = float(torch.stack([dxx[0, c, c].std(), 2 * dxy[0, c, c].std(), dyy[0, c, c].std()]).max())
    return _NOISE_GAIN[sigma]


def saddle_map(img: np.ndarray, sigma: float = 1.0, noise: float | None = None, k_noise: float = 6.0,
               min_quality: float = 0.3, max_candidates: int = 4000) -> SaddleMap:
    """Saddle candidates of a level image: local minima of det H (5×5) with −det H > (k σ_H)²."""
    t = torch.from_numpy(np.ascontiguousarray(img))[None, None]
    sm, dxx, dxy, dyy = _hessian(t, sigma)
    det = dxx * dyy - dxy * dxy
    noise = estimate_noise(img) if noise is None else noise
    sd_h = max(noise, 1e-4) * _det_noise_gain(sigma)
    neg = -det
    # noise-based, and at least 1e-3 of the strongest saddle (blur varies across a tilted-lens image, but a
    # corner's response falls as (blur)^-4 only down to the smoothing scale)
    thr = max((k_noise * sd_h) ** 2, 1e-3 * float(neg.max()))
    pooled = F.max_pool2d(neg[None], 5, stride=1, padding=2)[0]
    # saddle quality: −det / (½(Ixx² + Iyy²) + Ixy²) is 1 where the edges cross at right angles, about 0.5 for
    # edges at 45°, and near 0 or below on straight edges, in blobs and on noise riding on either
    quality = neg / (0.5 * (dxx * dxx + dyy * dyy) + dxy * dxy + 1e-30)
    # a saddle's centre is flat: |∇I| ≤ |H| δ within δ ≈ 1 px of it, while a point on an edge is steep
    import kornia

    grad = kornia.filters.spatial_gradient(sm, mode="diff", order=1, normalized=False)[:, 0]
    flat = torch.sqrt(grad[:, 0] ** 2 + grad[:, 1] ** 2) < 1.5 * torch.sqrt(neg.clamp_min(0))
    is_min = (neg == pooled) & (neg > thr) & (quality > min_quality) & flat
    # ignore the outermost pixels, where the smoothing saw the replicated border
    b = int(math.ceil(2 * sigma)) + 1
    is_min[:, :b] = False
    is_min[:, -b:] = False
    is_min[:, :, :b] = False
    is_min[:, :, -b:] = False
    ys, xs = torch.nonzero(is_min[0], as_tuple=True)
    s = neg[0, ys, xs]
    if s.numel() > max_candidates:
        keep = torch.topk(s, max_candidates).indices
        ys, xs, s = ys[keep], xs[keep], s[keep]
    dxx_n, dxy_n, dyy_n, det_n = (a[0].numpy() for a in (dxx, dxy, dyy, det))
    xy = np.stack([xs.numpy(), ys.numpy()], -1).astype(np.float64)
    xy = xy + _quadratic_peak(det_n, xs.numpy(), ys.numpy())
    edges = edge_directions(dxx_n[ys, xs], dxy_n[ys, xs], dyy_n[ys, xs])
    return SaddleMap(sm[0, 0].numpy(), dxx_n, dxy_n, dyy_n, det_n, xy, s.numpy().astype(np.float64), edges, thr)


def _quadratic_peak(f: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Sub-pixel offset (M, 2) of an extremum from a separable 3-point parabola fit, clipped to ±0.5."""
    h, w = f.shape
    xs, ys = np.clip(xs, 1, w - 2), np.clip(ys, 1, h - 2)
    c = f[ys, xs]
    dx = f[ys, xs + 1] - f[ys, xs - 1]
    dy = f[ys + 1, xs] - f[ys - 1, xs]
    cxx = f[ys, xs + 1] + f[ys, xs - 1] - 2 * c
    cyy = f[ys + 1, xs] + f[ys - 1, xs] - 2 * c
    ox = np.where(np.abs(cxx) > 1e-20, -0.5 * dx / np.where(np.abs(cxx) > 1e-20, cxx, 1.0), 0.0)
    oy = np.where(np.abs(cyy) > 1e-20, -0.5 * dy / np.where(np.abs(cyy) > 1e-20, cyy, 1.0), 0.0)
    return np.clip(np.stack([ox, oy], -1), -0.5, 0.5)


def edge_directions(hxx, hxy, hyy) -> np.ndarray:
    """(M, 2, 2): the two unit directions v with vᵀ H v = 0 (the edges through a saddle)."""
    # eigenvector of the negative eigenvalue at angle a; edges at a ± atan(sqrt(−λ1/λ2))
    tr, det = hxx + hyy, hxx * hyy - hxy * hxy
    disc = np.sqrt(np.maximum(0.25 * tr * tr - det, 0.0))
    l1, l2 = 0.5 * tr - disc, 0.5 * tr + disc
    a = 0.5 * np.arctan2(2 * hxy, hxx - hyy)  # angle of the eigenvector of the larger eigenvalue
    a_neg = a + 0.5 * np.pi
    half = np.arctan(np.sqrt(np.clip(-l1, 0, None) / np.maximum(l2, 1e-30)))
    th1, th2 = a_neg + half, a_neg - half
    return np.stack([np.stack([np.cos(th1), np.sin(th1)], -1), np.stack([np.cos(th2), np.sin(th2)], -1)], -2)
