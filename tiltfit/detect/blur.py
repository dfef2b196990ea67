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
# Pixel slots (points × bands × pixels a band, padding included) a model evaluation takes at once: an evaluation
# is some 60 element-wise passes over arrays of this size, and beyond it they leave the core's cache (a 1280 × 1024
# photo's 160 points in one evaluation, 380,000 slots, cost twice as much CPU time as in chunks of this size)
_CHUNK_SLOTS = 65536
# A point set's gathered tensors are kept while the solver asks for at least this share of it (the points it no
# longer asks for are evaluated along and their results dropped): gathering a set anew costs about as much as
# 1.5 evaluations of it, and the solver drops converged points a few at a time
_KEEP_SET_SHARE = 0.75



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
    hp, hm = 0.5 * (wa + wb), 0.5 * (wa - wb)
    reach = r + hp + 1e-3
    d = torch.maximum(torch.minimum(d, reach), -reach)  # E is exactly 0 or 1 beyond; keeps G2 small
    d, r, hp, hm, inv_area = torch.broadcast_tensors(d, r, hp, hm, 1 / (wa * wb))
    flat = (t.detach().double().reshape(-1).numpy() for t in (d, r, hp, hm, inv_area))
    out = [torch.from_numpy(v).reshape(d.shape) for v in _pixel_esf(*flat, with_derivatives) if v is not None]
    return tuple(out) if with_derivatives else out[0]


def _pixel_esf(d: np.ndarray, r: np.ndarray, hp: np.ndarray, hm: np.ndarray, inv_area: np.ndarray,
               with_derivatives: bool):
    """`pixel_esf` of (m,) float64 pixels from r ≥ 1e-3 and each box's half widths hp = (wa + wb)/2,
    hm = (wa − wb)/2 and 1/(wa wb) (wb ≥ 0.02): E, and with_derivatives ∂E/∂d and ∂E/∂r (else None). In numpy: the
    model's inner loop, where a call costs a third of torch's on the few thousand pixels a fit reaches.

    With G(u) = ∫_{−1}^{u} F (the disc edge spread function F, radius units) and G2(u) = ∫_{−1}^{u} G, and
    c = clip(u, −1, 1), s = √(1 − c²), α = asin(c)/π, h = c²/2 + 1/8, o = max(u − 1, 0):
        G2 = h (1/2 + α) + c s (13/24 + c²/12)/π + o (1 + o/2),   G = c (1/2 + α) + s (2 + c²)/(3π) + o,
    both 0 at u ≤ −1; E = r² (G2(u₁) − G2(u₂) − G2(u₃) + G2(u₄)) / (wa wb) at the four abscissae (d ± hp, d ± hm)/r.
    Written as few whole-array passes, most in place."""
    u = np.stack((d + hp, d + hm, d - hm, d - hp))
    u /= r
    norm = r * r
    norm *= inv_area
    uc = np.minimum(np.maximum(u, -1.0), 1.0)
    q = uc * uc
    s = 1.0 - q
    # floored: the square root of exact zeros (every |u| ≥ 1) is slow on some CPUs' vector units, and
    # √1e-30 = 1e-15 changes G and G2 by far less than the image's noise
    np.sqrt(np.maximum(s, 1e-30, out=s), out=s)
    half_a = np.arcsin(uc)
    half_a /= math.pi
    half_a += 0.5
    over = u - 1.0
    np.maximum(over, 0.0, out=over)
    G2 = q * 0.5
    G2 += 0.125
    G2 *= half_a
    t = q * (1 / (12 * math.pi))
    t += 13 / (24 * math.pi)
    t *= s
    t *= uc
    G2 += t
    t = over * 0.5
    t += 1.0
    t *= over
    G2 += t
    G2u = G2[0] - G2[1]
    G2u -= G2[2]
    G2u += G2[3]
    E = G2u * norm
    if not with_derivatives:
        return E, None, None
    G = uc * half_a
    t = q * (1 / (3 * math.pi))
    t += 2 / (3 * math.pi)
    t *= s
    G += t
    G += over
    norm /= r
    dE_dd = G[0] - G[1]
    dE_dd -= G[2]
    dE_dd += G[3]
    dE_dd *= norm
    G *= u
    dE_dr = 2.0 * G2u
    dE_dr -= G[0]
    dE_dr += G[1]
    dE_dr += G[2]
    dE_dr -= G[3]
    dE_dr *= norm
    return E, dE_dd, dE_dr


