"""The uncertainties of a calibration fit: the covariance of the fitted parameters (per-view cluster-robust with the
classical floor, `tiltfit.uncertainty.covariance`, or classical) and the σ of the values derived from them (w, U, d,
f, the tilts, the principal point, the distortion, the board, each view's pose), with held lens parameters of known
σ (an `init`'s) propagated through the refit. Used by `tiltfit.calibrate.fit._fit_camera`.

    derived(camera, params)                              -> (w, U, d, f, θF°, θL°, θL_paper°, φ°, cx, cy)
    uncertainties(prob, res, scale, init_sigma, model)   -> (C, sigma, view σ, s², extras)
"""
from __future__ import annotations

import math

import torch

from renderer.cameras import lens_values, stored_lens_sigma, w_from_stored
from tiltfit.calibrate.model import LensCamera
from tiltfit.solve import LMResult
from tiltfit.solve import covariance as solve_covariance


def derived(camera: LensCamera, params: dict) -> torch.Tensor:
    """(w, U, d, f, θF°, θL°, θL_paper°, φ°, cx, cy) as functions of the stored parameters."""
    from renderer.cameras import optics

    w, U, d, thF = lens_values(params)
    thL = optics.theta_L_from_theta_F(thF, w, U)
    f = optics.focal_length(w, U, thL)
    thLp = optics.theta_L_paper(thF, f, U)
    pp = camera.image_centre_px + params["pp_scaled"] * camera.pixel_scale_px
    deg = 180.0 / math.pi
    return torch.stack([w, U, d, f, thF * deg, thL * deg, thLp * deg, params["phi"] * deg, pp[0], pp[1]])


DERIVED_KEYS = ("w_mm", "U_mm", "d_mm", "f_mm", "theta_F_deg", "theta_L_deg", "theta_L_paper_deg",
                 "tilt_axis_deg")


def _held_sigma(init_sigma: dict | None, camera: LensCamera, names: list[str]) -> dict:
    """σ of held stored lens parameters from an `init` sigma dict (relative σ for log w, cm for d)."""
    if not init_sigma:
        return {}
    stored = stored_lens_sigma(float(camera.w_mm), float(camera.U_mm), init_sigma)
    return {n: s for n, s in stored.items() if n in names and n != "theta_F"}


def _jacobian_of(f, x: torch.Tensor) -> torch.Tensor:
    """(m, n) Jacobian of a small function (m, n ≲ 10) by reverse-mode autograd."""
    return torch.autograd.functional.jacobian(f, x.detach())


def _intrinsics(camera: LensCamera, params: dict) -> torch.Tensor:
    """(focal_px, cx, cy, k1 … k6, θL°, φ°) as functions of the stored parameters
    (`tiltfit.uncertainty.covariance.INTRINSIC_NAMES`: what the projection depends on; θL and φ place a lens-axis
    distortion's frame)."""
    w = w_from_stored(params["log_w_mm"])
    pp = camera.image_centre_px + params["pp_scaled"] * camera.pixel_scale_px
    k = torch.stack([params[n].reshape(()) for n in LensCamera.parameter_names("distortion")])
    # tan θL = w tan θF / (U + w) written with 1/U, finite (θL = 0) and differentiable at focus at infinity
    u = params["inv_U_per_m"] / 1000.0
    theta_L = torch.atan(w * torch.tan(params["theta_F"]) * u / (1.0 + w * u))
    deg = 180.0 / math.pi
    return torch.cat([(w / camera.pixel_pitch_mm).reshape(1), pp, k, (theta_L * deg).reshape(1),
                      (params["phi"] * deg).reshape(1)])


def uncertainties(prob, res: LMResult, scale: torch.Tensor, init_sigma: dict | None, sigma_model: str = "views"):
    """Covariance of the free parameters and σ of the derived quantities and per-view poses, under
    `sigma_model` ("views": per-view cluster-robust with the classical floor, `tiltfit.uncertainty.covariance`;
    "classical": s² (JᵀWJ)⁻¹); `prob` the fit's `tiltfit.calibrate.problem._Problem`. Returns (C, sigma, view σ, s²,
    extras {sigma_classical, sigma_model, intrinsics_covariance}).

    Raises:
        SolverError: the normal equations are singular (the free parameters are not all determined).
    """
    from tiltfit.uncertainty.covariance import INTRINSIC_NAMES

    cam = prob.camera
    n = prob.n_corner + prob.n_blur
    s2 = float((res.weights * res.r * res.r).sum()) / max(n - res.x_flat.numel(), 1)
    C_cls = solve_covariance(res, s2)
    robust = _view_covariance(prob, res, scale, s2) if sigma_model == "views" else None
    C, info = robust if robust is not None else (C_cls, {})
    model = {"name": "views" if robust is not None else "classical"} | info
    layout = res.layout
    G = _jacobian_of(lambda v: derived(cam, prob.params(layout.unflatten(v))), res.x_flat)
    held = _held_propagation(prob, res, scale, init_sigma, C_cls, s2, G)
    sigma, view_sig = _sigmas(prob, layout, C, G, held)
    sigma_classical = _sigmas(prob, layout, C_cls, G, held)[0] if robust is not None else dict(sigma)
    Gi = _jacobian_of(lambda v: _intrinsics(cam, prob.params(layout.unflatten(v))), res.x_flat)
    Ci = Gi @ C.matmul(Gi.T)
    extras = {"sigma_classical": sigma_classical, "sigma_model": model,
              "intrinsics_covariance": {"names": list(INTRINSIC_NAMES), "matrix": (0.5 * (Ci + Ci.T)).tolist()}}
    return C, sigma, view_sig, s2, extras


