"""Blur-disc diameter at each feature point, from the edges that meet there (paper (2), (4)).

A lens focused elsewhere spreads a point into a uniform disc of diameter b (per-axis standard deviation
b/4). Across a straight edge the image is then the edge spread function
    F(s) = 1/2 + (u √(1 − u²) + asin u)/π,   u = clip(s / r, −1, 1),   r = b / 2,
the area of the disc segment beyond the edge, and each pixel integrates F over its square: projected on
the edge normal n = (cos α, sin α) the square is a box of width |cos α| convolved with one of width
|sin α|, so the pixel value is a second difference of the double antiderivative of F (`pixel_esf`, exact).

For each feature point, pixels of a band along each of the (up to four) edges leaving it — the half of the
edge nearest the point, away from it by more than the blur radius so the crossing edge does not reach them
— are fitted with the profile of the cells the band crosses: the two cells on either side of the edge and
the next cell beyond each (their edges, placed by a local homography of the detected corners, share the
blur), so blur nearly as wide as a square is modelled. The blur varies over the neighbourhood as
b(x) = |β + g · (x − p)|, linear through zero if need be (the signed form of the paper's (4) is linear in
position to first order), so a point on the plane of focus is measured sharp although its edges, away from
it, are not. Free per point: β and g; per band: dark level, contrast and edge offset (Levenberg–Marquardt,
batched over points). The reported b is |β| with its standard error.

Fits run on the 2×2 box pyramid level where the blur is a few pixels (a level pixel is exactly the box
integral of f × f pixels, so the model holds there with b / f): a first pass where squares are 24–48 px
finds the blur, the next passes refit on bands cut for it.

Intensities must be linear: an sRGB-encoded image bends the profile and biases b (see the tests).
"""
from __future__ import annotations

import math

import numpy as np
import torch

from tiltfit.detect.blur_bands import _half_edges, _local_homographies
from tiltfit.detect.imaging import apply_homography, build_pyramid, torch_threads
from tiltfit.solve.batched import BatchedOptions, Normal, batched_levenberg_marquardt
from tiltfit.target.layout import Target

# The band model is evaluated in float64: Levenberg–Marquardt takes a step when the cost falls, and near the
# minimum the fall is below a float32 model's rounding, so where a float32 fit stopped depended on its path
# (a corner moved by 1e-6 px moved a first-pass width by 2e-3 px, and final widths by many σ through the passes
# that follow, whose bands are cut for the width found); in float64 the same first pass moves by 2e-6 px
_MODEL_DTYPE = torch.float64



def _G(u: torch.Tensor) -> torch.Tensor:
    """G(u) = ∫_{−1}^{u} F: antiderivative of the disc edge spread function (radius units); G(u ≥ 1) = u."""
    return _G_and_G2(u, with_G=True)[0]


def _G2(u: torch.Tensor) -> torch.Tensor:
    """G2(u) = ∫_{−1}^{u} G, closed form; G2(u ≥ 1) = 5/8 + (u² − 1)/2."""
    return _G_and_G2(u, with_G=False)[1]


def _G_and_G2(u: torch.Tensor, with_G: bool = True):
    """(G(u) or None, G2(u)), sharing the square root and arcsine (the costly part of the pixel ESF)."""
    uc = u.clamp(-1.0, 1.0)
    q = uc * uc
    # floored: the square root of exact zeros (every |u| >= 1) is slow on some CPUs' vector units, and
    # √1e-30 = 1e-15 changes G and G2 by far less than the image's noise
    s2 = (1 - q).clamp_min_(1e-30)  # s², reused below for s * s
    s = torch.sqrt(s2)
    a = torch.asin(uc)
    over = (u - 1).clamp_min_(0.0)
    inner = (0.25 * q + 1.0 / 16 + (a * (0.5 * q + 0.125) + uc * s * (0.625 - s2 / 12)) / math.pi)
    G2 = inner + over * (1 + 0.5 * over)  # (u² − 1)/2 = over + over²/2 for u = 1 + over
    if not with_G:
        return None, G2
    G = 0.5 * uc + (uc * a + s * (1 - s2 / 3.0)) / math.pi + over
    return G, G2


