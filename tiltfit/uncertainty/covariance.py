"""Honest uncertainties: a covariance that sees corner errors correlated within a view, the projection
uncertainty across the image, and the projection difference between two calibrations (cross-validation).

Error model ("views", the default). The classical covariance s² (JᵀWJ)⁻¹ treats every corner as independent
noise. Real corner errors are not: a detector's bias grows with blur, the board is not the ideal grid, the model
misfits; such errors repeat within a view. The per-view cluster-robust (sandwich) covariance lets them be
anything within a view and independent between views:

    C_g = S⁻¹ (Σ_v ũ_v ũ_vᵀ) S⁻¹,  ũ_v = J̃_vᵀ (I − H̃_vv)^(−1/2) r_v

for the global parameters (lens, principal point, distortion, blur offset), with each view's pose profiled out:
J̃_v = J_g,v − J_p,v A_vv⁻¹ A_vg (the view's global columns with its pose's directions removed), S = Σ_v J̃_vᵀ J̃_v
the Schur complement, H̃_vv = J̃_v S⁻¹ J̃_vᵀ the view's block of the hat matrix and (I − H̃_vv)^(−1/2) the CR2
small-sample correction (Bell and McCaffrey 2002; with per-cluster fixed effects absorbed as Pustejovsky and
Tipton 2018 recommend): the fit pulls each view's residuals toward its own data, and without the correction the
sandwich is too small by about (V − 1)/V and more for views of high leverage. Residuals and Jacobian rows carry
the solve's weights and 1/σ_group, so corners and blur widths (w, U, d, θF) are covered alike.

The classical covariance is the floor: C = the smallest matrix ≥ both (in whitened coordinates of the classical
one, the sandwich's eigenvalues below 1 are raised to 1), so no linear combination gets a smaller σ than
independent noise gives; with few views the sandwich alone is noisy and of rank < V.

Poses. A view's own pose cannot be judged this way (its score is orthogonal to its own residuals at the optimum:
an error shared by a view's corners moves its pose unseen), and a single inflation factor does not fit it: a
global design effect κ s² A_vv⁻¹ gave the rotations 0.57–0.70 of their Monte Carlo spread. So C_vv = Ω_v +
Y_v C_g Y_vᵀ (Y_v = A_vv⁻¹ A_vg; the globals' part keeps their sandwich) with the own part Ω_v from a random
effect: besides independent noise (σ_c² on corners, σ_b² on blur widths) each view's corners carry a random
affine map of the image, e_v = B_v η_v, η_v ~ N(0, τ² I), B_v the six affine fields (shift, linear map about the
corners' centroid) orthonormal over the view's corners: the first-order part of any smooth per-view error. The
pose absorbs most of those directions (shift, scale, roll and, through its tilt, much of the rest), so τ² is
estimated from what the residuals r still show, by two moment equations (MINQUE-like, H the hat matrix by its
Schur blocks, c the corner rows): E|r_c|² = σ_c² tr(I − H)_cc + τ² |(I − H)B|²_c and E Σ_v |B_vᵀ r_v|² =
σ_c² |(I − H)B|²_c + σ_b² |(I − H)B|²_b + τ² |Bᵀ(I − H)B|², with σ_b² = |r_b|² / tr(I − H)_bb. Assuming the
error isotropic across the six directions carries τ² to the ones the pose absorbs: Ω_v = A_vv⁻¹ J_pᵀ Σ_ε J_p
A_vv⁻¹ + τ² K_v K_vᵀ, K_v = A_vv⁻¹ J_pᵀ B_v (the pose move of each mode), never below the classical s² A_vv⁻¹
(the matrix max, as for the globals). Left out: the pose–global covariance these errors add (below 0.1 % of
the poses' σ in the Monte Carlo) and the projective (second-order) directions, which there see no error and
pulled τ² down (rotations 0.5–0.8). The Monte Carlo of tests/tiltfit/test_sigma_against_spread.py (8 views, pooled
over them): rotations 1.05–1.16 of the spread, translations 0.92–0.94; with independent noise alone τ² ≈ 0
and the own part is the classical one. On industrial_ds1 the flat-board fit's per-view pose errors (against the
fitted board's poses, benchmarks/calibration/bench_sigma_honesty.py) are 1.13 and 0.99 of this σ for the tilts (classical
and OpenCV 8.0 and 5.1) but 4.0 for the roll (25): an unmodelled board shape errs along the pose's own
directions more than isotropy says, which no residual shows (`board="auto"` fits the shape there).
`view_error_px`: the per-view affine error's RMS length at a corner.

Projection uncertainty: the intrinsics' covariance (focal length in px, principal point, distortion, and the lens
tilt θL and tilt axis φ that place a lens-axis distortion's frame: `INTRINSIC_NAMES`) propagated through the fitted
lens (`calib_lens`, `renderer.Lens.project`) to the projection of a grid of directions across the image, with the part a rotation of the camera frame
explains removed (as `projection_difference` removes the best-fitting rotation; the model's projection is
central, so the depth of the point does not enter). σ at a pixel is sqrt(σ_x² + σ_y²) (the RMS length of the
projection error).
"""
from __future__ import annotations

