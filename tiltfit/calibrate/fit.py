"""The least-squares fit of a tilt-lens camera: the problem over its free parameters, the solve with the noise
levels estimated, and the uncertainties. The starting camera is `tiltfit.calibrate.start`'s, the nested-model tests
`tiltfit.select.nested`'s, and the calibration flow built on them (which terms to free, the checks after the fit)
`tiltfit.calibrate.flow`'s:

    calibrate(obs, mode="unified" | "tilt" | "joint", init=None, options=FitOptions()) -> FitResult
                                                                        (tiltfit.calibrate.flow)
    fit_geometry(camera, obs, options, mode)                            -> FitResult   (corners only)

Modes (the paper's two stages, and one fit of everything):
    unified  stage 1, eq (3): θF = 0; fits w, U, d and every view's R, T from corners and blur.
    tilt     stage 2, eq (4): w, U, d held at `init`'s values; fits θF and every view's R, T. Because the
             lens tilts about its centre, the true U moves with the tilt (hinge rule); holding U biases θF.
    joint    w, U, d, θF and the poses together; `init` (if any) is only the starting point.
The principal point is fitted where the views support it (a likelihood-ratio test on the corners; held at the
image centre, or `init`'s, otherwise), or as `FitOptions.free_principal_point` forces. Distortion terms are
chosen by their held-out error (`tiltfit.select.held_out.select_distortion`).

Objective: ½ Σ ρ((r_i / σ_g)²) over reprojection residuals (group g = corners, pixels) and blur residuals
(g = blur, pixels); ρ is quadratic, Huber or Cauchy. The noise levels σ_g are estimated from the residuals
(variance components, with the degrees of freedom each group uses) unless given. Minimised by
Levenberg–Marquardt with Marquardt's diagonal scaling on the free parameters of `LensCamera`, its
Jacobian in closed form (`LensCamera.jacobian`), solved by `tiltfit.solve` (Schur complement of the per-view
poses), robust losses by iterative reweighting.

Uncertainties: C = s² (Jᵀ W J)⁻¹ on the free parameters (s² the residual variance factor), propagated to
w, U, d, θF, θL (exact Scheimpflug), θL of the paper's eq (1) and f by the Jacobian of those functions. In
`tilt` mode the held w, U, d carry the uncertainties `init` gives for them (through the fit's implicit
dependence on them), but not the bias of holding U.
The reported σ use the error model `FitOptions.sigma_model`: "views" (default) replaces C on the global
parameters by the per-view cluster-robust covariance (corner and blur errors correlated within a view), never
below the classical C (`tiltfit.uncertainty.covariance`); the classical σ stay in `FitResult.sigma_classical`.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import torch

from renderer.cameras.distortion import MODELS as DISTORTION_MODELS

from tiltfit.target.shape import BOARD_MODELS
from tiltfit.calibrate.model import (BLUR_MODELS, MIN_CORNERS, ROBUST_LOSSES, Observations, LensCamera,
                    distortion_parameter_names, residuals)
from tiltfit.calibrate.fit_sigma import DERIVED_KEYS, derived, uncertainties
from tiltfit.solve import LMResult, SolverError, solve_rescaling
from tiltfit.solve.blocks import DenseCovariance
from tiltfit.calibrate.problem import FitError, _Problem, _lm, _robust_options

MODES = ("unified", "tilt", "joint")
# A calibrated view reprojecting worse than this (RMS per corner; 5 px per coordinate) means mismatched data.
MAX_RMS_REPROJECTION_PX = 7.0

_MODE_FREE = {
    "unified": ("lens", "pose"),
    "tilt": ("theta_F", "pose"),
    "joint": ("lens", "theta_F", "pose"),
}


@dataclass(frozen=True)
class FitOptions:
    """Settings of `calibrate` (defaults in brackets).

    Attributes:
        robust: None, "huber" or "cauchy" [None]; `robust_scale` is the threshold in σ [3.0].
        free_principal_point: True fits the principal point, False holds it (at the image centre or `init`'s);
            None fits it where the views support it: free unless the likelihood-ratio test on the corners
            (`_geometry_with_principal_point`) finds it not justified; held when `model_selection` is off [None].
        held_out_folds: K of the K-fold held-out error that chooses the distortion model under "auto" [5].
        held_out_start: where each held-out fold's fit starts its training views' poses: "fit" (the fit on all
            views that the fold is scored for: its poses of those views, beside its lens and board) or "pnp" (PnP
            with that lens, as before; the fold then converges to the same minimum within the solver's tolerance)
            (`tiltfit.select.held_out.held_out_rms`) ["fit"].
        uncertainties: compute the covariance and σ (False: only the fitted camera is wanted, as in the held-out
            folds; a fit whose parameters are not all determined is then no error) [True].
        sigma_model: the error model of the σ: "views" (corner errors may be correlated within a view: per-view
            cluster-robust covariance with the classical one as floor, `tiltfit.uncertainty.covariance`) or "classical"
            (independent noise, s² (JᵀWJ)⁻¹) ["views"]. The fitted values do not depend on it.
        sigma_corner_px, sigma_blur_px: noise levels; None estimates them from the residuals [None].
        blur_model: the camera's blur model ("ellipse", "first_order", "paper") ["ellipse"].
        nominal_focal_mm: starting w when no `init` gives one; None estimates it from homographies [None].
        max_iterations: Levenberg–Marquardt iterations per solve [200].
        noise_iterations: re-estimations of σ_g (each followed by a warm re-solve) [4].
        model_selection: run the θF / principal-point tests [True].
        alpha: significance level of the tests [0.01].
        progress: callable(str) for progress lines, or None [None].
        distortion: "none", "k1", "k1k2", "opencv5", "rational5", "rational" or "auto" (the model with the smallest
            held-out error whose radial mapping is one-to-one over the image, `tiltfit.select.held_out`) ["none"].
        max_rms_px: a view reprojecting worse than this (RMS per corner) is an error (mismatched data); None: no
            check [7.0].
        min_corners: views with fewer detected corners are skipped (listed in `FitResult.skipped`)
            [`tiltfit.calibrate.model.MIN_CORNERS`, 6].
        blur_floor_px: blur widths all below this carry no information on U and d (sharp images): the fit is
            geometric and U, d are reported undetermined [1.0].
        outlier_factor: a view whose RMS exceeds this many times the median view RMS is flagged [3.0].
        blur_offset: fit a constant offset of the measured blur widths (the blur detector's bias) beside the
            lens [True]. Without it such a bias goes into d and U, and their σ (which only sees the scatter)
            is too small: on rendered captures a −0.011 px bias put stage 1's d 8–12σ off. Held at 0 when the
            depths do not straddle the plane of focus (then it is not separable from U), and in "tilt" mode,
            which holds `init`'s offset with its w, U, d (the same detector's bias, calibrated in stage 1).
        distortion_centre: where the distortion of a tilted lens is centred: "auto" tests the lens's own axis
            against the principal point in the joint fit (`tiltfit.calibrate.distortion_centre`) and
            keeps the one the data support; "sensor" holds it at the principal point (the model before the
            lens-axis centre, and every other library's untilted one) ["auto"].
        board: the target's shape (`tiltfit.target.shape.BOARD_MODELS`): "flat" (the target file's points as they are),
            "warp" (sag and print scale), "free" (every point, OpenCV's release-object method) or "auto" (the
            simplest the held-out views support, `tiltfit.select.board.select_board`) ["flat"].
    """

    robust: str | None = None
    robust_scale: float = 3.0
    free_principal_point: bool | None = None
    held_out_folds: int = 5
    held_out_start: str = "fit"
    sigma_corner_px: float | None = None
    sigma_blur_px: float | None = None
    blur_model: str = "ellipse"
    nominal_focal_mm: float | None = None
    max_iterations: int = 200
    noise_iterations: int = 4
    model_selection: bool = True
    alpha: float = 0.01
    progress: object = None
    distortion: str = "none"
    max_rms_px: float | None = MAX_RMS_REPROJECTION_PX
    min_corners: int = MIN_CORNERS
    blur_floor_px: float = 1.0
    outlier_factor: float = 3.0
    blur_offset: bool = True
    uncertainties: bool = True
    distortion_centre: str = "auto"
    board: str = "flat"
    sigma_model: str = "views"

    def __post_init__(self):
        if self.robust not in ROBUST_LOSSES:
            raise ValueError(f"robust: expected one of {ROBUST_LOSSES}, got {self.robust!r}")
        if self.blur_model not in BLUR_MODELS:
            raise ValueError(f"blur_model: expected one of {BLUR_MODELS}, got {self.blur_model!r}")
        if self.max_iterations < 1:
            raise ValueError(f"max_iterations: expected at least 1, got {self.max_iterations}")
        if self.held_out_start not in ("fit", "pnp"):
            raise ValueError(f"held_out_start: expected 'fit' or 'pnp', got {self.held_out_start!r}")
        if self.distortion_centre not in ("auto", "sensor"):
            raise ValueError(f"distortion_centre: expected 'auto' or 'sensor', got {self.distortion_centre!r}")
        if self.board not in BOARD_MODELS + ("auto",):
            raise ValueError(f"board: expected one of {BOARD_MODELS + ('auto',)}, got {self.board!r}")
        if self.sigma_model not in ("views", "classical"):
            raise ValueError(f"sigma_model: expected 'views' or 'classical', got {self.sigma_model!r}")
        if self.distortion not in DISTORTION_MODELS + ("auto",):
            raise ValueError(f"distortion: expected one of {DISTORTION_MODELS + ('auto',)}, got {self.distortion!r}")


def per_corner_rms_px(rss: dict) -> float:
    """The reprojection RMS per corner (px; OpenCV's `calibrateCamera` definition) of a fit's residual sums
    (`FitResult.rss`: the corners' RSS over two rows a corner): the one place it is computed."""
    return math.sqrt(rss["corners"] / max(rss["n_corners"] // 2, 1))


@dataclass
class FitResult:
    """What `calibrate` found.

    Attributes:
        mode: "unified", "tilt" or "joint".
        camera: the fitted camera (float64; free/frozen state as fitted).
        values: w_mm, U_mm, d_mm, f_mm, theta_F_deg, theta_L_deg, theta_L_paper_deg, tilt_axis_deg (φ, the tilt
            axis's direction: 0 unless the tilt-axis test freed it), principal_point_px.
        sigma: one-σ uncertainties of the same keys (0 for held ones without an `init` sigma).
        views: per view: image, R, T_mm, rms_reprojection_px, rms_blur_px, n_points, sigma_rvec_deg,
            sigma_T_mm.
        noise: estimated (or given) sigma_corner_px, sigma_blur_px.
        parameter_names, covariance: the free parameters (stored units of the camera, flat order) and their
            covariance (`tiltfit.solve.covariance`: `.dense()` the matrix, `.diagonal()`, `.submatrix(idx)`;
            by blocks, so thousands of views need no (P, P) matrix); None when `FitOptions.uncertainties` is off.
        chi2: Σ ρ((r/σ)²) at the solution; n_residuals, n_parameters; iterations; runtime_s.
        model_selection: per tested parameter, the test's numbers and a verdict (see the module docstring).
        distortion_model: the distortion terms fitted ("none", "k1", …); distortion_selection: the tests that
            chose them under `distortion="auto"` (one entry per candidate).
        undetermined: keys the data cannot determine (e.g. "U_mm", "d_mm" from sharp images); their values
            are not meaningful and CALIB.json writes null.
        skipped: views left out, [{image, reason}]; notes: one-line remarks for the user (stderr); warnings:
            one-line warnings (the blur model does not describe the lens).
        held_out: the K-fold held-out error of the chosen distortion model with the final principal-point state
            when the selection computed it (`tiltfit.select.held_out.held_out_rms`), else None.
        free_principal_point: whether the principal point was fitted.
        board: the target's fitted shape (`tiltfit.target.shape.Board`; None: the target file's points as they are);
            board_selection: the held-out test that chose its model (`tiltfit.select.board.select_board`'s entries).
        choice_variance: {"distortion" | "board": `tiltfit.select.held_out.choice_variance`'s dict}: the spread of the
            focal length and principal point over the models an automatic choice could not tell apart, added to
            `sigma` by `tiltfit.calibrate.flow` (`sigma_model["model_choice"]` records it).
        deferred_sigma: None, or a function giving this fit made again with the per-view error model where only the
            classical σ were computed (`with_deferred_sigma`): a geometric fit that a blur fit replaces.
    """

    mode: str
    camera: LensCamera
    values: dict
    sigma: dict
    views: list
    noise: dict
    parameter_names: list
    covariance: object
    chi2: float
    n_residuals: int
    n_parameters: int
    iterations: int
    runtime_s: float
    rss: dict = field(default_factory=dict)
    model_selection: dict = field(default_factory=dict)
    distortion_model: str = "none"
    distortion_selection: list = field(default_factory=list)
    undetermined: list = field(default_factory=list)
    skipped: list = field(default_factory=list)
    notes: list = field(default_factory=list)
    warnings: list = field(default_factory=list)
    held_out: dict | None = None
    free_principal_point: bool = False
    board: object = None
    board_selection: list = field(default_factory=list)
    sigma_classical: dict = field(default_factory=dict)
    sigma_model: dict = field(default_factory=dict)
    intrinsics_covariance: dict | None = None
    choice_variance: dict = field(default_factory=dict)
    deferred_sigma: object = None


#: What `with_deferred_sigma` takes from the fit made again: everything the error model sets.
_SIGMA_FIELDS = ("sigma", "views", "noise", "covariance", "sigma_classical", "sigma_model", "intrinsics_covariance")


def with_deferred_sigma(fit: FitResult) -> FitResult:
    """`fit` with the σ of its `FitOptions.sigma_model` where they were deferred (`FitResult.deferred_sigma`): made
    from the same solve's Jacobian and residuals and put in `fit` in place (its choices and records stay)."""
    if fit.deferred_sigma is None:
        return fit
    full = fit.deferred_sigma()
    for k in _SIGMA_FIELDS:
        setattr(fit, k, getattr(full, k))
    if fit.board is not None and full.board is not None:
        fit.board.sigma = full.board.sigma
    fit.deferred_sigma = None
    return fit


# ---------------------------------------------------------------------------------------------------------
# The solve and the uncertainties
# ---------------------------------------------------------------------------------------------------------

def _group_sigma(prob: _Problem, r_raw: torch.Tensor, normal, robust: str | None) -> tuple[float, float]:
    """Variance components: σ_g² = Σ_g r² / (n_g − tr_g(hat matrix)) (MAD-based under a robust loss); the
    hat matrix's diagonal from the normal equations' blocks (`normal.leverages`)."""
    try:
        cov = normal.covariance()
    except RuntimeError:
        cov = DenseCovariance(torch.linalg.pinv(normal.dense()))
    lev = normal.leverages(cov)
    out = []
    for rows, n in ((prob.corner_rows, prob.n_corner), (prob.blur_rows, prob.n_blur)):
        if n == 0:
            out.append(1.0)
            continue
        used = float(lev[rows].sum())
        dof = max(n - used, 1.0)
        rg = r_raw[rows]
        if robust in (None, "none"):
            s2 = float((rg * rg).sum()) / dof
        else:
            s2 = (1.4826 * float(rg.abs().median())) ** 2 * n / dof
        out.append(math.sqrt(max(s2, 1e-24)))
    return out[0], out[1]


def _solve(camera: LensCamera, obs: Observations, options: FitOptions, sigma=None, say=None, board=None):
    """Fit the camera's free parameters in place; returns (problem, LM result, σ_corner, σ_blur).

    Unless both σ are given, alternates solving with re-estimating them until they change by less than
    0.1 % (at most `noise_iterations` re-estimations), then solves once more with the final σ if needed.
    """
    prob = _Problem(camera, obs, board=board)
    sc = options.sigma_corner_px or (sigma[0] if sigma else 1.0)
    sb = options.sigma_blur_px or (sigma[1] if sigma else 1.0)
    one_group = (prob.n_corner == 0 or prob.n_blur == 0) and options.robust in (None, "none")
    # One group without uncertainties (held-out folds, candidates scored by their residuals): σ moves no
    # minimiser and nothing reads it, so its estimate (a covariance and the leverages) is not made.
    estimate = (options.sigma_corner_px is None or options.sigma_blur_px is None) and not (
        one_group and not options.uncertainties)
    lm_options = _robust_options(options.robust, options.robust_scale, options.max_iterations)
    sigma_now = [sc, sb]   # σ_corner, σ_blur of the current solve

    def solve(x):
        return _lm(prob.evaluate(prob.scale(*sigma_now)), x, prob.blocks, prob.view_rows, lm_options, prob.row_points)

    def rescale(res, k: int, last: bool):
        if not estimate or last:
            return res, False
        sc, sb = sigma_now
        new_sc, new_sb = _group_sigma(prob, res.r / prob.scale(sc, sb), res.normal, options.robust)
        new_sc = options.sigma_corner_px or new_sc
        new_sb = options.sigma_blur_px or new_sb
        changed = abs(new_sc / sc - 1) > 1e-3 or abs(new_sb / sb - 1) > 1e-3
        if say:
            say(f"  pass {k + 1}: cost {res.cost:.6g} after {res.iterations} iterations; "
                f"σ_corner {new_sc:.4g} px, σ_blur {new_sb:.4g} px")
        if not changed:
            return res, False
        sigma_now[:] = new_sc, new_sb
        if one_group:
            # One σ scales every residual alike: the minimiser stays, and the estimate is final.
            return res.scaled(sc / new_sc if prob.n_corner else sb / new_sb), False
        return res, True

    res, iterations = solve_rescaling(solve, rescale, prob.x0(), options.noise_iterations + 1)
    res.iterations = iterations
    prob.write_back(res.x)
    return prob, res, sigma_now[0], sigma_now[1]




def _set_free(camera: LensCamera, mode: str, free_pp: bool):
    camera.freeze("all")
    camera.free(*_MODE_FREE[mode])
    if free_pp:
        camera.free("principal_point")
    if mode == "unified":
        with torch.no_grad():
            camera.theta_F.zero_()


def _group_rss(prob: _Problem, res: LMResult, scale: torch.Tensor) -> dict:
    raw = res.r / scale
    return {"corners": float((raw[prob.corner_rows] ** 2).sum()), "blur": float((raw[prob.blur_rows] ** 2).sum()),
            "n_corners": prob.n_corner, "n_blur": prob.n_blur}


def _fit_camera(camera: LensCamera, obs: Observations, options: FitOptions, init_sigma=None, say=None,
                sigma=None, mode: str = "joint", board=None, defer_sigma: bool = False):
    """Fit the camera's free parameters (and `board`'s, a `tiltfit.target.shape.Board`, if given: fitted in place and
    kept in the result's `board`, the observations then seen as its points). `defer_sigma`: the σ of
    `options.sigma_model` "views" are made only when `with_deferred_sigma` asks (from this solve's Jacobian and
    residuals: the same numbers as at once); until then the result carries the classical ones."""
    t0 = time.perf_counter()
    prob, res, sc, sb = _solve(camera, obs, options, sigma, say, board)
    if board is not None:
        from tiltfit.target.shape import with_points

        obs = with_points(obs, board.points())
    scale = prob.scale(sc, sb)
    defer = defer_sigma and options.uncertainties and options.sigma_model != "classical"

    def sigma_of(model: str):
        try:
            return uncertainties(prob, res, scale, init_sigma, model)
        except SolverError:
            raise FitError("the fit is degenerate: the free parameters are not all determined by the data") from None

    if options.uncertainties:
        C, sig, view_sig, s2, extras = sigma_of("classical" if defer else options.sigma_model)
    else:  # only the fitted camera is wanted (held-out folds): σ unknown, and a near-degenerate fit is no error
        C, view_sig, s2, extras = None, [{}] * obs.n_views, math.nan, {}
        sig = {k: math.nan for k in DERIVED_KEYS} | {"principal_point_px": [math.nan, math.nan],
                                                       "distortion": [math.nan] * 8}
    with torch.no_grad():
        vals = derived(camera, dict(camera.named_parameters()))
        rc, rb = residuals(camera, obs).rms_per_view()
    values = {k: float(vals[i]) for i, k in enumerate(DERIVED_KEYS)}
    values["principal_point_px"] = [float(vals[8]), float(vals[9])]
    values["blur_offset_px"] = float(camera.blur_offset_px.detach())
    R = camera.R.detach()
    T = camera.T_mm.detach()
    n_points = obs.corner_mask.sum(-1).tolist()
    plain = [{"image": obs.names[v], "R": R[v].tolist(), "T_mm": T[v].tolist(), "rms_reprojection_px": float(rc[v]),
              "rms_blur_px": float(rb[v]), "n_points": int(n_points[v])} for v in range(obs.n_views)]
    fit = FitResult(
        mode=mode, camera=camera, values=values, sigma=sig, views=[{**p, **s} for p, s in zip(plain, view_sig)],
        noise={"sigma_corner_px": sc, "sigma_blur_px": sb, "variance_factor": s2},
        parameter_names=res.layout.flat_names(), covariance=C, chi2=2.0 * res.cost,
        n_residuals=prob.n_corner + prob.n_blur, n_parameters=res.x_flat.numel(), iterations=res.iterations,
        runtime_s=time.perf_counter() - t0, rss=_group_rss(prob, res, scale), board=_fitted_board(board, sig),
        **extras)
    if defer:
        def deferred() -> FitResult:
            C, sig, view_sig, s2, extras = sigma_of(options.sigma_model)
            return replace(fit, sigma=sig, views=[{**p, **s} for p, s in zip(plain, view_sig)], covariance=C,
                           noise=dict(fit.noise, variance_factor=s2), board=_fitted_board(board, sig), **extras)

        fit.deferred_sigma = deferred
    return fit


def _fitted_board(board, sigma: dict):
    """The fitted board with its parameters' σ (None without a board)."""
    if board is None:
        return None
    if board.n_params and "board" in sigma:
        board.sigma = torch.tensor(sigma["board"], dtype=torch.float64)
    return board


def without_blur(obs: Observations) -> Observations:
    """The same observations with every blur width removed (geometry only)."""
    return Observations(obs.points_mm, obs.corners_px, torch.full_like(obs.blur_px, math.nan), obs.image_size_px,
                        obs.pixel_pitch_mm, list(obs.names))


def _set_free_geometry(camera: LensCamera, mode: str, free_pp: bool, distortion: str | None):
    """Free the geometric parameters; `distortion` None holds the coefficients as they are, a model name frees
    its terms and sets the others to 0."""
    camera.freeze("all")
    camera.free("pose")
    if mode != "tilt":
        camera.free("w")
    if free_pp:
        camera.free("principal_point")
    if distortion is not None:
        free = distortion_parameter_names(distortion)
        with torch.no_grad():
            for n in camera.parameter_names("distortion"):
                if n not in free:
                    getattr(camera, n).zero_()
        camera.free(*free)


def fit_geometry(camera: LensCamera, obs: Observations, options: FitOptions, mode: str = "unified",
                 say=None, hold_distortion: bool = False, board=None, defer_sigma: bool = False) -> FitResult:
    """Fit w (unless `mode` is "tilt"), the poses, the principal point if `options.free_principal_point` is
    True and the distortion on the corners alone (blur widths ignored; U, d, θF held).

    `options.distortion` names the terms to free (the others are set to 0, except with `hold_distortion`, which
    keeps the camera's coefficients fixed as they are); "auto" is `tiltfit.calibrate.flow.fit_geometry`'s.
    `board` (a `tiltfit.target.shape.Board`) is fitted beside the camera, starting from its parameters.
    `defer_sigma`: the per-view σ made only when `with_deferred_sigma` asks (`_fit_camera`).
    """
    if options.distortion == "auto" and not hold_distortion:
        raise ValueError("distortion: auto is chosen by held-out error in tiltfit.calibrate.flow.fit_geometry; "
                         "this fit takes a named model")
    quiet = replace(options, model_selection=False, progress=None)
    cam = camera.copy()
    _set_free_geometry(cam, mode, bool(options.free_principal_point), None if hold_distortion else options.distortion)
    fit = _fit_camera(cam, without_blur(obs), quiet, mode=mode, board=board, defer_sigma=defer_sigma)
    fit.distortion_model = "none" if hold_distortion else options.distortion
    return fit