def pixel_esf(d: torch.Tensor, r: torch.Tensor, wa: torch.Tensor, wb: torch.Tensor, with_derivatives: bool = False):
    """Disc edge spread function integrated exactly over a pixel.

    The pixel square projected on the edge normal is a box of width wa convolved with one of width wb
    (wa ≥ wb: |cos α|, |sin α|); integrating F over both is a second difference of G2:
        E(d) = r² [G2(u₁) − G2(u₂) − G2(u₃) + G2(u₄)] / (wa wb),   u = (d ± (wa ± wb)/2) / r.

    Args:
        d: (...) signed distance of pixel centres from the edge, pixels (positive on the far side).
        r: blur-disc radius b/2, pixels (broadcast); wa, wb: projected pixel widths (broadcast).
    Returns:
        E (...) in [0, 1]; with_derivatives: also ∂E/∂d and ∂E/∂r.
    """
    r = r.clamp_min(1e-3)
    wb = wb.clamp_min(0.02)  # an axis-aligned edge: a box of 0.02 px changes E by < 1e-4
    reach = r + 0.5 * (wa + wb) + 1e-3
    d = torch.maximum(torch.minimum(d, reach), -reach)  # E is exactly 0 or 1 beyond; keeps G2 small
    hp, hm = 0.5 * (wa + wb), 0.5 * (wa - wb)
    # the four abscissae lead (not trail), so the second differences are plain sums of whole arrays
    u = torch.stack(torch.broadcast_tensors(d + hp, d + hm, d - hm, d - hp)) / r
    norm = r * r / (wa * wb)
    G, G2 = _G_and_G2(u, with_G=with_derivatives)
    G2u = (G2[0] + G2[3]) - (G2[1] + G2[2])
    E = G2u * norm
    if not with_derivatives:
        return E
    uG = u * G
    dE_dd = ((G[0] + G[3]) - (G[1] + G[2])) * norm / r
    dE_dr = (2 * G2u - ((uG[0] + uG[3]) - (uG[1] + uG[2]))) * norm / r
    return E, dE_dd, dE_dr


def _pixel_esf_on_edges(d: torch.Tensor, r: torch.Tensor, wa: torch.Tensor, wb: torch.Tensor, deriv: bool):
    """`pixel_esf` evaluated only at the pixels the blurred edge reaches; elsewhere E is exactly 0 or 1.

    Most pixels of a band lie inside the cells, beyond the blur disc and the pixel's own width from the
    edge (|d| >= r + (wa + wb)/2), where E is 1 (d > 0) or 0 with zero derivatives: the closed form is
    evaluated on the rest only (typically 5–15 % of a band).

    Args:
        d, r: (..., n) distances and radii, pixels; wa, wb: (..., 1) projected pixel widths per band.
    Returns:
        E, ∂E/∂d, ∂E/∂r (..., n); the derivatives None without deriv.
    """
    E = (d > 0).to(d.dtype)
    E_d = torch.zeros_like(d) if deriv else None
    E_r = torch.zeros_like(d) if deriv else None
    sel = d.abs() < r + (0.5 * (wa + wb.clamp_min(0.02)) + 1e-3)
    at = sel.reshape(-1).nonzero().squeeze(1)
    if at.numel() == 0:
        return E, E_d, E_r
    band = at // d.shape[-1]
    out = pixel_esf(d.reshape(-1)[at], r.reshape(-1)[at], wa.reshape(-1)[band], wb.reshape(-1)[band], deriv)
    for full, part in zip((E, E_d, E_r), out if deriv else (out,)):
        full.view(-1).index_copy_(0, at, part)
    return E, E_d, E_r