import math

import numpy as np
import torch

from .columns import KRYLOV_MAX_CONDITION, _DenseColumns, _PointColumns


#: Names of the error models written to CALIB.json's `sigma_model.name`.
SIGMA_MODELS = ("views", "classical")

#: The intrinsics the projection depends on, in `intrinsics_covariance`'s order: focal length and principal point
#: (px), the distortion (OpenCV's order), the lens tilt θL and the tilt axis φ (degrees; they place the distortion's
#: frame when it is about the lens axis).
INTRINSIC_NAMES = ("focal_px", "cx_px", "cy_px", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "theta_L_deg",
                   "tilt_axis_deg")
_AT = {name: i for i, name in enumerate(INTRINSIC_NAMES)}   # θ's entries by name


# ---------------------------------------------------------------------------------------------------------
# The per-view cluster-robust covariance
# ---------------------------------------------------------------------------------------------------------

def view_cluster_covariance(res, s2: float, modes: torch.Tensor | None = None, kinds: torch.Tensor | None = None):
    """The per-view cluster-robust covariance (module docstring) of an LM result with per-view blocks.

    Args:
        res: `tiltfit.solve.LMResult` whose jacobian is a `BlockJacobian` (poses per view; a point block, a free
            board's points, counts among the global parameters and keeps its 3 columns a row, `_PointColumns`).
        s2: the residual variance factor of the classical covariance s² A⁻¹.
        modes: (V, R, m) each view's correlated-error fields on its residual rows (`bj.rows` order), in the
            residuals' units (`affine_modes` times the rows' 1/σ); kinds: (V, R) 1 corner row, 2 blur row, 0 none.
            Given both, the poses' own part is the random-effects one (module docstring); else the design effect.
    Returns:
        (covariance (`SchurCovariance`, flat `res.layout` order), info {design_effect, ratio_min, ratio_max,
        n_views, and with modes view_error_px, pose_ratio_min, pose_ratio_max}) or None where the problem has no
        per-view blocks or fewer than 2 views.
    """
    from tiltfit.solve.blocks import BlockJacobian, SchurCovariance

    bj = res.jacobian
    if not isinstance(bj, BlockJacobian) or bj.rows.shape[0] < 2 or bj.Js.shape[1] + (bj.Jq is not None) == 0:
        return None
    a = res.weights.clamp_min(0).sqrt()
    Jp = (bj.Jp * a[:, None])[bj.rows]                                  # (V, R, K)
    r = (res.r * a)[bj.rows]                                            # (V, R)
    App = Jp.transpose(1, 2) @ Jp
    App_inv = torch.linalg.inv(App)
    Jt = _DenseColumns(bj, a, Jp, App_inv) if bj.Jq is None else _PointColumns(bj, a, Jp, App_inv)
    S = Jt.gram()
    # S⁻¹ = L Lᵀ by the eigenvalues of S in its diagonal scaling (S may be badly conditioned: U, d from blur)
    Dg = torch.diagonal(S).clamp_min(1e-300).rsqrt()
    mu, Vs = torch.linalg.eigh(Dg[:, None] * S * Dg[None, :])
    if not bool(torch.isfinite(mu).all()) or float(mu.min()) <= 1e-13 * float(mu.max()):
        return None
    L = Dg[:, None] * Vs * mu.rsqrt()[None, :]
    L_inv = (Vs * mu.sqrt()[None, :]).T / Dg[None, :]
    S_inv = L @ L.T
    krylov = float(mu.max()) < KRYLOV_MAX_CONDITION * float(mu.min())
    e = Jt.corrected(r, L, S_inv, krylov)                               # (I − H̃_vv)^(−1/2) r_v, clamped λ
    u = Jt.left(e[..., None]).squeeze(-1)                               # (V, S)
    meat = u.T @ u
    C_rob = S_inv @ meat @ S_inv
    C_cls = s2 * S_inv
    # the matrix max of the two: in the classical covariance's whitened coordinates, eigenvalues raised to ≥ 1
    Dw = L_inv @ C_rob @ L_inv.T / s2
    nu, Q = torch.linalg.eigh(0.5 * (Dw + Dw.T))
    nu = nu.clamp_min(1.0)
    C_g = s2 * (L @ (Q * nu) @ Q.T @ L.T)
    ratio = torch.diagonal(C_rob) / torch.diagonal(C_cls)
    kappa = float(nu.mean())
    info = {"design_effect": kappa, "ratio_min": float(ratio.min()), "ratio_max": float(ratio.max()),
            "n_views": int(bj.rows.shape[0])}
    pose = None if modes is None or kinds is None else \
        _pose_random_effect(Jp, Jt, r, S_inv, App, App_inv, modes * a[bj.rows][..., None], kinds, s2)
    if pose is not None:
        own, extra = pose
        info |= extra
    else:
        own = kappa * s2 * App_inv
    cov = SchurCovariance(C_g, own, Jt.Y, Jt.s_idx, bj.p_idx, bj.n_params)
    return cov, info