def _view_covariance(prob, res: LMResult, scale: torch.Tensor, s2: float):
    """The per-view cluster-robust covariance (`view_cluster_covariance`), the poses' own part from a random affine
    error of each view's corners; (covariance, info) or None where it cannot be formed."""
    from tiltfit.uncertainty.covariance import affine_modes, view_cluster_covariance

    rows = prob.view_rows
    V, N = prob.cmask.shape
    am = affine_modes(prob.corners, prob.cmask)
    modes = torch.zeros(*rows.shape, am.shape[-1], dtype=torch.float64)
    modes[:, :2 * N] = am
    kinds = torch.zeros(rows.shape, dtype=torch.long)
    kinds[:, :2 * N] = 1
    kinds[:, 2 * N:] = 2
    return view_cluster_covariance(res, s2, modes * scale[rows][..., None], kinds)


def _held_propagation(prob, res: LMResult, scale: torch.Tensor, init_sigma: dict | None, C_cls, s2: float, G):
    """(G_h, Σ_h): held lens parameters with known σ (`init_sigma`), their total derivative through the re-fitted
    free parameters, dx/dh = −(JᵀWJ)⁻¹ JᵀW J_h, and their covariance; None where none is held with a σ."""
    cam = prob.camera
    held_sig = _held_sigma(init_sigma, cam, list(prob.held))
    if not held_sig:
        return None
    hnames = list(held_sig)
    h0 = torch.stack([prob.held[k].reshape(()) for k in hnames])

    def with_h(hv):
        held = dict(prob.held)
        for i, k in enumerate(hnames):
            held[k] = hv[i]
        return held

    _, jh = prob.raw_jacobian(res.x, hnames)
    Jh = torch.cat([jh[k] for k in hnames], 1) * scale[:, None]
    # JᵀW v is the normal equations' gradient of v
    JtWJh = torch.stack([res.normal.gradient(Jh[:, i]) for i in range(len(hnames))], 1)
    dx_dh = -C_cls.matmul(JtWJh) / s2
    Gh = _jacobian_of(lambda hv: derived(cam, prob.params(res.x, with_h(hv))), h0) + G @ dx_dh
    return Gh, torch.diag(torch.tensor([held_sig[k] ** 2 for k in hnames], dtype=torch.float64))


def _sigmas(prob, layout, Cx, G, held):
    """(σ of the derived values, the distortion, 1/U, the blur offset and the board; [per-view pose σ]) from the
    covariance `Cx` of the free parameters."""
    cam = prob.camera
    cov_d = G @ Cx.matmul(G.T)
    if held is not None:
        Gh, Sh = held
        cov_d = cov_d + Gh @ Sh @ Gh.T
    sig = torch.sqrt(torch.clamp(torch.diagonal(cov_d), min=0.0))
    sigma = {k: float(sig[i]) for i, k in enumerate(DERIVED_KEYS)}
    sigma["principal_point_px"] = [float(sig[8]), float(sig[9])]
    offsets = layout.offsets
    sd = Cx.diagonal().clamp_min(0).sqrt().tolist()
    sigma["distortion"] = [sd[offsets[n][0]] if n in offsets else 0.0
                           for n in LensCamera.parameter_names("distortion")]
    if "inv_U_per_m" in offsets:
        sigma["inv_U_per_m"] = sd[offsets["inv_U_per_m"][0]]
    if "blur_offset_px" in offsets:
        sigma["blur_offset_px"] = sd[offsets["blur_offset_px"][0]]
    if prob.BOARD in offsets:
        o, k = offsets[prob.BOARD]
        sigma["board"] = sd[o:o + k]
    view_sig = []
    for v in range(cam.n_views):  # per-view pose σ, if the poses are free
        entry = {}
        if "rvec" in offsets:
            o = offsets["rvec"][0] + 3 * v
            entry["sigma_rvec_deg"] = [math.degrees(sd[o + k]) for k in range(3)]
        if "T_scaled" in offsets:
            o = offsets["T_scaled"][0] + 3 * v
            entry["sigma_T_mm"] = [sd[o + k] * cam.length_scale_mm for k in range(3)]
        view_sig.append(entry)
    return sigma, view_sig