def _pack_bands(img: np.ndarray, groups: list[list[dict]]):
    """The bands of C points padded into tensors (B bands a point at most, n pixels a band at most): mask (the
    square root of the pixel's weight, so that residuals and Jacobian rows times mask weight the squares), values,
    d0, d_lo, d_hi (C, B, n), dxy (C, B, n, 2), kappa (C, B, 4), wa, wb (C, B, 1); padding has mask 0 and its far
    lines out of reach. float64 for the mask, values and far lines, `_MODEL_DTYPE` for the model's geometry."""
    C = len(groups)
    B = max(len(g) for g in groups)
    n = max(len(b["d0"]) for g in groups for b in g)
    mask = np.zeros((C, B, n))
    vals = np.zeros((C, B, n))
    d0 = np.zeros((C, B, n))
    dlo = np.full((C, B, n), 1e6)
    dhi = np.full((C, B, n), -1e6)
    dxy = np.zeros((C, B, n, 2))
    kap = np.ones((C, B, 4))
    wa = np.ones((C, B))
    wb = np.zeros((C, B))
    for c, g in enumerate(groups):
        for e, b in enumerate(g):
            m = len(b["d0"])
            mask[c, e, :m] = np.sqrt(b["w"])
            vals[c, e, :m] = img[b["px"][:, 1], b["px"][:, 0]]
            d0[c, e, :m], dlo[c, e, :m], dhi[c, e, :m] = b["d0"], b["d_lo"], b["d_hi"]
            dxy[c, e, :m] = b["dxy"]
            kap[c, e], wa[c, e], wb[c, e] = b["kappa"], b["wa"], b["wb"]
    dt, t = _MODEL_DTYPE, torch.from_numpy
    return (t(mask), t(vals), t(d0.clip(-1e4, 1e4)).to(dt), t(dlo), t(dhi), t(dxy).to(dt), t(kap).to(dt),
            t(wa).to(dt)[..., None], t(wb).to(dt)[..., None])


def _normal_equations(Kt: torch.Tensor, res: torch.Tensor):
    """JᵀJ (k, P, P) and Jᵀ res (k, P), P = 3 + 3B, from the six non-zero Jacobian columns Kt (k, B, 6, n) per pixel
    of `fit_corners`' model (the point's β, gx, gy; the band's dark level, contrast, edge offset; zero on padding)
    and the residuals res (k, B, n)."""
    k, B = Kt.shape[:2]
    P = 3 + 3 * B
    M = Kt @ Kt.transpose(-1, -2)  # (k, B, 6, 6)
    v = (Kt @ res[..., None])[..., 0]  # (k, B, 6)
    A = torch.zeros(k, P, P, dtype=torch.float64)
    A[:, :3, :3] = M[:, :, :3, :3].sum(1)
    for e in range(B):
        sl = slice(3 + 3 * e, 6 + 3 * e)
        A[:, :3, sl] = M[:, e, :3, 3:]
        A[:, sl, :3] = M[:, e, 3:, :3]
        A[:, sl, sl] = M[:, e, 3:, 3:]
    return A, torch.cat([v[:, :, :3].sum(1), v[:, :, 3:].reshape(k, 3 * B)], 1)


def _start(model, I: torch.Tensor, mask: torch.Tensor, has_band: torch.Tensor, r0: torch.Tensor) -> torch.Tensor:
    """`fit_corners`' start (C, P): β scanned from 4 % to 200 % of 2 r0 (g = 0), the levels of each band solved
    linearly at each β (weighted by mask²), the β that leaves the least weighted squared residual kept.
    model(theta, idx, deriv) is the fit's."""
    C, B = mask.shape[:2]
    every = torch.arange(C)
    w = mask * mask
    npix = w.sum(-1)
    best = torch.full((C,), float("inf"), dtype=torch.float64)
    theta = torch.zeros(C, 3 + 3 * B, dtype=torch.float64)
    for frac in (0.05, 0.13, 0.3, 0.55, 1.0, 1.6):
        trial = torch.zeros(C, 3 + 3 * B, dtype=torch.float64)
        trial[:, 0] = (2 * r0 * frac).clamp_min(0.1)  # β is a diameter
        trial[:, 4::3] = 1.0
        gg = model(trial, every, deriv=False)[0]
        sg, sI = (w * gg).sum(-1), (w * I).sum(-1)
        sgg, sgI = (w * gg * gg).sum(-1), (w * gg * I).sum(-1)
        det = npix * sgg - sg * sg
        cc = (npix * sgI - sg * sI) / det.clamp_min(1e-30)
        oo = (sI - cc * sg) / npix.clamp_min(1e-9)
        cost = ((((I - oo[..., None] - cc[..., None] * gg) * mask) ** 2).sum((-1, -2)))
        better = cost < best
        trial[:, 3::3], trial[:, 4::3] = oo, torch.where(has_band, cc, torch.ones_like(cc))
        theta = torch.where(better[:, None], trial, theta)
        best = torch.where(better, cost, best)
    return theta


