"""σ of the photometric refinement: the robust residual scale, the per-view cluster-robust covariance, the
sandwich over blur-disc tiles, what the held principal point and distortion add, and σ in CALIB.json's units."""
from __future__ import annotations

import math

import torch

from renderer.cameras import LENS_PARAMETERS, lens_values
from renderer.cameras.optics import theta_L_from_theta_F

from ..solve import dense_jacobian
from .render import board_blur_px
from .problem import _Problem


def _robust_sigma(r: torch.Tensor) -> float:
    return 1.4826 * float(torch.median(r.abs())) + 1e-12


def _cluster_sandwich(res, problem: _Problem) -> torch.Tensor:
    """Covariance (P, P) of the flat parameters by the cluster-robust sandwich A⁻¹ B A⁻¹ of the Huber fit.

    A = Σ w J Jᵀ is the fit's own normal matrix; B = Σ_c g_c g_cᵀ sums the score g_c = Σ_{i ∈ c} w_i r_i J_i
    of each cluster c: the pixels of one square tile of a view, as wide as that view's blur disc (at least
    8 px). Residuals of neighbouring pixels share their errors (the same blurred edge mis-modelled, render and
    shot noise largest on edges), so the textbook (JᵀWJ)⁻¹ s², which assumes independent residuals of one
    variance, comes out too small. Scaled by C / (C − 1) for C clusters; invariant to the residuals' scale.
    """
    J = dense_jacobian(res.jacobian)
    psi = (res.weights * res.r)[:, None] * J
    scores, offset = [], 0
    for v, dv in enumerate(problem.data):
        n = dv.uv.shape[0]
        side = max(8.0, board_blur_px(problem.camera_of(res.x, v), problem.target))
        tile = torch.floor(dv.uv / side).to(torch.int64)
        _, cluster = torch.unique(tile[:, 0] * 100003 + tile[:, 1], return_inverse=True)
        scores.append(torch.zeros(int(cluster.max()) + 1, J.shape[1], dtype=J.dtype).index_add_(
            0, cluster, psi[offset:offset + n]))
        offset += n
    G = torch.cat(scores)
    C = G.shape[0]
    B = G.T @ G * (C / max(C - 1, 1))
    try:
        A_inv = res.normal.covariance().dense()
    except RuntimeError:   # a parameter the data no longer move (one at its trust bound): held, σ 0
        try:
            A_inv = torch.linalg.pinv(res.normal.dense(), hermitian=True)
        except RuntimeError:
            return torch.full_like(B, math.nan)
    return A_inv @ B @ A_inv


def _view_covariance(res, s2: float, cov_tiles: torch.Tensor, held: list | None = None):
    """(covariance (P, P), sigma_model) of the Huber fit under the per-view error model (module docstring):
    `tiltfit.uncertainty.covariance.view_cluster_covariance` with views as clusters. `held`: flat positions of global
    parameters the data no longer move (a lens parameter at its trust bound), left out of the covariance (σ 0).
    The tile sandwich `cov_tiles` where the per-view one cannot be formed (one view, a singular Schur complement)."""
    from types import SimpleNamespace

    from ..solve.blocks import BlockJacobian
    from tiltfit.uncertainty.covariance import view_cluster_covariance

    bj = res.jacobian
    if not isinstance(bj, BlockJacobian):
        return cov_tiles, {"name": "tiles", "n_views": 1}
    P = bj.n_params
    keep = torch.ones(P, dtype=torch.bool)
    if held:
        keep[torch.tensor(held)] = False
    pos = torch.cumsum(keep.to(torch.int64), 0) - 1           # each kept parameter's place in the reduced vector
    cols = keep[bj.s_idx]
    reduced = BlockJacobian(bj.Js[:, cols], bj.Jp, bj.rows, pos[bj.s_idx[cols]], pos[bj.p_idx], int(keep.sum()))
    try:
        got = view_cluster_covariance(SimpleNamespace(jacobian=reduced, weights=res.weights, r=res.r), s2)
    except RuntimeError:   # a singular per-view block (a view whose pixels no longer move its pose)
        got = None
    if got is None:
        return cov_tiles, {"name": "tiles", "n_views": int(bj.rows.shape[0])}
    cov, info = got
    idx = torch.nonzero(keep).squeeze(1)
    full = torch.zeros(P, P, dtype=cov_tiles.dtype)
    full[idx[:, None], idx[None, :]] = cov.dense()
    return full, {"name": "views", **info}