def _pack_bands(img: np.ndarray, groups: list[list[dict]], B: int):
    """The bands of C points padded into tensors (B bands a point, n pixels a band at most): mask (the square root
    of the pixel's weight, so that residuals and Jacobian rows times mask weight the squares), values, d0, d_lo,
    d_hi (C, B, n), dxy (C, B, n, 2), kappa (C, B, 4), wa, wb (C, B, 1); padding has mask 0 and every edge out of
    reach. float64 for the mask, values and far lines, `_MODEL_DTYPE` for the model's geometry."""
    C = len(groups)
    n = max(len(b["d0"]) for g in groups for b in g)
    mask = np.zeros((C, B, n))
    vals = np.zeros((C, B, n))
    d0 = np.full((C, B, n), 1e4)  # padding: every edge out of reach, so no closed form is evaluated there
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


def _band_blocks(B: int):
    """Where the (7, 7) product of a band's rows (β, gx, gy, dark level, contrast, edge offset; residual) goes in a
    point's normal equations: flat indices into JᵀJ (P × P, P = 3 + 3B) of each band's 6 × 6 block (B * 36,) (the
    point's 3 × 3 block is shared by its bands and summed), and into Jᵀr (P,) of each band's 6 (B * 6,)."""
    P = 3 + 3 * B
    params = np.array([[0, 1, 2, 3 + 3 * e, 4 + 3 * e, 5 + 3 * e] for e in range(B)])  # (B, 6)
    to_A = (params[:, :, None] * P + params[:, None, :]).reshape(-1)
    return torch.from_numpy(to_A), torch.from_numpy(params.reshape(-1))