def _diameter_sigma(A: torch.Tensor, cost: torch.Tensor, npix: torch.Tensor, has_band: torch.Tensor,
                    contrast: torch.Tensor) -> torch.Tensor:
    """(C,) one-σ of the fitted diameter β: from the normal matrix A (C, P, P) (bands without pixels left out) and
    the residual variance per degree of freedom."""
    C, P = A.shape[:2]
    dof = (npix.sum(-1) - (3 + 3 * has_band.sum(-1))).clamp_min(1)
    # a floor of 0.1 % of the contrast keeps noise-free fits honest where b is not identifiable (a sharp
    # edge almost parallel to the pixel grid samples its profile at one phase only)
    s2 = torch.maximum(cost / dof, (1e-3 * contrast) ** 2)
    keep = torch.cat([torch.ones(C, 3, dtype=torch.bool), has_band.repeat_interleave(3, dim=1)], 1)
    A = torch.where(keep[:, :, None] & keep[:, None, :], A, torch.diag_embed(torch.ones(C, P, dtype=torch.float64)))
    # β's information with every other parameter free (the Schur complement of the rest); none left (β in the
    # null space: no pixel the blur reaches) gives σ = inf, not the 0 a pseudo-inverse would
    info = A[:, 0, 0] - (A[:, 0:1, 1:] @ torch.linalg.pinv(A[:, 1:, 1:]) @ A[:, 1:, 0:1])[:, 0, 0]
    determined = info > 1e-9 * A[:, 0, 0].clamp_min(1e-300)
    return torch.where(determined, torch.sqrt(s2 / torch.where(determined, info, 1.0)), math.inf)