def _held_covariance(problem: "_Problem", res, start_covariance: dict | None):
    """(P, P) covariance the held principal point and distortion add to the fitted parameters, or None.

    The fit holds them at the corner fit's values, so its own covariance is conditional on them; they carry the
    corner fit's uncertainty (`start_covariance`: its `intrinsics_covariance`, {names, matrix}, cx_px, cy_px,
    k1 … k6 among the names), which moves the solution by dx/dh = −A⁻¹ JᵀW J_h (J_h: the residuals'
    derivatives with respect to each held h, by forward differences of 0.1 of its σ). Returns D C_hh Dᵀ with
    D = dx/dh (in the solver's flat order), ignoring the correlation between the corners' errors and the pixels'
    (the same views): on the real sets the held parameters alone moved w between subsets by many times the
    conditional σ (benchmarks/results/photometric_sigma.md)."""
    from tiltfit.uncertainty.covariance import INTRINSIC_NAMES

    if not isinstance(start_covariance, dict) or "names" not in start_covariance:
        return None
    names, M = list(start_covariance["names"]), torch.as_tensor(start_covariance["matrix"], dtype=torch.float64)
    cam = problem.camera
    dist = cam.parameter_names("distortion")
    # Each held intrinsic: (index in the matrix, camera parameter, element, camera units per intrinsic unit).
    targets = {"cx_px": ("pp_scaled", 0, 1.0 / cam.pixel_scale_px), "cy_px": ("pp_scaled", 1, 1.0 / cam.pixel_scale_px)}
    targets |= {n: (dn, None, 1.0) for n, dn in zip(INTRINSIC_NAMES[3:], dist)}
    held = [(names.index(n), *targets[n]) for n in names if n in targets and float(M[names.index(n), names.index(n)]) > 0]
    if not held:
        return None
    idx = torch.tensor([h[0] for h in held])
    C_hh = M[idx[:, None], idx[None, :]]
    try:
        cov = res.normal.covariance()
    except RuntimeError:   # a parameter the data no longer move: no sensitivities
        return None
    with torch.no_grad():
        r0 = problem.evaluate(res.x, False)[0]
        cols = []
        for (i, name, el, unit), var in zip(held, torch.diagonal(C_hh)):
            step = 0.1 * math.sqrt(float(var))
            param = getattr(cam, name)
            before = param.detach().clone()
            if el is None:
                param.add_(step * unit)
            else:
                param[el] += step * unit
            cols.append((problem.evaluate(res.x, False)[0] - r0) / step)
            param.copy_(before)
    Jh = torch.stack(cols, 1)
    if not bool(torch.isfinite(Jh).all()):
        return None
    g = torch.stack([res.normal.gradient(Jh[:, j]) for j in range(Jh.shape[1])], 1)   # JᵀW J_h (P, H)
    D = -cov.matmul(g)
    return D @ C_hh @ D.T


def _lens_sigma(lens: torch.Tensor, cov_lens: torch.Tensor) -> dict:
    """One-σ of w, 1/U, U, d, θF, θL (mm, 1/m, degrees) from the covariance of the stored lens block."""
    def physical(p):
        w, U, d, theta_F = lens_values(p)
        inv_U = p[LENS_PARAMETERS.index("inv_U_per_m")]
        return torch.stack([w, inv_U, U, d, theta_F, theta_L_from_theta_F(theta_F, w, U)])

    Jp = torch.func.jacrev(physical)(lens.detach())
    var = torch.diagonal(Jp @ cov_lens @ Jp.T)
    sd = [math.sqrt(max(float(x), 0.0)) if math.isfinite(float(x)) else math.nan for x in var]
    return {"w_mm": sd[0], "inv_U_per_m": sd[1], "U_mm": sd[2], "d_mm": sd[3],
            "theta_F_deg": math.degrees(sd[4]), "theta_L_deg": math.degrees(sd[5])}


def _sigma_dict(res, cov: torch.Tensor, problem: "_Problem") -> dict:
    layout = res.layout

    def block(name):
        if name not in layout.offsets:
            return None
        a, n = layout.offsets[name]
        return slice(a, a + n)

    s = block("lens")
    Jm = problem.lens_jacobian(res.x["lens"])
    out = _lens_sigma(problem.full_lens(res.x["lens"]), Jm @ cov[s, s] @ Jm.T)
    for name, key in (("vignetting", "vignetting"), ("psf", "psf_sigma_px")):
        b = block(name)
        out[key] = math.sqrt(max(float(cov[b, b][0, 0]), 0.0)) if b is not None else 0.0
    return out