def _start(model, I: torch.Tensor, mask: torch.Tensor, has_band: torch.Tensor, r0: torch.Tensor) -> torch.Tensor:
    """`fit_corners`' start (C, P): β scanned from 4 % to 200 % of 2 r0 (g = 0), the levels of each band solved
    linearly at each β (weighted by mask²), the β that leaves the least weighted squared residual kept.
    model.profile_np(theta, idx) gives the cells' profile at unit contrast and zero dark level (numpy, as the
    sums here: a few dozen calls on small arrays, a third of torch's cost each)."""
    C, B = mask.shape[:2]
    every = torch.arange(C)
    I, mask, has_band, r0 = I.numpy(), mask.numpy(), has_band.numpy(), r0.numpy()
    w = mask * mask
    npix = w.sum(-1)
    sI = (w * I).sum(-1)
    best = np.full(C, np.inf)
    theta = np.zeros((C, 3 + 3 * B))
    for frac in (0.05, 0.13, 0.3, 0.55, 1.0, 1.6):
        trial = np.zeros((C, 3 + 3 * B))
        trial[:, 0] = np.maximum(2 * r0 * frac, 0.1)  # β is a diameter
        trial[:, 4::3] = 1.0
        gg = model.profile_np(trial, every)
        wg = w * gg
        sg, sgg, sgI = wg.sum(-1), (wg * gg).sum(-1), (wg * I).sum(-1)
        det = npix * sgg - sg * sg
        cc = (npix * sgI - sg * sI) / np.maximum(det, 1e-30)
        oo = (sI - cc * sg) / np.maximum(npix, 1e-9)
        res = I - oo[..., None] - cc[..., None] * gg
        res *= mask
        cost = (res * res).sum((-1, -2))
        better = cost < best
        trial[:, 3::3], trial[:, 4::3] = oo, np.where(has_band, cc, 1.0)
        theta = np.where(better[:, None], trial, theta)
        best = np.where(better, cost, best)
    return torch.from_numpy(theta)


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
    """`fit_corners`' model of one chunk of points' packed bands: the cells' profile, and the normal equations.

    A band's profile crosses three edges, its own and the parallel edges before and after it, each a step (0 or 1)
    blurred by the disc. They are evaluated as one list of candidate slots: every slot for the band's own edge, and
    for the far edges, which do not move, the slots within reach of the largest blur allowed (`r_cap`); the closed
    form (`pixel_esf`) runs on the candidates the current blur reaches, elsewhere a profile is its step. The
    solver asks for the same points for several iterations (until one of them stops), so their tensors and
    candidates are gathered once per set of points.
    """

    def __init__(self, img: np.ndarray, groups: list[list[dict]], r_cap: torch.Tensor, B: int):
        dt = _MODEL_DTYPE  # the model's working precision
        self.mask, self.I, d0, dlo, dhi, dxy, kap, wa, wb = _pack_bands(img, groups, B)
        lim = 1.3 * (r_cap + 2.0)[:, None, None]
        c_lo, c_0, c_hi = ((kap[..., j + 1] - kap[..., j])[..., None] for j in range(3))
        # the profile where no blur reaches: the cells' levels with every edge a step
        steps = kap[..., 0:1] + c_lo * (dlo > 0) + c_hi * (dhi > 0)  # the far edges' steps, which do not move
        self._points = dict(I=self.I, mask=self.mask.to(dt), d0=d0, dx=dxy[..., 0].contiguous(),
                            dy=dxy[..., 1].contiguous(), steps=steps, c_0=c_0, wa=wa, wb=wb,
                            far=torch.stack([dlo.abs() < lim, dhi.abs() < lim]), d_far=torch.stack([dlo, dhi]).to(dt),
                            c_far=torch.stack([c_lo, c_hi]))
        self._to_A, self._to_g = _band_blocks(B)
        self._idx, self._at, self._theta, self._prior = None, None, None, None

    def at(self, idx: torch.Tensor) -> dict:
        """The points' tensors gathered at idx (k,), and their candidate slots (class docstring), kept until
        another set is asked for."""
        if self._idx is not None and idx.numel() == self._idx.numel() and torch.equal(idx, self._idx):
            return self._at
        p = self._points
        g = {k: p[k][idx] for k in ("I", "mask", "d0", "dx", "dy", "c_0", "wa", "wb")}
        k, B, n = g["d0"].shape
        # where the own edge is a step: the cells' levels, the own step written 1/2 + sign(d)/2 (a float
        # sign, not a comparison: several times cheaper in torch)
        g["steps"] = torch.addcmul(p["steps"][idx], g["c_0"], torch.tensor(0.5, dtype=torch.float64))
        g["half_c_0"] = 0.5 * g["c_0"]
        reach = 0.5 * (g["wa"] + g["wb"].clamp_min(0.02)) + 1e-3  # (k, B, 1) beyond the blur radius
        g["reach"] = reach.expand(k, B, n).reshape(-1).numpy()
        far = p["far"][:, idx].reshape(-1).nonzero().squeeze(1)  # (line, slot) of the far edges' candidates
        slot_far = far % (k * B * n)
        g["slot_far"] = slot_far
        g["d_far"] = p["d_far"][:, idx].reshape(-1)[far]
        g["reach_far"] = reach.reshape(-1)[slot_far // n].numpy()
        band = torch.cat([torch.arange(k * B).repeat_interleave(n), slot_far // n])
        g["coef"] = torch.cat([g["c_0"].expand(k, B, n).reshape(-1), p["c_far"][:, idx].reshape(-1)[far // n]])
        wa, wb = g["wa"].reshape(-1)[band], g["wb"].reshape(-1)[band].clamp_min(0.02)  # as `pixel_esf` has them
        g["cand_hp"], g["cand_hm"], g["cand_inv_area"] = 0.5 * (wa + wb), 0.5 * (wa - wb), 1 / (wa * wb)
        g["rows"] = torch.empty(k, B, 7, n, dtype=torch.float64)  # `normal`'s rows; the dark level's is √weight
        g["rows"][:, :, 3] = g["mask"]
        g["neg_Im"] = -g["I"] * g["mask"]
        # what `_profile` reads at the candidates, as numpy arrays (views of the tensors)
        g["np"] = {key: g[key].numpy() for key in ("slot_far", "d_far", "coef", "cand_hp", "cand_hm", "cand_inv_area")}
        g["np"]["mask"] = g["mask"].numpy().reshape(-1)
        self._idx, self._at, self._theta = idx, g, None
        return g

    def _within_kept(self, idx: torch.Tensor) -> torch.Tensor | None:
        """Where the points idx (k,) (ascending) sit in the kept set, if they are a strict subset of it with at least
        `_KEEP_SET_SHARE` of its points; else None."""
        kept = self._idx
        if self._theta is None or not (_KEEP_SET_SHARE * kept.numel() <= idx.numel() < kept.numel()):
            return None
        pos = torch.searchsorted(kept, idx).clamp_max_(kept.numel() - 1)
        return pos if torch.equal(kept[pos], idx) else None

    def _profile(self, g: dict, theta: torch.Tensor, deriv: bool):
        """The cells' profile (k, B, n) at unit contrast and zero dark level for parameters theta (k, P), and with
        deriv the mask times Σ (cell step) ∂E/∂r over the edges times sign(β + g · x) (∂E/∂β / ∂r/∂β · 2), and the
        mask times ∂E/∂d of the own edge (both (k, B, n)). The passes over every slot run in torch, the candidates'
        closed form in numpy (`_pixel_esf`: a few thousand values, where a call's cost, a third of torch's,
        outweighs its arithmetic)."""
        a = g["np"]
        beta, gx, gy = (theta[:, j, None, None] for j in range(3))
        delta = theta[:, 5::3, None]  # (k, B, 1)
        sb = torch.addcmul(beta, gx, g["dx"]).addcmul_(gy, g["dy"])
        r = sb.abs().mul_(0.5).clamp_min_(1e-3)
        d = g["d0"] - delta
        S = d.numel()
        dn, rn = d.numpy().reshape(-1), r.numpy().reshape(-1)
        r_far = rn[a["slot_far"]]
        # the candidates the blur reaches
        own = np.flatnonzero(np.abs(dn) < rn + g["reach"])
        far = np.flatnonzero(np.abs(a["d_far"]) < r_far + g["reach_far"])
        at = np.concatenate([own, far + S])  # into the candidates: own slots, then the far edges' list
        slot = np.concatenate([own, a["slot_far"][far]])
        ds = np.concatenate([dn[own], a["d_far"][far]])
        rs = np.concatenate([rn[own], r_far[far]])
        # r ≥ 1e-3 already, and a reached |d| is below r + hp + 1e-3, where `pixel_esf` would clamp it
        E, E_dd, E_dr = _pixel_esf(ds, rs, a["cand_hp"][at], a["cand_hm"][at], a["cand_inv_area"][at], deriv)
        coef = a["coef"][at]
        gsum = torch.addcmul(g["steps"], g["half_c_0"], torch.sign(d))
        # at the candidates reached, the step there (1/2 + sign/2 for the own edge, as above) becomes E
        no = own.size
        step = np.concatenate([np.sign(ds[:no]) * 0.5 + 0.5, (ds[no:] > 0).astype(np.float64)])
        slot_t = torch.from_numpy(slot)
        gsum.view(-1).index_add_(0, slot_t, torch.from_numpy(coef * (E - step)))
        if not deriv:
            return gsum, None, None
        m = a["mask"]
        coef *= E_dr
        coef *= m[slot]
        coef *= np.sign(sb.numpy().reshape(-1)[slot])
        E_r = torch.zeros(S, dtype=gsum.dtype).index_add_(0, slot_t, torch.from_numpy(coef))
        E_d = torch.zeros(S, dtype=gsum.dtype).index_copy_(0, slot_t[:no], torch.from_numpy(E_dd[:no] * m[own]))
        return gsum, E_r.view_as(gsum), E_d.view_as(gsum)

    def profile(self, theta: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        """The cells' profile (k, B, n) at the points idx (k,) for parameters theta (k, P), unit contrast and zero
        dark level (the start's model)."""
        return self._profile(self.at(idx), theta.to(_MODEL_DTYPE), deriv=False)[0]

    def profile_np(self, theta: np.ndarray, idx: torch.Tensor) -> np.ndarray:
        """`profile` of numpy parameters theta (k, P), as a numpy array."""
        return self.profile(torch.from_numpy(theta), idx).numpy()

    def normal(self, theta: torch.Tensor, idx: torch.Tensor, prior: torch.Tensor) -> Normal:
        """`tiltfit.solve.Normal` of the points idx (k,) at parameters theta (k, P): the cost Σ mask² (model − data)²
        with the prior on g (prior² |g|², prior (k,)), JᵀJ (k, P, P) and Jᵀr (k, P), r model − data.

        A pixel of band e depends on the point's (β, gx, gy) and on band e's (dark level, contrast, edge offset)
        only: its six Jacobian entries and its residual form 7 rows a band, whose products (one bmm) are the
        band's blocks of the normal equations and its squared residuals."""
        th = theta.to(_MODEL_DTYPE)
        pos = self._within_kept(idx)
        if pos is None:
            g = self.at(idx)
        else:  # the kept set, the other points at their last parameters
            g = self._at
            th, prior = self._theta.index_copy(0, pos, th), self._prior.index_copy(0, pos, prior)
        self._theta, self._prior = th, prior
        k, B, n = g["d0"].shape
        P = 3 + 3 * B
        o, c = th[:, 3::3, None], th[:, 4::3, None]  # (k, B, 1)
        gsum, E_r, E_d = self._profile(g, th, deriv=True)
        m, rows = g["mask"], g["rows"]  # √weight, 0 on padding: the rows there are zeroed exactly
        torch.mul(E_r, 0.5 * c, out=rows[:, :, 0])  # ∂r/∂β = sign(β + g · x) / 2
        torch.mul(rows[:, :, 0], g["dx"], out=rows[:, :, 1])
        torch.mul(rows[:, :, 0], g["dy"], out=rows[:, :, 2])
        torch.mul(gsum, m, out=rows[:, :, 4])
        torch.mul(E_d, -c * g["c_0"], out=rows[:, :, 5])
        torch.addcmul(g["neg_Im"], c, rows[:, :, 4], out=rows[:, :, 6]).addcmul_(o, m)
        M = rows @ rows.transpose(-1, -2)  # (k, B, 7, 7)
        A = torch.zeros(k, P * P, dtype=torch.float64).index_add_(1, self._to_A, M[..., :6, :6].reshape(k, B * 36))
        A = A.view(k, P, P)
        grad = torch.zeros(k, P, dtype=torch.float64).index_add_(1, self._to_g, M[..., :6, 6].reshape(k, B * 6))
        p2 = prior * prior
        A[:, 1, 1] += p2
        A[:, 2, 2] += p2
        grad[:, 1:3] += p2[:, None] * th[:, 1:3]
        cost = M[..., 6, 6].sum(-1) + p2 * (th[:, 1:3] ** 2).sum(-1)
        if pos is not None:
            return Normal(cost[pos], A[pos], grad[pos])
        return Normal(cost, A, grad)


def _chunks(groups: list[list[dict]]) -> list[np.ndarray]:
    """The points in chunks a model evaluation takes at once: ordered by their longest band (so a chunk pads its
    bands to about their own length) and cut into as few chunks of about equal pixel slots as keep each within
    about `_CHUNK_SLOTS`."""
    B = max(len(g) for g in groups)
    n = np.array([max(len(b["d0"]) for b in g) for g in groups])
    order = np.argsort(n, kind="stable")
    slots = np.cumsum(B * n[order])
    pieces = math.ceil(slots[-1] / _CHUNK_SLOTS)
    cuts = np.searchsorted(slots, slots[-1] * np.arange(1, pieces) / pieces)
    return [ch for ch in np.split(order, cuts) if ch.size]


def fit_corners(img: np.ndarray, groups: list[list[dict]], r0: np.ndarray, iterations: int = 30):
    """Levenberg–Marquardt fit of the cell-profile model to the bands of each point, batched over points.

    The blur diameter varies linearly over a point's neighbourhood through zero if need be,
    b(x) = |β + g · (x − p)| (the paper's (4) is linear in position to first order), so a point on the plane
    of focus is measured as sharp even though its edges away from it are not. Free per point: β, g (2);
    per band: dark level, contrast and edge offset. The model is evaluated in chunks of points (`_chunks`).

    Args:
        img: the (pyramid-level) image; groups: per point, the bands from `_half_edges`;
        r0: (C,) upper bound of the blur radius per point, pixels (the start is scanned below it).
    Returns:
        b (C,) = |β|, sigma_b (C,), grad (C, 2), ok (C,), in pixels of `img`.
    """
    chunks = _chunks(groups)
    order = np.concatenate(chunks)  # the fit runs on the points in this order
    B = max(len(g) for g in groups)
    r0 = torch.as_tensor(np.asarray(r0, dtype=np.float64)[order])
    r_cap = 1.5 * r0 + 1.0
    bounds = np.cumsum([0] + [len(ch) for ch in chunks])
    spans = list(zip(bounds[:-1].tolist(), bounds[1:].tolist()))
    models = [_BandModel(img, [groups[i] for i in ch], r_cap[a:b], B) for ch, (a, b) in zip(chunks, spans)]
    has_band = torch.cat([m.mask.any(-1) for m in models])
    npix = torch.cat([(m.mask * m.mask).sum(-1) for m in models])  # the bands' weights: pixels, tapered
    theta = torch.cat([_start(m, m.I, m.mask, m.mask.any(-1), r0[a:b]) for m, (a, b) in zip(models, spans)])
    # weak prior on g (1 % per pixel) keeps points with few bands well posed: residuals prior · (gx, gy)
    prior = 1e-2 * torch.sqrt(npix.sum(-1)) * theta[:, 4::3].abs().mean(-1).clamp_min(1e-6)
    starts = torch.as_tensor(bounds)

    def evaluate(th, idx):
        """`tiltfit.solve.Normal` of the points idx (ascending) at th (k, P), chunk by chunk."""
        cuts = torch.searchsorted(idx, starts).tolist()
        parts = [m.normal(th[p:q], idx[p:q] - a, prior[idx[p:q]])
                 for m, (a, _), p, q in zip(models, spans, cuts, cuts[1:]) if q > p]
        if len(parts) == 1:
            return parts[0]
        return Normal(*(torch.cat(x) for x in zip(*((n.cost, n.A, n.g) for n in parts))))

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
    back = np.argsort(order)
    return b.numpy()[back], sig.numpy()[back], theta[:, 1:3].numpy()[back], ok.numpy()[back]


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
            # the first pass only plans the next: a point it finds too sharp to tell (β undetermined, σ infinite: no
            # pixel its blur reaches on this level) is refitted on the level chosen for that blur, not dropped
            # (whether its tiny β's information passed the test of `_diameter_sigma` was a matter of rounding)
            planned = ok | (first & np.isfinite(b) & np.isinf(sb))
            for i, k in enumerate(keys):
                if planned[i]:
                    results[k] = (b[i] * f, sb[i] * f, grad[i])
        new_plan = {}
        for k, (m, s, g) in results.items():
            if np.isfinite(s):
                blur[k], sigma[k] = m, s
            f_new = level_for(square[k], m)
            r_new = 0.55 * m / f_new + 0.5
            fk, r_l, _, first = plan[k]
            if first or f_new != fk or abs(r_new - r_l) > 0.25 * r_l:
                new_plan[k] = (f_new, r_new, g, False)
        plan = new_plan
    return blur, sigma