def affine_modes(corners_px: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """(V, 2N, 6) the affine maps of the image plane as error fields on each view's corners (rows u0, v0, u1, …):
    a shift (2) and a linear map about the corners' centroid (4), orthonormal over the view's observed corners
    (px per unit; 0 at unobserved corners). `view_cluster_covariance`'s `modes` (times the rows' 1/σ)."""
    V, N = mask.shape
    m = mask.to(torch.float64)[..., None]
    xy = torch.nan_to_num(corners_px.to(torch.float64)) * m
    c = xy.sum(1, keepdim=True) / m.sum(1, keepdim=True).clamp_min(1.0)
    d = (xy - c) * m                                                    # (V, N, 2)
    F = xy.new_zeros(V, N, 2, 6)
    for i in range(2):
        F[:, :, i, i] = m[..., 0]
        F[:, :, i, 2 + 2 * i] = d[..., 0]
        F[:, :, i, 3 + 2 * i] = d[..., 1]
    F = F.reshape(V, 2 * N, 6)
    Q, Rq = torch.linalg.qr(F)
    ok = torch.diagonal(Rq, dim1=-2, dim2=-1).abs() > 1e-9 * Rq.abs().amax((-2, -1))[:, None].clamp_min(1e-300)
    return Q * ok[:, None, :]


def _pose_random_effect(Jp, Jt, r, S_inv, App, App_inv, B, kinds, s2):
    """The poses' own covariance under the per-view random effect (module docstring).

    Jp (V, R, K), Jt the pose-profiled global columns (`_DenseColumns`), r (V, R), S_inv (S, S) and App_inv
    (V, K, K) the unscaled inverses, B (V, R, m) the modes, all in whitened weighted rows; kinds (V, R). Returns
    (own (V, K, K), info), or None without corner rows."""
    cm = (kinds == 1).to(r.dtype) * (B != 0).any(-1).to(r.dtype)
    bm = (kinds == 2).to(r.dtype) * (Jp != 0).any(-1).to(r.dtype)
    F = Jt.times(S_inv)                                                 # (V, R, S) J̃ S⁻¹
    h = ((Jp @ App_inv) * Jp).sum(-1) + Jt.rowdot(F)                   # leverages
    R1, a1 = float((cm * r * r).sum()), float((cm * (1 - h)).sum())
    if a1 <= 0:
        return None
    R3, a3 = float((bm * r * r).sum()), float((bm * (1 - h)).sum())
    Kp = App_inv @ (Jp.transpose(1, 2) @ B)                             # (V, K, m): a mode's pose shift
    PB = Jp @ Kp
    g = Jt.left(B)                                                      # (V, S, m)
    Fg = F @ g
    Nv = B - PB - Fg                                                    # (I − H) B, the view's own rows
    GG = (g @ g.transpose(1, 2)).sum(0)
    gSg = g.transpose(1, 2) @ S_inv @ g                                 # (V, m, m)
    # |(I − H) B|² on corner rows: Σ cm |Nv|² + Σ_v tr(Φ_v GG) − Σ_v tr(g_vᵀ Φ_v g_v), Φ_v = F_vᵀ diag(cm) F_v,
    # with Σ_v tr(Φ_v GG) = Σ_i cm_i J̃_i (S⁻¹ GG S⁻¹) J̃_iᵀ (no (S, S) matrix a view), which is tr(S⁻¹ GG) where
    # every row outside the corner rows has no Jacobian (a geometric fit: Σ_i cm_i J̃_iᵀ J̃_i = S)
    if Jt.rows_touch(cm == 0):
        spread = (cm * Jt.rowdot(Jt.right(S_inv @ GG @ S_inv))).sum()
    else:
        spread = (S_inv * GG).sum()
    b1 = float((cm[..., None] * Nv * Nv).sum() + spread - (cm[..., None] * Fg * Fg).sum())
    D = B.transpose(1, 2) @ B - B.transpose(1, 2) @ PB
    a2 = float(torch.diagonal(D - gSg, dim1=-2, dim2=-1).sum())         # tr Bᵀ(I − H)B
    SG = S_inv @ GG
    b2 = float((D * D).sum() - 2 * (D * gSg).sum() + (SG * SG.T).sum())  # |Bᵀ(I − H)B|²
    R2 = float(((B.transpose(1, 2) @ r[..., None]) ** 2).sum())        # the residuals' energy in the modes
    sb2 = R3 / a3 if a3 > 0 else 0.0
    R2 = R2 - sb2 * (a2 - b1)                                           # the blur rows' noise in the modes
    det = a1 * b2 - b1 * b1
    sc2, tau2 = ((b2 * R1 - b1 * R2) / det, (a1 * R2 - b1 * R1) / det) if det > 1e-12 * a1 * b2 else (R1 / a1, 0.0)
    if tau2 < 0:
        sc2, tau2 = R1 / a1, 0.0
    elif sc2 < 0:
        sc2, tau2 = 0.0, R2 / b2
    d = sc2 * cm + sb2 * bm
    own = App_inv @ (Jp.transpose(1, 2) @ (d[..., None] * Jp)) @ App_inv + tau2 * Kp @ Kp.transpose(1, 2)
    # floor: the classical s² A_vv⁻¹ (the matrix max in its whitened coordinates), as for the globals
    Dp = torch.diagonal(App, dim1=-2, dim2=-1).clamp_min(1e-300).rsqrt()          # diagonal scaling first
    Lc, bad = torch.linalg.cholesky_ex(Dp[..., :, None] * App * Dp[..., None, :])  # D App D = Lc Lcᵀ
    if not bool(bad.any()):
        Lw = Lc / Dp[..., :, None]                                      # App = Lw Lwᵀ
        Ow = Lw.transpose(1, 2) @ own @ Lw / s2                         # s² A_vv⁻¹ ↦ I
        nu, Q = torch.linalg.eigh(0.5 * (Ow + Ow.transpose(1, 2)))
        Li = torch.linalg.inv(Lw.transpose(1, 2))
        own = s2 * Li @ (Q * nu.clamp_min(1.0)[:, None, :]) @ Q.transpose(1, 2) @ Li.transpose(1, 2)
    ratio = torch.diagonal(own, dim1=-2, dim2=-1) / torch.diagonal(s2 * App_inv, dim1=-2, dim2=-1)
    n_corner = float(cm.sum()) / 2 / cm.shape[0]                        # observed corners per view
    return own, {"view_error_px": math.sqrt(B.shape[-1] * tau2 / max(n_corner, 1.0)),
                 "pose_ratio_min": float(ratio.min()),
                 "pose_ratio_max": float(ratio.max())}


# ---------------------------------------------------------------------------------------------------------
# Projection: the fitted lens, unprojection, σ across the image, difference of two calibrations
# ---------------------------------------------------------------------------------------------------------

#: A variance whose σ exceeds this (in the parameter's own unit: px, 1, degrees) is not an uncertainty but a
#: broken file (1e300 on a diagonal); well above any σ a calibration of a real sensor can have.
MAX_SIGMA = 1e6


def calib_lens(calib: dict):
    """The `renderer.Lens` of a CALIB.json dict (plain floats), as `tiltfit.files.calibrated.Calibration` builds it
    (`tiltfit.files.calib_lens.lens_from_calib`: w, θF and θL, tilt axis, principal point, distortion and its centre,
    sensor). The one entry point for the projection of a calibration file here."""
    from tiltfit.files.calib_lens import lens_from_calib

    return lens_from_calib(calib)[0]


def intrinsics_vector(lens) -> torch.Tensor:
    """θ (`INTRINSIC_NAMES`: focal_px, cx, cy, k1 … k6, θL°, φ°) of a `renderer.Lens` or a CALIB.json dict
    (`calib_lens`): the parameters the projection depends on, the coordinates of `intrinsics_covariance`."""
    if isinstance(lens, dict):
        lens = calib_lens(lens)
    lens = lens.detached()
    k = (list(lens.distortion or ()) + [0.0] * 8)[:8]
    cx, cy = lens.center_px
    return torch.tensor([float(lens.focal_px), cx, cy, *k, math.degrees(lens.theta_L), math.degrees(lens.phi)],
                        dtype=torch.float64)


def _lens_at(lens, theta: torch.Tensor):
    """The `Lens` of intrinsics θ (`INTRINSIC_NAMES`; tensors, graph kept), U, d, sensor and distortion centre
    from `lens`: θL and φ place the distortion's frame (`Lens.distortion_frame`; θF from θL at U)."""
    from renderer.cameras import Lens

    def at(name):
        return theta[_AT[name]]

    return Lens.from_theta_L(at("focal_px") * lens.sensor.pixel_pitch, lens.U, lens.d, torch.deg2rad(at("theta_L_deg")),
                             sensor=lens.sensor, principal_point_px=(at("cx_px"), at("cy_px")),
                             distortion=theta[_AT["k1"]:_AT["k6"] + 1], phi=torch.deg2rad(at("tilt_axis_deg")),
                             distortion_centre=lens.distortion_centre)


def _project(lens, theta: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """(n, 3) camera-frame directions -> (n, 2) pixels through the lens of intrinsics θ (`Lens.project`)."""
    return _lens_at(lens, theta).project(v)


def pixel_grid(image_size_px, nx: int = 32, ny: int | None = None):
    """(xs (nx,), ys (ny,)) pixel centres of a regular grid spanning the image (pixel centres 0 … W−1)."""
    W, H = image_size_px
    ny = ny or max(2, round(nx * H / W))
    return np.linspace(0.0, W - 1.0, nx), np.linspace(0.0, H - 1.0, ny)


#: Central differences' step of `_jac`, relative to 1 + |x_i| (float64: truncation error ~1e-12 relative, round-off
#: ~1e-10; the σ map agrees with forward-mode derivatives to 1e-10 on the shipped sets).
JACOBIAN_STEP = 1e-6


def _jac(fn, x: torch.Tensor) -> torch.Tensor:
    """(m, n) Jacobian of a function of a few inputs (n ≲ 13) with many outputs, by central differences: two
    plain passes per input. Forward-mode dual numbers gave the same to 1e-10 at 50× the time: the lens's
    broadcast arithmetic has no batched forward rule and fell back to torch's Python decompositions (1.6 s a
    projection σ map, most of the automatic distortion choice's checks)."""
    cols = []
    for i in range(x.numel()):
        h = JACOBIAN_STEP * (1.0 + abs(float(x.reshape(-1)[i])))
        e = torch.zeros_like(x)
        e.view(-1)[i] = h
        cols.append((fn(x + e) - fn(x - e)) / (2.0 * h))
    return torch.stack(cols, -1)


def _rotation_jacobian(lens, theta: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """(2n, 3) derivative of the projections of directions v by a small rotation ω of them (v + ω × v)."""
    w0 = torch.zeros(3, dtype=torch.float64)
    return _jac(lambda w: _project(lens, theta, v + torch.cross(w.expand_as(v), v, dim=-1)).reshape(-1), w0)


def projection_sigma(lens, cov: torch.Tensor, nx: int = 32, ny: int | None = None,
                     compensate_rotation: bool = True):
    """σ of the projection through the fitted lens across the image, rotation-compensated (module docstring).

    Args:
        lens: the `renderer.Lens` (`calib_lens`, or a fitted camera's `lens`); the projection is its own
            (`Lens.project`: focal length, principal point, distortion about the principal point or the tilted
            lens's axis).
        cov: (13, 13) covariance of its intrinsics (`INTRINSIC_NAMES`, `covariance_from_calib`).
        compensate_rotation: remove the part a rotation of the camera frame explains [True]; False: the whole
            σ of the projection of a fixed camera-frame direction (a principal point's σ counts in full).
    Returns:
        (xs, ys, sigma (ny, nx) px; NaN where the distortion cannot be inverted).
    """
    lens = lens.detached()
    theta = intrinsics_vector(lens)
    xs, ys = pixel_grid(lens.sensor.size_px, nx, ny)
    X, Yg = np.meshgrid(xs, ys)
    q = torch.tensor(np.stack([X.ravel(), Yg.ravel()], -1), dtype=torch.float64)
    v = lens.unproject(q)
    ok = torch.isfinite(v).all(-1)
    sig = torch.full((q.shape[0],), math.nan, dtype=torch.float64)
    if int(ok.sum()) >= 3:
        vo = v[ok]
        G = _jac(lambda t: _project(lens, t, vo).reshape(-1), theta)                           # (2n, 13)
        if compensate_rotation:
            Gw = _rotation_jacobian(lens, theta, vo)
            G = G - Gw @ torch.linalg.lstsq(Gw, G).solution
        var = ((G @ cov) * G).sum(-1).reshape(-1, 2).sum(-1)
        sig[ok] = var.clamp_min(0).sqrt()
    return xs, ys, sig.reshape(len(ys), len(xs)).numpy()


def projection_summary(lens, cov, nx: int = 32) -> dict:
    """CALIB.json's `projection_uncertainty`: median and worst σ over the image, and the map on a grid."""
    xs, ys, sig = projection_sigma(lens, cov, nx)
    finite = sig[np.isfinite(sig)]
    return {"median_px": float(np.median(finite)) if finite.size else None,
            "worst_px": float(finite.max()) if finite.size else None,
            "grid_x_px": [float(x) for x in xs], "grid_y_px": [float(y) for y in ys],
            "sigma_px": [[None if not np.isfinite(s) else round(float(s), 6) for s in row] for row in sig],
            "method": "intrinsics covariance (focal length, principal point, distortion, lens tilt and tilt axis) "
                      "propagated through the fitted lens to a grid of directions, the part a rotation of the "
                      "camera frame explains removed; any depth (central projection)"}


def _best_rotation(lens_a, lens_b, v_a, q):
    """Rotation ω (axis-angle) minimising Σ |proj_B(R(ω) v_a) − q|² (`tiltfit.solve.least_squares` from Kabsch)."""
    from renderer import axis_angle_to_matrix, matrix_to_axis_angle

    v_b = lens_b.unproject(q)
    ok = torch.isfinite(v_b).all(-1)
    Hm = v_a[ok].T @ v_b[ok]
    Uu, _, Vt = torch.linalg.svd(Hm)
    D = torch.eye(3, dtype=torch.float64)
    D[2, 2] = torch.sign(torch.linalg.det(Vt.T @ Uu.T))
    w = matrix_to_axis_angle(Vt.T @ D @ Uu.T)

    def resid(w):
        return (lens_b.project(v_a @ axis_angle_to_matrix(w).T) - q).reshape(-1)

    from tiltfit.solve import LMOptions, least_squares

    w = least_squares(resid, w, LMOptions(max_iterations=50), jacobian_fn=lambda x: _jac(resid, x)).x
    return w


#: Fewer distinct grid pixels than this along a side leave nothing for the comparison to see once the rotation
#: (3 parameters) is fitted: a focal length or distortion difference needs points away from each other.
MIN_COMPARE_SIDE_PX = 8


def projection_difference(calib_a: dict, calib_b: dict, nx: int = 32, cov_a=None, cov_b=None,
                          rotation: bool = True) -> dict:
    """The projection difference of two calibrations of one camera across the image, after the best-fitting
    rotation between their camera frames (as mrcal-show-projection-diff), against the difference their
    uncertainties predict: sqrt(σ_A² + σ_B²) per pixel (each rotation-compensated, `projection_sigma`).

    Each grid pixel q is unprojected with A, rotated from A's camera frame to B's and projected with B; the
    difference is |proj_B(R v_A(q)) − q|. Both project through their full fitted lens (`calib_lens`: tilt, tilt
    axis and the distortion's centre included). The rotation absorbs whatever a rotation of the camera frame
    explains: a common shift of the principal point (the poses turn with it), so such a shift is not in the
    difference.

    No verdict (`consistent` None) where the σ say nothing: an image under `MIN_COMPARE_SIDE_PX` a side (the
    rotation absorbs any difference there), a predicted σ of 0 or not finite, or one larger than the image.

    Args:
        calib_a, calib_b: CALIB.json dicts (same image size); cov_a/cov_b: their intrinsics covariances (13, 13)
            (default: the files' `intrinsics_covariance`, `covariance_from_calib`; without one the prediction
            is None).
        rotation: fit the rotation [True]; False: R = I, and the prediction is not rotation-compensated either.
    Returns:
        {grid_x_px, grid_y_px, difference_px (ny, nx), predicted_px (ny, nx) or None, median_px, worst_px,
        predicted_median_px, predicted_worst_px, rms_ratio (RMS difference / RMS predicted), rotation_deg (the
        fitted rotation's angle, A's camera frame to B's; 0 without one), rotation_fitted, consistent
        (rms_ratio ≤ 2: within what the two σ allow; None: no verdict), verdict}.
    Raises:
        ValueError: an `intrinsics_covariance` that is not a covariance (`covariance_from_calib`).
    """
    from renderer import axis_angle_to_matrix

    size = tuple(int(s) for s in calib_a["image_size_px"])
    la, lb = calib_lens(calib_a), calib_lens(calib_b)
    xs, ys = pixel_grid(size, nx)
    X, Yg = np.meshgrid(xs, ys)
    q = torch.tensor(np.stack([X.ravel(), Yg.ravel()], -1), dtype=torch.float64)
    v_a = la.unproject(q)
    ok = torch.isfinite(v_a).all(-1)
    w = _best_rotation(la, lb, v_a[ok], q[ok]) if rotation else torch.zeros(3, dtype=torch.float64)
    diff = torch.full((q.shape[0],), math.nan, dtype=torch.float64)
    diff[ok] = (lb.project(v_a[ok] @ axis_angle_to_matrix(w).T) - q[ok]).norm(dim=-1)
    diff = diff.reshape(len(ys), len(xs)).numpy()
    cov_a = cov_a if cov_a is not None else covariance_from_calib(calib_a)
    cov_b = cov_b if cov_b is not None else covariance_from_calib(calib_b)
    pred = None
    if cov_a is not None and cov_b is not None:
        sa = projection_sigma(la, cov_a, nx, compensate_rotation=rotation)[2]
        sb = projection_sigma(lb, cov_b, nx, compensate_rotation=rotation)[2]
        pred = np.sqrt(sa ** 2 + sb ** 2)
    fin = np.isfinite(diff) & (np.isfinite(pred) if pred is not None else True)
    out = {"grid_x_px": [float(x) for x in xs], "grid_y_px": [float(y) for y in ys],
           "difference_px": _nested(diff), "predicted_px": _nested(pred) if pred is not None else None,
           "median_px": float(np.median(diff[fin])) if fin.any() else None,
           "worst_px": float(diff[fin].max()) if fin.any() else None,
           "rotation_deg": math.degrees(float(w.norm())), "rotation_fitted": bool(rotation)}
    if pred is None:
        return out | {"predicted_median_px": None, "predicted_worst_px": None, "rms_ratio": None,
                      "consistent": None, "verdict": "no prediction: a calibration has no intrinsics covariance"}
    rms_pred = float(np.sqrt(np.mean(pred[fin] ** 2))) if fin.any() else math.nan
    ratio = float(np.sqrt(np.mean(diff[fin] ** 2))) / rms_pred if rms_pred > 0 else math.nan
    out |= {"predicted_median_px": float(np.median(pred[fin])) if fin.any() else None,
            "predicted_worst_px": float(pred[fin].max()) if fin.any() else None,
            "rms_ratio": ratio if math.isfinite(ratio) else None}
    silent = _silent_sigma(size, rms_pred)
    if silent:
        return out | {"consistent": None, "verdict": f"no verdict: {silent}"}
    return out | {"consistent": bool(ratio <= 2.0),
                  "verdict": ("consistent: the calibrations differ by what their uncertainties predict"
                              if ratio <= 2.0 else
                              f"inconsistent: they differ {ratio:.1f}× more than their uncertainties predict "
                              f"(an error the σ do not cover: board shape, a model misfit, a changed camera)")}


def _silent_sigma(size, rms_pred: float) -> str | None:
    """Why the predicted σ cannot judge a difference (a clause), or None."""
    W, H = size
    if min(W, H) < MIN_COMPARE_SIDE_PX:
        return (f"a {W}×{H} px image is too small to compare projections (under {MIN_COMPARE_SIDE_PX} px a side, "
                f"the best-fitting rotation absorbs any difference)")
    if not (math.isfinite(rms_pred) and rms_pred > 0):
        return "the predicted σ is 0 or not finite, so it says nothing about the difference"
    if rms_pred > math.hypot(W, H):
        return (f"the predicted σ ({rms_pred:.3g} px RMS) is larger than the image, so it says nothing about the "
                f"difference")
    return None


def _nested(a):
    return [[None if not np.isfinite(x) else round(float(x), 6) for x in row] for row in a]


def covariance_problem(names, matrix) -> str | None:
    """Why {names, matrix} is not a covariance of intrinsics (a clause naming the field), or None.

    A covariance is a square matrix of finite numbers, one row per name (`INTRINSIC_NAMES`), symmetric, with no
    negative variance of any parameter or combination (positive semi-definite, to rounding) and no σ above
    `MAX_SIGMA` (in the parameter's unit)."""
    if not (isinstance(names, list) and names and all(n in INTRINSIC_NAMES for n in names)
            and len(set(names)) == len(names)):
        return f"intrinsics_covariance.names: expected distinct names among {', '.join(INTRINSIC_NAMES)}"
    n = len(names)
    if not (isinstance(matrix, list) and len(matrix) == n and all(
            isinstance(row, list) and len(row) == n and all(
                isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in row)
            for row in matrix)):
        return f"intrinsics_covariance.matrix: expected {n}×{n} finite numbers"
    C = np.array(matrix, dtype=np.float64)
    d = np.diag(C)
    if (d < 0).any():
        i = int(np.argmin(d))
        return f"intrinsics_covariance.matrix: the variance of {names[i]} is negative ({d[i]:.3g})"
    if (d > MAX_SIGMA ** 2).any():
        i = int(np.argmax(d))
        return (f"intrinsics_covariance.matrix: the variance of {names[i]} ({d[i]:.3g}) is not an uncertainty "
                f"(σ above {MAX_SIGMA:g})")
    s = np.sqrt(d)
    scale = np.outer(s, s)
    if (np.abs(C - C.T) > 1e-6 * scale + 1e-300).any():
        return "intrinsics_covariance.matrix: not symmetric"
    live = s > 0
    if (np.abs(C[~live]) > 0).any():
        return "intrinsics_covariance.matrix: a parameter of zero variance has non-zero covariances"
    if live.any():
        corr = C[np.ix_(live, live)] / scale[np.ix_(live, live)]
        if float(np.linalg.eigvalsh(corr).min()) < -1e-6:
            return ("intrinsics_covariance.matrix: not positive semi-definite (a combination of the parameters "
                    "has a negative variance)")
    return None


def covariance_from_calib(calib: dict, check: bool = True):
    """(13, 13) intrinsics covariance (`INTRINSIC_NAMES` order) from a CALIB.json dict, or None without one.

    A file written before θL and the tilt axis were among the names gets their variances from `sigma`
    (theta_L_deg, tilt_axis_deg; uncorrelated with the rest). `check` False: a fit's own covariance, taken as
    it is (rounding may leave it a hair indefinite).

    Raises:
        ValueError: the file's `intrinsics_covariance` is not a covariance (`covariance_problem`, one line)."""
    ic = calib.get("intrinsics_covariance")
    if not isinstance(ic, dict) or "matrix" not in ic or "names" not in ic:
        return None
    problem = covariance_problem(ic["names"], ic["matrix"]) if check else None
    if problem:
        raise ValueError(problem)
    C = torch.zeros(len(INTRINSIC_NAMES), len(INTRINSIC_NAMES), dtype=torch.float64)
    idx = [INTRINSIC_NAMES.index(n) for n in ic["names"]]
    M = torch.tensor(ic["matrix"], dtype=torch.float64)
    C[torch.tensor(idx)[:, None], torch.tensor(idx)[None, :]] = M
    sigma = calib.get("sigma") or {}
    for name in ("theta_L_deg", "tilt_axis_deg"):
        s = sigma.get(name)
        if name not in ic["names"] and isinstance(s, (int, float)) and math.isfinite(s) and 0 <= s <= MAX_SIGMA:
            i = INTRINSIC_NAMES.index(name)
            C[i, i] = float(s) ** 2
    return C
