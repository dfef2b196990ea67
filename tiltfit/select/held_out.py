"""Held-out reprojection error, and the distortion model it chooses.

The fit RMS measures how well the model explains the corners it was fitted to; with many parameters
(distortion terms) it always drops. The held-out error is the honest one: split the views into K folds;
for each fold fit the lens (w, principal point, distortion, as the full fit did) on the other views, then
hold that lens fixed and fit only each held-out view's pose; the RMS of those views' residuals is what the
lens predicts. Blur widths are not used (geometry only). RMS per corner, OpenCV's definition:
sqrt(mean(dx² + dy²)).

    held_out_rms(obs, options, folds=5) -> {"rms_px", "per_view_px", "folds", "median_view_px"}
    select_distortion(camera, obs, options, mode) -> FitResult      (`FitOptions.distortion` "auto")
    radial_fold(camera, obs) -> None | str                          (a radial mapping that folds in the image)
    undetermined_distortion(fit, model, n_views) -> None | str      (coefficients the views do not determine)
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import torch

from renderer.cameras.distortion import MODEL_TERMS, MODELS as DISTORTION_MODELS

from tiltfit.calibrate.fit import FitError, FitOptions, FitResult, fit_geometry, per_corner_rms_px, without_blur
from tiltfit.calibrate.start import initialize
from tiltfit.calibrate.model import Observations, LensCamera

# Models whose held-out errors lie within this fraction of the best are not told apart by K-fold validation
# on a few dozen views (its fold-to-fold scatter is of this order); the one with the fewest terms is chosen.
HELD_OUT_TOLERANCE = 0.01
MAX_UNDISTORTED_RADIUS = 60.0  # tan of 89°: the radial mapping is checked up to rays 89° off the axis
# A distortion model asked for by name (one of `CHECKED_MODELS`) is refused where its radial mapping at the
# image corner is uncertain by more than this (pixels, 1σ from the fit's covariance): the views do not
# determine its coefficients. GoPro views (data/real/gopro_wide, benchmarks/calibration/rational_views.py), rational: 1 view
# ±24 px, 2 views ±19 px, 3 views ±2.1 px, 10 views ±0.6 px, 35 views ±0.27 px.
MAX_MAPPING_SIGMA_PX = 5.0
# The models so checked: the rational model's numerator and denominator terms trade against each other over
# the radii one view covers (1 view: σ of 1.5-1.9 on coefficients of order 1; issue 24 found 3.6e5). Models
# with fewer terms keep their fold warning only: opencv5 / k1k2 / k1 from one GoPro view are uncertain by
# 31 / 6 / 11 px at the corner, and a general rule would refuse them too (k1 even from 35 views, which it
# misfits).
# rational5 (k1 k2 p1 p2 k4) is checked as well: one denominator term against two numerator terms, determined by
# a dozen GoPro views (σ of 2-5 % on k1 and k4), but on a narrow lens k1 and k4 trade as the rational model's do
# (industrial_ds1, free board: ±8.6 px at the corner, refused; flat board k1 3.8 ± 16).
CHECKED_MODELS = ("rational5", "rational")
# The automatic choice (`select_distortion`) also refuses one of the `CHECKED_MODELS` whose projection is uncertain
# by more than this anywhere in the image (pixels, 1σ: CALIB.json's `projection_uncertainty.worst_px`, from the
# fit's intrinsics covariance): its coefficients trade against each other (numerator against denominator) and
# only the radii the boards cover pin the mapping down. 12 GoPro views (data/real/gopro_wide): rational 79-181 px
# with the flat board, 14 px with the free one (k1 905 ± 3118, k4 901 ± 3089), opencv5 3.9 px; the three
# 12-view thirds of the set 55-2200 px against opencv5's 2.1-6.0 (benchmarks/results/selection.md);
# industrial_ds1 (20 views), flat board: rational 2.0 px (accepted). A model asked for by name is only held to
# `MAX_MAPPING_SIGMA_PX`.
MAX_PROJECTION_SIGMA_PX = 5.0
# ... or, where the views leave even the polynomial model `REFERENCE_MODEL` that uncertain (the image's corners
# beyond the boards: its worst σ on the GoPro thirds is 2.9-10.5 px), by more than `PROJECTION_SIGMA_FACTOR` times
# that model's worst σ on the same views: a model no more uncertain than opencv5 away from the boards is no less
# determined. GoPro, free board (benchmarks/results/rational_terms.md): rational5 2.9-7.4 px where opencv5 has
# 2.9-10.5 (at most 2.0×; accepted), rational 22-1700 px (4.2-580×; refused) on 11-12 views, 10.9 against 7.8 px
# (1.4×; accepted) on all 35.
REFERENCE_MODEL = "opencv5"
#: How `undetermined_for_choice`'s refusal begins (a refusal the fitted board may lift: `tiltfit.calibrate.flow`).
PROJECTION_REFUSAL = "coefficients not determined by these views"
PROJECTION_SIGMA_FACTOR = 3.0
#: The one-standard-error rule of the automatic choices (`_fewest_terms_within_one_se`): a model with fewer terms
#: is kept where the best model's held-out gain over it is at most this many standard errors over the views.
ONE_SE = 1.0


def predict_views(camera, obs: Observations, options: FitOptions = FitOptions(), poses=None):
    """Fit only the poses of `obs`'s views with `camera`'s lens held (w, U, d, θF, principal point,
    distortion); returns the FitResult (its RMS is the prediction error). `poses` ((rvec (V, 3), T_mm (V, 3)), e.g.
    a fit's of these views with a nearby lens) start them; None: PnP."""
    held = replace(options, distortion="none", free_principal_point=False, model_selection=False, progress=None,
                   max_rms_px=None)
    cam = keep_distortion_axis(initialize(obs, "tilt", init=camera, options=held, blur=False, poses=poses), camera)
    return fit_geometry(cam, without_blur(obs), held, mode="tilt", hold_distortion=True)


def keep_distortion_axis(camera: LensCamera, start: LensCamera | None) -> LensCamera:
    """`camera` (a geometric start made by `initialize`, which sets θF = 0 and centres the distortion on the
    principal point) given `start`'s tilt (θF, φ) and centre where `start`'s distortion is about its lens axis:
    the corners then see the distortion where the lens puts it (θF and φ are held by the geometric fits)."""
    if start is None or start.distortion_centre != "lens_axis":
        return camera
    with torch.no_grad():
        camera.theta_F.copy_(start.theta_F)
        camera.phi.copy_(start.phi)
    camera.distortion_centre = "lens_axis"
    return camera


def held_out_rms(obs: Observations, options: FitOptions = FitOptions(), folds: int = 5,
                 distortion: str | None = None, start: LensCamera | None = None, board: str | None = None) -> dict:
    """K-fold held-out reprojection RMS (pixels per corner) of a geometric calibration with `options`' settings.

    Args:
        obs: all views (views with too few corners should already be removed).
        options: the fit's settings (distortion model, principal point: free only when True).
        folds: K (views are dealt round-robin into folds; at most one fold per view).
        distortion: overrides options.distortion (a model name, not "auto").
        start: a camera whose lens (w, principal point, distortion) starts each fold's fit (e.g. the fit on all
            views); None starts from the homographies without distortion.
        board: a board model (`tiltfit.target.shape.BOARD_MODELS`) fitted with the lens in each fold and held with it
            when the fold's views are predicted, or a `tiltfit.target.shape.Board` of that model whose parameters start
            each fold's (as `start` starts its lens); None: the target's points as they are.
    Returns:
        {"rms_px": RMS over all held-out corners, "per_view_px": [...] in obs order, "folds": K,
        "median_view_px"}.
    """
    V = obs.n_views
    K = max(2, min(int(folds), V))
    if V < 3:
        raise FitError(f"held-out error needs at least 3 views, got {V}")
    opts = replace(options, model_selection=False, progress=None, max_rms_px=None, uncertainties=False,
                   free_principal_point=bool(options.free_principal_point),
                   distortion=distortion or options.distortion)
    if opts.distortion == "auto":
        raise ValueError("held_out_rms: give the distortion model (not auto)")
    per_view = [math.nan] * V
    sq, n = 0.0, 0
    # `start` fitted on these views (`FitOptions.held_out_start` "fit"): its poses of each fold's training views
    # start the fold's fit, its poses of the held-out views their prediction (no PnP)
    warm = opts.held_out_start == "fit" and start is not None and start.n_views == V
    for k in range(K):
        test = [v for v in range(V) if v % K == k]
        train = [v for v in range(V) if v % K != k]
        tr = obs.subset(train)
        poses = (start.rvec.detach()[train], start.T_mm.detach()[train]) if warm else None
        held_poses = (start.rvec.detach()[test], start.T_mm.detach()[test]) if warm else None
        cam = keep_distortion_axis(initialize(tr, "unified", init=start, options=opts, blur=False, poses=poses),
                                   start)
        if board is None:
            fit = fit_geometry(cam, tr, opts, mode="unified")
            pred = predict_views(fit.camera, obs.subset(test), opts, held_poses)
        else:
            from tiltfit.target.shape import Board, with_points

            b = Board(tr.points_mm, board.model, board.params) if isinstance(board, Board) else \
                Board(tr.points_mm, board)
            fit = fit_geometry(cam, tr, opts, mode="unified", board=b)
            pred = predict_views(fit.camera, with_points(obs.subset(test), fit.board.points()), opts, held_poses)
        sq += pred.rss["corners"]
        n += pred.rss["n_corners"] // 2
        for v, view in zip(test, pred.views):
            per_view[v] = view["rms_reprojection_px"]
    return {"rms_px": math.sqrt(sq / max(n, 1)), "per_view_px": per_view, "folds": K,
            "median_view_px": float(np.nanmedian(per_view))}


def _radial_coefficients(camera: LensCamera) -> tuple[float, ...]:
    """k1, k2, k3 (numerator) and k4, k5, k6 (denominator) of the camera's radial mapping."""
    k = [float(c) for c in camera.distortion.detach()]
    return k[0], k[1], k[4], k[5], k[6], k[7]


def _corner_radius(camera: LensCamera) -> float:
    """Normalised radius of the image corner farthest from the principal point (what `cv2.undistort` samples)."""
    W, H = camera.image_size_px
    F = float(camera.focal_px.detach())
    cx, cy = (float(c) for c in camera.principal_point_px.detach())
    return max(math.hypot(x - cx, y - cy) for x in (-0.5, W - 0.5) for y in (-0.5, H - 0.5)) / F


def radial_fold(camera: LensCamera, obs: Observations) -> str | None:
    """Where the camera's radial distortion stops being one-to-one on the image, or None.

    The radial mapping r ↦ r_d = r (1 + k1 r² + k2 r⁴ + k3 r⁶) / (1 + k4 r² + k5 r⁴ + k6 r⁶) (normalised radii
    about the principal point) must increase from the axis over the image's undistorted radii: up to the image
    corner's radius (what undistorting the photo with its own camera matrix samples, as `cv2.undistort` does)
    and up to every fitted corner's undistorted radius (a corner beyond the fold is imaged by the mapping's
    falling branch, where two directions share one pixel). Otherwise the undistorted photo folds over near its
    border and the lens beyond the board is wrong, although the corners fit (OpenCV users meet this as
    opencv/opencv#15992). Returns None, or why the mapping is refused (one line).
    """
    k1, k2, k3, k4, k5, k6 = _radial_coefficients(camera)
    r_image = _corner_radius(camera)
    with torch.no_grad():
        p = camera.to_camera(obs.points_mm.to(camera.rvec.dtype))[obs.corner_mask]
    r_obs = float(torch.sqrt(p[:, 0] ** 2 + p[:, 1] ** 2).div(p[:, 2].clamp_min(1e-12)).max()) if len(p) else 0.0
    r_max = min(max(r_image, r_obs), MAX_UNDISTORTED_RADIUS)
    r = np.linspace(0.0, r_max, 200001)
    r2 = r * r
    a = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    b = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    with np.errstate(all="ignore"):
        bad = ~(b > 0) | ~(np.diff(r * a / b, prepend=-1.0) > 0)
    if not bad.any():
        return None
    r_fold = float(r[int(np.argmax(bad))])
    where = (f"a fitted corner's ({math.degrees(math.atan(r_obs)):.1f}°)" if r_obs > r_image else
             f"the image corner's ({math.degrees(math.atan(r_image)):.1f}°)")
    return f"the radial mapping folds back at {math.degrees(math.atan(r_fold)):.1f}° off the axis, inside {where}"


def mapping_sigma_px(fit: FitResult) -> float:
    """One-σ uncertainty (pixels) of the fitted radial mapping r ↦ r_d at the image corner farthest from the
    principal point, propagated from the covariance of the radial coefficients (k1…k6); 0 without free radial
    terms, inf (undetermined) where the fit has no covariance: no covariance is no evidence of a determined
    mapping."""
    names = list(fit.parameter_names or [])
    radial = ("dist_k1", "dist_k2", "dist_k3", "dist_k4", "dist_k5", "dist_k6")
    idx = [names.index(n) for n in radial if n in names]
    if not idx:
        return 0.0
    if fit.covariance is None:
        return math.inf
    k1, k2, k3, k4, k5, k6 = _radial_coefficients(fit.camera)
    r = _corner_radius(fit.camera)
    r2 = r * r
    a = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    b = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    if b == 0:  # a pole at the corner (`radial_fold` says so); elsewhere a fold is no matter of uncertainty
        return math.inf
    grad = {"dist_k1": r * r2 / b, "dist_k2": r * r2 ** 2 / b, "dist_k3": r * r2 ** 3 / b,
            "dist_k4": -r * a * r2 / b ** 2, "dist_k5": -r * a * r2 ** 2 / b ** 2, "dist_k6": -r * a * r2 ** 3 / b ** 2}
    g = torch.tensor([grad[names[i]] for i in idx], dtype=torch.float64)
    C = fit.covariance.submatrix(idx).to(torch.float64)
    return float(fit.camera.focal_px.detach()) * math.sqrt(max(float(g @ C @ g), 0.0))


def undetermined_distortion(fit: FitResult, model: str, n_views: int) -> str | None:
    """Why the views do not determine the coefficients of the distortion `model` (one line), or None: for the
    `CHECKED_MODELS`, its radial mapping at the image corner is uncertain by more than `MAX_MAPPING_SIGMA_PX` (a single view of
    the board fits the rational model's eight coefficients to anything: issue 24 found 3.6e5), the fit has no
    covariance to tell, or a denominator term is undetermined (`undetermined_denominator`)."""
    if model not in CHECKED_MODELS:
        return None
    sigma = mapping_sigma_px(fit)
    head = f"distortion {model}: too few views ({n_views}) to determine its {len(MODEL_TERMS[model])} coefficients"
    advice = "calibrate from more views spread over the image, or a model with fewer terms"
    if math.isinf(sigma) and fit.covariance is None:
        return f"{head}: the fit has no covariance to show they are determined; {advice}"
    if sigma > MAX_MAPPING_SIGMA_PX:
        return (f"{head}: the fitted mapping at the image corner is uncertain by ±{sigma:.3g} px (1σ; at most "
                f"{MAX_MAPPING_SIGMA_PX:g} px accepted); {advice}")
    why = undetermined_denominator(fit, model)
    return f"{head}: {why}; {advice}" if why else None


# A rational denominator term (k4, k5, k6) whose σ exceeds both its own size (not even its sign known) and this
# (an absolute floor, so that a small term of a lens with little distortion stays) is not determined: the
# numerator and denominator trade against each other, which leaves the mapping at the image corner pinned
# (`mapping_sigma_px` small) while the projection elsewhere is not. industrial_ds1, flat board, rational5:
# 1 view k4 260 ± 594, 12 views −7.2 ± 8.3 (refused), 3 views −24.5 ± 1.7 (kept); GoPro, 18 views: 2–5 %.
MAX_DENOMINATOR_SIGMA = 1.0


def undetermined_denominator(fit: FitResult, model: str) -> str | None:
    """Which rational denominator term of `model` the fit does not determine (a clause), or None."""
    from renderer.cameras.distortion import COEFFICIENT_NAMES

    sig = list((fit.sigma or {}).get("distortion") or [])
    k = [float(c) for c in fit.camera.distortion.detach()]
    for name in ("k4", "k5", "k6"):
        if name not in MODEL_TERMS[model]:
            continue
        i = COEFFICIENT_NAMES.index(name)
        s = sig[i] if i < len(sig) else math.nan
        if not math.isfinite(s) or (s > abs(k[i]) and s > MAX_DENOMINATOR_SIGMA):
            return (f"its denominator term {name} = {k[i]:.3g} ± {s:.3g} is not determined (the numerator and "
                    f"denominator trade against each other)")
    return None


def projection_sigma_worst_px(fit: FitResult) -> float:
    """The worst one-σ uncertainty (pixels) of the fit's projection over the image (`tiltfit.uncertainty.covariance`'s map,
    as CALIB.json's `projection_uncertainty.worst_px`); inf (undetermined) where the fit has no intrinsics
    covariance."""
    ic = getattr(fit, "intrinsics_covariance", None)
    if not ic:
        return math.inf
    from tiltfit.uncertainty.covariance import covariance_from_calib, projection_summary

    worst = projection_summary(fit.camera.lens, covariance_from_calib({"intrinsics_covariance": ic}, check=False),
                               nx=24)["worst_px"]
    return math.inf if worst is None else float(worst)


def undetermined_for_choice(fit: FitResult, model: str, reference: FitResult | None = None) -> str | None:
    """Why the automatic choice does not take `model`'s fit although it may be asked for by name (one line), or
    None: for the `CHECKED_MODELS`, a projection uncertain by more than `MAX_PROJECTION_SIGMA_PX` somewhere in
    the image, and by more than `PROJECTION_SIGMA_FACTOR` times that of `reference` (the `REFERENCE_MODEL`'s fit
    on the same views, or None) (the views determine the mapping where the boards were, not its coefficients)."""
    if model not in CHECKED_MODELS:
        return None
    worst = projection_sigma_worst_px(fit)
    limit = MAX_PROJECTION_SIGMA_PX
    ref = projection_sigma_worst_px(reference) if reference is not None else 0.0
    if math.isfinite(ref):
        limit = max(limit, PROJECTION_SIGMA_FACTOR * ref)
    if worst <= limit:
        return None
    return (f"{PROJECTION_REFUSAL}: the projection is uncertain by up to ±{worst:.3g} px "
            f"(1σ) in the image, more than the {limit:.3g} px an automatic choice accepts (the larger of "
            f"{MAX_PROJECTION_SIGMA_PX:g} px and {PROJECTION_SIGMA_FACTOR:g}× {REFERENCE_MODEL}'s ±{ref:.3g} px; "
            f"views with the board near the image's corners determine it)")


def held_out_gain(simple: dict | None, rich: dict | None, obs: Observations) -> float | None:
    """How many standard errors the richer model's held-out squared error is below the simpler one's, over the
    views: the per-view differences n_v (e_simple² − e_rich²) (n_v corners, e the per-view held-out RMS), their
    mean over its standard error (a paired t statistic). None without per-view errors for both, or with fewer
    than 3 views; +inf where every view gains alike."""
    if not simple or not rich:
        return None
    a, b = simple.get("per_view_px"), rich.get("per_view_px")
    if a is None or b is None or len(a) != len(b) or len(a) != obs.n_views:
        return None
    n = obs.corner_mask.sum(-1).double()
    d = [float(n[v]) * (a[v] ** 2 - b[v] ** 2) for v in range(len(a)) if math.isfinite(a[v]) and math.isfinite(b[v])]
    if len(d) < 3:
        return None
    mean = sum(d) / len(d)
    var = sum((x - mean) ** 2 for x in d) / (len(d) - 1)
    if var <= 0:
        return math.inf if mean > 0 else -math.inf
    return mean / math.sqrt(var / len(d))


def select_distortion(camera: LensCamera, obs: Observations, options: FitOptions, mode: str = "unified",
                      say=None, folds: int = 5, board=None, known: dict | None = None,
                      models=DISTORTION_MODELS, defer_sigma: bool = False) -> FitResult:
    """Fit every distortion model on the corners and keep the one that predicts held-out views best.

    Models none, k1, k1k2, opencv5, rational5, rational are fitted in turn on all views (each starting from the previous
    fit); a model whose radial mapping folds inside the image (`radial_fold`), whose coefficients the views do
    not determine (`undetermined_distortion`, `undetermined_for_choice`) or whose fit fails is refused;
    the others are scored by their K-fold held-out error (`held_out_rms`, the lens of each fold started from
    the model's fit on all views; not computed for a model whose fit RMS already exceeds the best held-out
    error, which it cannot beat). The chosen model is the one with the fewest terms whose held-out error is
    within `HELD_OUT_TOLERANCE` of the smallest or within one standard error of it over the views
    (`_fewest_terms_within_one_se`); `choice_variance` gives what the choice leaves open. With fewer than 3 views (no held-out error) the score is
    BIC on the fitted corners. Returns that model's fit; `distortion_selection` holds one entry per model
    ({model, n_terms, rms_px, held_out_rms_px | bic, refused?, chosen}); `held_out` the chosen one's
    held-out result. The principal point is free when `options.free_principal_point` is True.

    `board` (a fitted `tiltfit.target.shape.Board`, or None: the target's points as they are): the board's shape is
    fitted beside every model (started from `board`) and refitted without the held-out views in each fold, so
    every figure is the held-out error of the whole calibration (lens and board). `known` ({model: (fit,
    held-out dict)}) gives fits already made with these settings (and `board`'s model), not made again;
    `models` the candidates (fewest terms first).

    Each candidate is warm-started from the previous one's fit (lens and board); only the models whose checks read a
    covariance (`CHECKED_MODELS`, `REFERENCE_MODEL`) are fitted with their uncertainties, the chosen one's added after
    the choice (a refit from its own solution: the same minimum). `defer_sigma`: that refit computes the classical
    σ only (which tell a degenerate fit as the per-view ones do) and leaves the per-view error model to
    `tiltfit.calibrate.fit.with_deferred_sigma`, for a fit that a later one (the blur fit) usually replaces.
    """
    obs = without_blur(obs)
    fixed = replace(options, progress=None, model_selection=False, free_principal_point=bool(
        options.free_principal_point))
    fits, entries = _fit_candidates(camera, obs, fixed, mode, board, known or {}, models)
    use_held_out = obs.n_views >= 3
    held = _score_held_out(obs, fixed, folds, fits, entries, known or {}, models) if use_held_out else {}
    if use_held_out:
        fits = {m: f for m, f in fits.items() if m in held}
    shape = "" if board is None else f" (board {board.model} fitted, and refitted in each fold)"
    for entry in entries if say else []:
        say(f"distortion {entry['model']}{shape}: " + _entry_line(entry))
    while True:
        if not fits:
            raise FitError("no distortion model could be fitted: " + "; ".join(
                f"{e['model']}: {e.get('refused')}" for e in entries))
        key = "held_out_rms_px" if use_held_out else "bic"
        scores = {e["model"]: e[key] for e in entries if e["model"] in fits and key in e}
        chosen = _fewest_terms_within_one_se(models, scores, held, obs, entries) if use_held_out else \
            min(scores, key=scores.get)
        try:
            result = _with_uncertainties(fits[chosen], obs, replace(fixed, distortion=chosen), mode, defer_sigma)
            break
        except FitError as e:  # degenerate: refused as a fit with its uncertainties would have been
            entries[models.index(chosen)]["refused"] = f"not fitted ({e})"
            fits.pop(chosen)
    for e in entries:
        e["chosen"] = e["model"] == chosen
        if board is not None:
            e["board"] = board.model
    result.distortion_model = chosen
    result.distortion_selection = entries
    result.held_out = held.get(chosen)
    if use_held_out:
        var = choice_variance({m: (fits[m].values, held.get(m)) for m in fits}, chosen, obs, ONE_SE)
        result.choice_variance = {"distortion": var} if var else {}
    return result


def _fit_candidates(camera, obs: Observations, fixed: FitOptions, mode: str, board, known: dict, models):
    """Each model fitted on all views, each from the previous fit (`known` ones taken as given), and checked:
    returns ({model: fit} of those not refused, entries {model, n_terms, rms_px, bic | refused})."""
    fits, entries, prev, reference = {}, [], None, None
    for m in models:
        entry = {"model": m, "n_terms": len(MODEL_TERMS[m])}
        entries.append(entry)
        try:
            if m in known:
                fit = known[m][0]
            else:
                start = board if prev is None or board is None else prev.board
                needs_sigma = m in CHECKED_MODELS or m == REFERENCE_MODEL  # their checks read the covariance
                fit = fit_geometry((prev.camera if prev is not None else camera).copy(), obs,
                                   replace(fixed, distortion=m, uncertainties=fixed.uncertainties and needs_sigma),
                                   mode, board=None if board is None else start.copy())
        except FitError as e:
            entry["refused"] = f"not fitted ({e})"
            continue
        prev = fit
        if m == REFERENCE_MODEL:
            reference = fit
        entry["rms_px"] = per_corner_rms_px(fit.rss)
        seen = obs if fit.board is None else _with_board(obs, fit.board)
        fold = (radial_fold(fit.camera, seen) or undetermined_distortion(fit, m, obs.n_views)
                or undetermined_for_choice(fit, m, reference))
        if fold:
            entry["refused"] = fold
        else:
            fits[m] = fit
            n = fit.rss["n_corners"]
            entry["bic"] = n * math.log(max(fit.rss["corners"], 1e-300) / n) + fit.n_parameters * math.log(n)
    return fits, entries


def _score_held_out(obs: Observations, fixed: FitOptions, folds: int, fits: dict, entries: list, known: dict,
                    models) -> dict:
    """{model: held-out dict} of the candidates, best-fitting model first (entries get `held_out_rms_px`, or why
    not). A model whose fit RMS already exceeds the best held-out error found (with the tolerance) is not scored:
    its held-out error is at least its fit RMS (a fit explains the views it was fitted to better than new ones),
    so it cannot be chosen."""
    held = {}
    for m in sorted(fits, key=lambda m: fits[m].rss["corners"]):
        entry = entries[models.index(m)]
        best = min((h["rms_px"] for h in held.values()), default=math.inf)
        if entry["rms_px"] > (1 + HELD_OUT_TOLERANCE) * best:
            entry["held_out_skipped"] = "its fit RMS exceeds the best held-out error"
            continue
        try:
            given = known.get(m, (None, None))[1]
            held[m] = given if (given or {}).get("folds") == min(max(2, folds), obs.n_views) else held_out_rms(
                obs, replace(fixed, distortion=m), folds, start=fits[m].camera, board=fits[m].board)
            entry["held_out_rms_px"] = held[m]["rms_px"]
        except FitError as e:
            entry["refused"] = f"held-out error not computed ({e})"
    return held


def _entry_line(entry: dict) -> str:
    """A candidate's progress line after its name: fit RMS and score, or why it was not scored."""
    score = (f"held-out {entry['held_out_rms_px']:.4f} px" if "held_out_rms_px" in entry else
             f"refused: {entry['refused']}" if "refused" in entry else
             f"held-out not computed ({entry['held_out_skipped']})" if "held_out_skipped" in entry else
             f"BIC {entry['bic']:.1f}")
    return (f"RMS {entry['rms_px']:.4f} px per corner, " if "rms_px" in entry else "") + score


def _with_uncertainties(fit: FitResult, obs: Observations, options: FitOptions, mode: str,
                        defer: bool = False) -> FitResult:
    """`fit` with its covariance and σ (refitted from its own solution where it was fitted without them); `defer`:
    the classical σ now, the per-view ones when `tiltfit.calibrate.fit.with_deferred_sigma` asks (from the same
    refit's solve)."""
    if fit.covariance is not None or not options.uncertainties:
        return fit
    return fit_geometry(fit.camera.copy(), obs, options, mode, board=None if fit.board is None else fit.board.copy(),
                        defer_sigma=defer)


def _fewest_terms_within_one_se(models, scores: dict, held: dict, obs: Observations, entries: list) -> str:
    """The one-standard-error rule (Hastie, Tibshirani & Friedman, ESL §7.10): the model with the fewest terms whose
    held-out error is within `HELD_OUT_TOLERANCE` of the smallest, or whose excess over the best model is at most
    one standard error over the views (`held_out_gain` of the best over it at most `ONE_SE`). On a dozen views of a
    small board the held-out errors of k1 … opencv5 differ by less than their scatter over the views, and a choice
    made on the mean alone flips between halves of one set (issue 33 §5: k1 against opencv5). The entry of a
    model so chosen records the best model's gain over it in standard errors (`gain_z_of_best`)."""
    best_m = min(scores, key=scores.get)
    for m in models:
        if m not in scores:
            continue
        if scores[m] <= (1 + HELD_OUT_TOLERANCE) * scores[best_m]:
            return m
        gain = held_out_gain(held.get(m), held.get(best_m), obs)
        if gain is not None and gain <= ONE_SE:
            entries[models.index(m)]["gain_z_of_best"] = gain
            return m
    return best_m


def choice_variance(candidates: dict, chosen: str, obs: Observations, rule_z: float) -> dict | None:
    """The variance of the focal length and principal point that an automatic model choice leaves (model-selection
    uncertainty, Buckland, Burnham & Augustin 1997, Biometrics 53:603): Σ_m w_m (θ_m − θ_chosen)² / Σ_m w_m over
    the candidate models m, weighted as the choice itself weighs them. The choice takes a richer model where its
    held-out gain over the simpler one is at least `rule_z` standard errors over the views (`held_out_gain`):
    read as a likelihood ratio exp(z|z|/2) against prior odds exp(−rule_z²/2) per step to a richer model, the
    weight of m relative to the chosen model c is exp((z|z| − rule_z²)/2) with z the gain of m over c where m is
    richer, and its inverse with z the gain of c over m where m is simpler. So at the rule's threshold two models
    weigh alike (the choice is a coin's toss and σ holds half their difference), the chosen one weighs most, and
    models the views tell apart add nothing. Issue 33 §5: k1 against opencv5 moved the principal point by 30 px on
    five industrial_ds1 views, each σ 2-7 px.

    Args:
        candidates: {model: (fit values {w_mm, principal_point_px}, held-out dict with per_view_px)}, fewest
            parameters first.
        chosen: the model whose values are reported.
        rule_z: the standard errors the choice asks of a richer model.
    Returns:
        {"w_mm": variance (mm²), "principal_point_px": [variance, variance] (px²), "weights": {model: w}}, or None
        with fewer than two scored candidates.
    """
    scored = {m: c for m, c in candidates.items() if c[1] and c[1].get("per_view_px") is not None}
    if chosen not in scored or len(scored) < 2:
        return None
    order = list(scored)
    weights = {}
    for m, (_, held) in scored.items():
        if m == chosen:
            weights[m] = 1.0
            continue
        richer = order.index(m) > order.index(chosen)
        z = held_out_gain(scored[chosen][1], held, obs) if richer else held_out_gain(held, scored[chosen][1], obs)
        if z is None:
            weights[m] = 0.0
            continue
        log_odds = 0.5 * (z * abs(z) - rule_z ** 2) if math.isfinite(z) else math.copysign(math.inf, z)
        weights[m] = math.exp(min(log_odds if richer else -log_odds, 50.0))
    total = sum(weights.values())
    ref = scored[chosen][0]

    def spread(get):
        return sum(w * (get(scored[m][0]) - get(ref)) ** 2 for m, w in weights.items()) / total

    return {"w_mm": spread(lambda v: float(v["w_mm"])),
            "principal_point_px": [spread(lambda v, i=i: float(v["principal_point_px"][i])) for i in (0, 1)],
            "weights": {m: round(w / total, 4) for m, w in weights.items()}}


def _with_board(obs: Observations, board) -> Observations:
    from tiltfit.target.shape import with_points

    return with_points(obs, board.points())


def describe_choice(selection: list) -> str:
    """One line: which distortion model `select_distortion` chose and why."""
    chosen = next((e for e in selection if e.get("chosen")), None)
    if chosen is None:
        return "no model chosen"
    if "held_out_rms_px" in chosen:  # compared with the models scored with the same board
        best = min((e for e in selection if "held_out_rms_px" in e and e.get("board") == chosen.get("board")),
                   key=lambda e: e["held_out_rms_px"])
        within = (f"within one standard error over the views (a gain of {chosen['gain_z_of_best']:.2g})"
                  if "gain_z_of_best" in chosen else f"within {100 * HELD_OUT_TOLERANCE:g} %")
        why = (f"smallest held-out error, {chosen['held_out_rms_px']:.4f} px per corner" if best is chosen else
               f"held-out {chosen['held_out_rms_px']:.4f} px per corner, {within} of "
               f"{best['model']}'s {best['held_out_rms_px']:.4f} px with fewer terms")
    else:
        why = "smallest BIC (too few views for a held-out error)"
    refused = [f"{e['model']} ({e['refused']}" + (f", with the {e['board']} board" if e.get("board") and
                                                  e.get("board") != chosen.get("board") else "") + ")"
               for e in selection if e.get("refused")]
    board = f" (board {chosen['board']} refitted in each fold)" if chosen.get("board") else ""
    return f"{chosen['model']}{board}: {why}" + (f"; refused: {'; '.join(refused)}" if refused else "")