def _small_step(step: torch.Tensor, th: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """`fit_corners` converged: the diameter moves by < 1e-4 of itself (+1e-4 px) and the gradient by < 1e-5 (a
    corner whose step is this small would hardly move again: < 0.01 σ of its blur on the shipped real photos)."""
    return (step[:, 0].abs() < 1e-4 * (th[:, 0].abs() + 1)) & (step[:, 1:3].abs().max(1).values < 1e-5)


class _BandModel:
    """`fit_corners`' model of the packed bands: values and Jacobian columns at the points idx.

    The solver asks for the same points for several iterations (until one of them stops), so the tensors of the
    points asked for are gathered once per set; the far lines do not move, so the pixels they may reach are
    listed once per set too, and only those are tested against the current blur.
    """

    def __init__(self, img: np.ndarray, groups: list[list[dict]], r_cap: torch.Tensor):
        dt = _MODEL_DTYPE  # the model's working precision
        self.mask, self.I, d0, dlo, dhi, dxy, kap, wa, wb = _pack_bands(img, groups)
        lim = (r_cap + 2.0)[:, None, None] + 0.0
        # far lines: only the entries within reach are evaluated, elsewhere the step is 0 or 1
        self._far = [((dlo.abs() < 1.3 * lim), dlo.to(dt)), ((dhi.abs() < 1.3 * lim), dhi.to(dt))]
        self._points = dict(I=self.I, mask=self.mask, m_model=self.mask.to(dt), d0=d0, dx=dxy[..., 0].contiguous(),
                            dy=dxy[..., 1].contiguous(), kap0=kap[..., 0:1], wa=wa, wb=wb,
                            c_lo=(kap[..., 1] - kap[..., 0])[..., None], c_0=(kap[..., 2] - kap[..., 1])[..., None],
                            c_hi=(kap[..., 3] - kap[..., 2])[..., None])
        self._idx, self._at = None, None

    def at(self, idx: torch.Tensor) -> dict:
        """The points' tensors gathered at idx (k,), kept until another set is asked for."""
        if self._idx is not None and idx.numel() == self._idx.numel() and torch.equal(idx, self._idx):
            return self._at
        g = {k: v[idx] for k, v in self._points.items()}
        n = g["d0"].shape[-1]
        reach = (0.5 * (g["wa"] + g["wb"].clamp_min(0.02)) + 1e-3).reshape(-1)  # per band, beyond the blur radius
        g["far"] = []
        for near, dist in self._far:
            d = dist[idx]
            px = near[idx].reshape(-1).nonzero().squeeze(1)  # the pixels this line may reach
            g["far"].append(((d > 0).to(d.dtype), px, d.reshape(-1)[px], px // n, reach[px // n]))
        self._idx, self._at = idx, g
        return g

    @staticmethod
    def _far_term(g: dict, line, r: torch.Tensor, deriv: bool):
        """E and ∂E/∂r (None without deriv) of a far line: the step, and `pixel_esf` where the blur reaches."""
        step, px, d, band, reach = line
        E = step.clone()
        E_r = torch.zeros_like(step) if deriv else None
        r_px = r.reshape(-1)[px]
        sel = (d.abs() < r_px + reach).nonzero().squeeze(1)
        if sel.numel() == 0:
            return E, E_r
        at, b = px[sel], band[sel]
        out = pixel_esf(d[sel], r_px[sel], g["wa"].reshape(-1)[b], g["wb"].reshape(-1)[b], deriv)
        E.view(-1).index_copy_(0, at, out[0] if deriv else out)
        if deriv:
            E_r.view(-1).index_copy_(0, at, out[2])
        return E, E_r

    def __call__(self, theta: torch.Tensor, idx: torch.Tensor, deriv: bool = True):
        """Model values f (k, B, n) at the points idx (k,) for parameters theta (k, P) and, with deriv, the six
        non-zero columns of the Jacobian per pixel (k, B, 6, n), float64, zero on padding: a pixel of band e depends
        on the point's (β, gx, gy) and on band e's (dark level, contrast, edge offset) only."""
        g = self.at(idx)
        th = theta.to(_MODEL_DTYPE)
        beta, gx, gy = th[:, 0], th[:, 1], th[:, 2]
        o, c, delta = th[:, 3::3], th[:, 4::3], th[:, 5::3]  # (k, B)
        sb = beta[:, None, None] + gx[:, None, None] * g["dx"] + gy[:, None, None] * g["dy"]
        r = (0.5 * sb.abs()).clamp_min(1e-3)
        e0, e0_d, e0_r = _pixel_esf_on_edges(g["d0"] - delta[..., None], r, g["wa"], g["wb"], deriv)
        (elo, elo_r), (ehi, ehi_r) = (self._far_term(g, line, r, deriv) for line in g["far"])
        cl, c0, ch = g["c_lo"], g["c_0"], g["c_hi"]
        gsum = g["kap0"] + cl * elo + c0 * e0 + ch * ehi
        f = o[..., None] + c[..., None] * gsum
        if not deriv:
            return f.double(), None
        m = g["m_model"]  # √weight, 0 on padding: the columns there are zeroed exactly
        dr = c[..., None] * (cl * elo_r + c0 * e0_r + ch * ehi_r) * 0.5 * torch.sign(sb) * m
        Kt = torch.empty(*m.shape[:2], 6, m.shape[-1], dtype=torch.float64)  # the rows, cast exactly once
        for row, col in enumerate((dr, dr * g["dx"], dr * g["dy"], m, gsum * m, -c[..., None] * c0 * e0_d * m)):
            Kt[:, :, row] = col
        return f.double(), Kt


def fit_corners(img: np.ndarray, groups: list[list[dict]], r0: np.ndarray, iterations: int = 30):
    """Levenberg–Marquardt fit of the cell-profile model to the bands of each point, batched over points.

    The blur diameter varies linearly over a point's neighbourhood through zero if need be,
    b(x) = |β + g · (x − p)| (the paper's (4) is linear in position to first order), so a point on the plane
    of focus is measured as sharp even though its edges away from it are not. Free per point: β, g (2);
    per band: dark level, contrast and edge offset.

    Args:
        img: the (pyramid-level) image; groups: per point, the bands from `_half_edges`;
        r0: (C,) upper bound of the blur radius per point, pixels (the start is scanned below it).
    Returns:
        b (C,) = |β|, sigma_b (C,), grad (C, 2), ok (C,), in pixels of `img`.
    """
    r0 = torch.as_tensor(np.asarray(r0, dtype=np.float64))
    r_cap = 1.5 * r0 + 1.0
    model = _BandModel(img, groups, r_cap)
    mask = model.mask
    has_band = mask.any(-1)
    npix = (mask * mask).sum(-1)  # the bands' weights: pixels, tapered at the band's limits
    theta = _start(model, model.I, mask, has_band, r0)
    # weak prior on g (1 % per pixel) keeps points with few bands well posed: residuals prior · (gx, gy)
    prior = 1e-2 * torch.sqrt(npix.sum(-1)) * theta[:, 4::3].abs().mean(-1).clamp_min(1e-6)

    def evaluate(th, idx):
        """`tiltfit.solve.Normal` (cost, JᵀJ, Jᵀr) of the corners idx at parameters th (k, P), r model − data,
        the prior included."""
        f, Kt = model(th, idx)
        at = model.at(idx)
        res = (at["I"] - f) * at["mask"]
        p = prior[idx]
        cost = (res * res).sum((-1, -2)) + ((p[:, None] * th[:, 1:3]) ** 2).sum(-1)
        A, Kr = _normal_equations(Kt, res)
        A[:, 1, 1] += p ** 2
        A[:, 2, 2] += p ** 2
        g = -Kr
        g[:, 1:3] += p[:, None] ** 2 * th[:, 1:3]
        return Normal(cost, A, g)

    def within_cap(th, idx):
        th[:, 0] = th[:, 0].clamp(-2 * r_cap[idx], 2 * r_cap[idx])
        return th

    sol = batched_levenberg_marquardt(evaluate, theta, BatchedOptions(max_iterations=iterations),
                                      small_step=_small_step, project=within_cap)
    theta, cost = sol.x, sol.cost
    contrast = theta[:, 4::3].abs().max(-1).values
    b = theta[:, 0].abs()
    sig = _diameter_sigma(sol.A, cost, npix, has_band, contrast)
    ok = torch.isfinite(b) & torch.isfinite(sig) & (contrast > 0) & (has_band.sum(-1) >= 1)
    return b.numpy(), sig.numpy(), theta[:, 1:3].numpy(), ok.numpy()


def _level_homography(Hm: np.ndarray, factor: int) -> np.ndarray:
    """Compose a full-resolution homography with full -> pyramid-level pixels, x_l = (x + 0.5)/f − 0.5."""
    S = np.array([[1.0 / factor, 0.0, 0.5 / factor - 0.5], [0.0, 1.0 / factor, 0.5 / factor - 0.5], [0, 0, 1.0]])
    return S @ Hm


def measure_blur(gray: np.ndarray, target: Target, corners_px: np.ndarray, *, levels: dict | None = None,
                 max_passes: int = 3, max_pixels: int = 600, level_blur_px: float = 5.0,
                 min_level_square_px: float = 16.0) -> tuple[np.ndarray, np.ndarray]:
    """Blur-disc diameter at each found feature point.

    Each fit runs on a level of the 2×2 box pyramid (a level pixel is exactly the box integral of f × f
    pixels, so the model holds there with b/f): the first pass on the level where squares are about
    24–48 px, with bands cut for blur up to 0.8 of a square; later passes on the level where the blur found
    is about `level_blur_px` (but squares at least `min_level_square_px`), with bands cut for that blur.
    A corner is refitted until its level and band stop changing (at most `max_passes`).

    Args:
        gray: (H, W) linear image.
        target: the Target; corners_px: (N, 2) detected feature points (full resolution), NaN where missing.
        levels: the pyramid of `gray` ({factor: image}), if already built.
        max_pixels: pixels per band at most (evenly thinned beyond).
    Returns:
        blur_px (N,), blur_sigma_px (N,): diameters and one-standard-deviation uncertainties, full-resolution
        pixels, NaN where not measured.
    """
    with torch_threads(1):
        return _measure_blur(gray, target, corners_px, levels, max_passes, max_pixels, level_blur_px,
                             min_level_square_px)


def _measure_blur(gray, target, corners_px, levels, max_passes, max_pixels, level_blur_px, min_level_square_px):
    if levels is None:
        levels = build_pyramid(np.asarray(gray, dtype=np.float32))
    factors = sorted(levels)
    N = target.n_points
    blur = np.full(N, np.nan)
    sigma = np.full(N, np.nan)
    found = np.isfinite(corners_px).all(1)
    Hs = _local_homographies(target, corners_px, found)
    if not Hs:
        return blur, sigma
    ny, nx = target.grid_shape
    square = {}
    for k, Hm in Hs.items():
        j, i = divmod(k, nx)
        c = apply_homography(Hm, np.array([[target.x_edges[i + 1], target.y_edges[j + 1]]]))[0]
        nb = apply_homography(Hm, np.array([[target.x_edges[i], target.y_edges[j + 1]],
                                  [target.x_edges[i + 2], target.y_edges[j + 1]],
                                  [target.x_edges[i + 1], target.y_edges[j]],
                                  [target.x_edges[i + 1], target.y_edges[j + 2]]]))
        square[k] = float(np.min(np.hypot(*(nb - c).T)))

    def level_for(sq, b=None):
        ok = [f for f in factors if sq / f >= (24.0 if b is None else min_level_square_px)
              and (b is None or f <= max(1.0, b / level_blur_px))]
        return ok[-1] if ok else factors[0]

    # plan per point: (level factor, expected radius there, its gradient, first pass?)
    plan = {k: (level_for(square[k]), 0.4 * square[k] / level_for(square[k]), None, True) for k in Hs}
    for _ in range(max_passes):
        if not plan:
            break
        results = {}
        for f in sorted({p[0] for p in plan.values()}):
            keys, groups = [], []
            for first in (True, False):
                ks = [k for k, p in plan.items() if p[0] == f and p[3] == first]
                if not ks:
                    continue
                grads = None if first else np.array([plan[k][2] for k in ks])
                # the first pass only has to find the blur to within ~10 %: fewer pixels, fewer iterations
                bands = _half_edges(target, np.array(ks), np.stack([_level_homography(Hs[k], f) for k in ks]),
                                    np.array([plan[k][1] for k in ks]), levels[f].shape,
                                    max_pixels // 3 if first else max_pixels, first_pass=first, grads=grads)
                keys += [k for k, bk in zip(ks, bands) if bk]
                groups += [bk for bk in bands if bk]
            if not groups:
                continue
            r0 = np.array([max(plan[k][1], 0.3) for k in keys])
            first = plan[keys[0]][3]
            b, sb, grad, ok = fit_corners(levels[f], groups, r0, iterations=8 if first else 30)
            for i, k in enumerate(keys):
                if ok[i]:
                    results[k] = (b[i] * f, sb[i] * f, grad[i])
        new_plan = {}
        for k, (m, s, g) in results.items():
            blur[k], sigma[k] = m, s
            f_new = level_for(square[k], m)
            r_new = 0.55 * m / f_new + 0.5
            fk, r_l, _, first = plan[k]
            if first or f_new != fk or abs(r_new - r_l) > 0.25 * r_l:
                new_plan[k] = (f_new, r_new, g, False)
        plan = new_plan
    return blur, sigma
