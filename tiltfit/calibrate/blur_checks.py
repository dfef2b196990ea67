"""The checks of the thin-lens blur model on a fitted calibration: the widths' noise, whether the model describes
them (`blur_misfit`), whether U rests on widths below the detector's floor (`focus_below_floor`), a trend of the
residuals with depth (`blur_trend`), focus values the fit cannot determine or that lie outside their physical range,
and CALIB.json's record of it all (`blur_record`). Used by the calibration's blur stage (`tiltfit.calibrate.blur_stage`).

    blur_noise_px(obs)                    -> the widths' measurement noise, px (no blur model)
    blur_misfit(result, obs, noise)       -> why the model does not describe the widths, or None
    focus_below_floor(result, obs, ...)   -> why U rests on sub-floor widths, or None
    blur_trend(result, obs, noise)        -> the residuals' trend with depth, or None
    undetermined_focus(result)            -> ["U_mm", "d_mm"] those within 2σ of 0
    undetermined_focus_deferred(result)   -> the same, the per-view σ made only where the classical ones leave it open
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import torch

from tiltfit.calibrate.fit import FitError, FitOptions, FitResult, _fit_camera, with_deferred_sigma
from tiltfit.calibrate.model import Observations, residuals, robust_rho, robust_weight
from tiltfit.solve import LMOptions, SolverError, least_squares


def undetermined_focus(result: FitResult) -> list:
    """U and d the blur fit could not pin down: 1/U within 2σ of 0 (focus indistinguishable from infinity) or
    d within 2σ of 0 (indistinguishable from a pinhole: relative σ above 0.5)."""
    out = []
    cam = result.camera
    s_inv = result.sigma.get("inv_U_per_m")
    # 1/U at or below 0 (focus beyond infinity) is as undetermined as 1/U within 2σ of 0.
    if s_inv is not None and not float(cam.inv_U_per_m.detach()) > 2.0 * s_inv:
        out.append("U_mm")
    s_d = result.sigma.get("d_mm")
    if "d_scaled" in result.parameter_names and s_d is not None and not float(cam.d_mm.detach()) > 2.0 * s_d:
        out.append("d_mm")
    return out


def undetermined_focus_deferred(result: FitResult) -> list:
    """`undetermined_focus` of a fit whose per-view σ may be deferred (`FitResult.deferred_sigma`): where the
    classical σ already leave every focus parameter it tests undetermined, so do the per-view ones, which are never
    below them (the classical covariance is their floor, `tiltfit.uncertainty.covariance`), and they are not made
    (a blur fit with U and d undetermined is not reported); else they are made and decide."""
    out = undetermined_focus(result)
    tested = ["U_mm"] + (["d_mm"] if "d_scaled" in result.parameter_names else [])
    if result.deferred_sigma is None or out == tested:
        return out
    return undetermined_focus(with_deferred_sigma(result))


def focus_beyond_infinity(result: FitResult) -> str | None:
    """Where the blur fit put the focus beyond infinity (1/U ≤ 0: widths at a detector's floor, a lens focused
    far beyond the views), the camera's focus is set to infinity, the nearest physical value, so that no negative
    U reaches a lens, a file or a later stage (per-view annotations, uncertainty, photometric refinement);
    returns the note saying why U is undetermined, or None where 1/U > 0."""
    cam = result.camera
    inv_u = float(cam.inv_U_per_m.detach())
    if inv_u > 0.0 or not math.isfinite(inv_u):
        return None
    s_inv = result.sigma.get("inv_U_per_m")
    with torch.no_grad():
        cam.inv_U_per_m.zero_()
    result.values["U_mm"] = math.inf
    result.values["f_mm"] = float(cam.w_mm.detach())  # f = U w / (U + w) → w at U = ∞
    spread = f" ± {s_inv:.2g}" if s_inv is not None and math.isfinite(s_inv) else ""
    return (f"U undetermined: the blur widths put the focus beyond infinity (1/U = {inv_u:.3g}{spread} per m); "
            f"the lens is held focused at infinity for the per-view values")


def blur_record(used: bool, noise_px: float, misfit: str | None, trend: dict | None) -> dict:
    """CALIB.json's `model_selection.blur`: whether the thin-lens blur model gave U (`used`), why it was refused
    (`blur_misfit`; null where it was not, or where the notes say why U is undetermined), the widths' noise and
    the residuals' trend with depth (`blur_trend`)."""
    finite = lambda v: v if v is not None and math.isfinite(v) else None  # noqa: E731
    out = {"used": bool(used), "why_not": misfit, "noise_px": finite(noise_px)}
    if trend is not None:
        out["trend_with_depth"] = {k: trend[k] for k in ("significant", "p_value", "amplitude_px", "depth_mm")}
    return out


# Physical ranges of the lens values (`out_of_range`): a value outside is not a measurement of this lens.
PHYSICAL_RANGES = {"w_mm": (0.0, math.inf), "U_mm": (0.0, math.inf), "d_mm": (0.0, math.inf),
                   "f_mm": (0.0, math.inf)}


def out_of_range(result: FitResult) -> list:
    """Keys whose fitted value is not finite or outside its physical range (w, U, f > 0, d ≥ 0): the fit's
    number for them is not a measurement, so they are reported undetermined (null)."""
    out = []
    for k, (lo, hi) in PHYSICAL_RANGES.items():
        v = result.values.get(k)
        if v is None:
            continue
        ok = math.isfinite(v) and (v >= lo if k == "d_mm" else v > lo) and v < hi
        if not ok:
            out.append(k)
    return out


# When the thin-lens blur model is refused (`blur_misfit`); see docs/real_cameras.md. Measured (blur noise from
# second differences): a rendered capture through a lens tilted by 5° leaves residuals 1.1× the noise and
# explains widths varying 13× the noise; the untilted GoPro set's fit leaves 1.15× and explains 0.6×.
BLUR_MISFIT_RESIDUAL_RATIO = 3.0  # residual σ above this many noise σ: structure the model cannot explain
BLUR_MIN_SIGNAL_RATIO = 1.0  # explained variation below this many noise σ: the widths carry no resolvable defocus


def blur_noise_px(obs: Observations) -> float:
    """The blur widths' measurement noise (pixels), without a blur model, from second differences along the
    target's rows and columns (Rice 1984; Gasser, Sroka and Jennen-Steinmetz 1986).

    Three consecutive corners on the target lie at nearly the same depth and the blur changes nearly linearly
    across them whatever the lens (tilted or not), so b_(i−1) − 2 b_i + b_(i+1) is noise with variance 6 σ²
    plus a curvature term that only makes the estimate err large. NaN with fewer than 10 triples."""
    pts = obs.points_mm.numpy()
    triples = []
    for axis in (0, 1):
        other = 1 - axis
        for line in np.unique(np.round(pts[:, other], 6)):
            idx = np.flatnonzero(np.abs(pts[:, other] - line) < 1e-6)
            idx = idx[np.argsort(pts[idx, axis])]
            triples += list(zip(idx[:-2], idx[1:-1], idx[2:]))
    if not triples:
        return math.nan
    i, j, k = (torch.as_tensor(np.array(v)) for v in zip(*triples))
    m = obs.blur_mask
    ok = m[:, i] & m[:, j] & m[:, k]
    if int(ok.sum()) < 10:
        return math.nan
    d2 = (obs.blur_px[:, i] - 2 * obs.blur_px[:, j] + obs.blur_px[:, k])[ok].double()
    return math.sqrt(float((d2 * d2).mean()) / 6.0)


def blur_misfit(result: FitResult, obs: Observations, noise_px: float | None = None) -> str | None:
    """Why the fitted thin-lens blur model does not describe the lens's blur widths, or None.

    Against the widths' measurement noise σ_n (`blur_noise_px`, found without a blur model): the model does not
    describe them when its residuals' σ exceeds `BLUR_MISFIT_RESIDUAL_RATIO` σ_n (it leaves structure it
    cannot explain), or when the widths it predicts vary across the corners (their standard deviation) by less
    than `BLUR_MIN_SIGNAL_RATIO` σ_n: every width is then more noise than defocus, and U and d rest on the
    average of many noisy widths, where a systematic error of the widths (edges curved by distortion, JPEG
    compression, sharpening) weighs as much as defocus. The fitted U, d and a θF test then describe the
    model's compromise, not the lens (an untilted action camera's θF came out "justified" at −19°).

    `noise_px`: σ_n found beforehand (on the target file's points, where `obs` holds a fitted board's), or None
    to find it here."""
    m = obs.blur_mask
    if result.rss.get("n_blur", 0) < 10:
        return None
    noise = blur_noise_px(obs) if noise_px is None else noise_px
    if not (math.isfinite(noise) and noise > 0):
        return None
    with torch.no_grad():
        r = residuals(result.camera, obs).blur_px[m]
    resid = float(r.pow(2).mean().sqrt())
    explained = float((obs.blur_px[m] + r).std())
    if resid > BLUR_MISFIT_RESIDUAL_RATIO * noise:
        return (f"its blur residuals (RMS {resid:.3g} px) are {resid / noise:.1f}× the widths' noise ({noise:.3g} "
                f"px, from neighbouring corners)")
    if explained < BLUR_MIN_SIGNAL_RATIO * noise:
        return (f"the blur it explains varies by {explained:.3g} px across the corners, less than the widths' noise "
                f"({noise:.3g} px, from neighbouring corners)")
    return None


#: Widths below the detector's floor that may carry U before `focus_below_floor` checks (a share of all widths).
FLOOR_SHARE = 0.1


def focus_below_floor(result: FitResult, obs: Observations, options: FitOptions, mode: str) -> str | None:
    """Why U rests on blur widths below the detector's floor (`options.blur_floor_px`), or None.

    Below its floor a detector's width is its own resolution, not defocus (`blur_is_informative`): such widths
    say that the blur there is small, not how small. Where at least `FLOOR_SHARE` of the widths are below the
    floor, the blur fit is repeated from `result` without them; where that fit cannot determine U
    (`undetermined_focus`: 1/U within 2σ of 0) or fails, U came from the sub-floor widths alone. On the
    shipped GoPro set's last 11 views (far views' widths 0.4–0.5 px, near views' 1–2.4 px) U = 217 ± 12 mm
    with them and 208 ± 1e8 mm without; a capture through a lens focused inside the views' depths keeps U
    from the widths on both sides of the plane of focus."""
    m = obs.blur_mask
    below = m & (obs.blur_px < options.blur_floor_px)
    if int(below.sum()) < FLOOR_SHARE * int(m.sum()):
        return None
    above = Observations(obs.points_mm, obs.corners_px, torch.where(below, torch.nan, obs.blur_px),
                         obs.image_size_px, obs.pixel_pitch_mm, list(obs.names))
    share = f"{100 * int(below.sum()) / int(m.sum()):.0f} % of the widths"
    try:
        alt = _fit_camera(result.camera.copy(), above, replace(options, model_selection=False, progress=None),
                          mode=mode)
    except FitError as e:
        return (f"U rests on the widths below the detector's floor ({options.blur_floor_px:g} px; {share}): "
                f"without them the blur fit fails ({e})")
    if "U_mm" not in undetermined_focus(alt):
        return None
    with_deferred_sigma(result)  # its σ in the line below are the reported ones
    return (f"U rests on the widths below the detector's floor ({options.blur_floor_px:g} px; {share}): "
            f"{result.values['U_mm']:.0f} ± {result.sigma['U_mm']:.2g} mm with them, undetermined without them "
            f"(1/U within 2σ of 0)")


# When the blur residuals trend with depth (`blur_trend`): the trend must be significant with the views' errors
# sharing their errors (an F test on the views' means, α), and its size over the views' depths at least this many of the
# widths' noise σ (smaller trends bias U and d by less than the widths' scatter does). On industrial_ds1 the
# residuals' median rises by about 0.2 px from the nearest to the farthest corners (noise 0.18 px): flagged.
BLUR_TREND_ALPHA = 1e-2  # a warning: 1 % of captures without a trend get it (the test holds its level)
BLUR_TREND_MIN_RATIO = 0.5
BLUR_TREND_MIN_VIEWS = 4  # the cluster-robust covariance of 3 coefficients needs more views than that
HUBER_K = 1.5  # Huber's threshold, in robust σ of the residuals (Huber 1964: 95 % efficiency at the Gaussian)


def blur_trend(result: FitResult, obs: Observations, noise_px: float | None = None) -> dict | None:
    """Whether the fitted blur model's residuals change with depth: structure the thin-lens law does not explain.

    The residuals r (model − measured, px) are regressed on a quadratic in depth, r = a + b t + c t² with
    t = (z − median z) / (z₉₅ − z₅) (z in the camera frame), by Huber IRLS (a few widths at a detector's floor
    must not make a trend); the coefficients' covariance is the cluster-robust sandwich with the views as
    clusters (a view's widths share its errors): (b, c) = 0 is F-tested on the views' weighted means (their
    regression on the same quadratic, F(2, G − 3) for G views), which holds its level where a view's widths share
    an error. The trend is `significant` where p < `BLUR_TREND_ALPHA` and its range over z₅..z₉₅ is at least `BLUR_TREND_MIN_RATIO` of
    the widths' noise σ_n (`blur_noise_px`; the residuals' robust σ where it cannot be found).

    Returns:
        None with fewer than 30 widths or `BLUR_TREND_MIN_VIEWS` views; else {significant, p_value, f_statistic,
        amplitude_px, noise_px, depth_mm: [z₅, z₉₅], why (one line)}.
    """
    m = obs.blur_mask
    if int(m.sum()) < 30:
        return None
    with torch.no_grad():
        r = residuals(result.camera, obs).blur_px[m].double().numpy()
        z = result.camera.to_camera(obs.points_mm.to(result.camera.rvec.dtype))[..., 2][m].double().numpy()
    view = np.broadcast_to(np.arange(obs.n_views)[:, None], tuple(m.shape))[m.numpy()]
    groups = np.unique(view)
    ok = np.isfinite(r) & np.isfinite(z)
    if len(groups) < BLUR_TREND_MIN_VIEWS or ok.sum() < 30:
        return None
    r, z, view = r[ok], z[ok], view[ok]
    z5, z50, z95 = np.percentile(z, [5, 50, 95])
    span = max(z95 - z5, 1e-9)
    t = (z - z50) / span
    X = np.stack([np.ones_like(t), t, t * t], 1)
    # Huber fit (`tiltfit.solve.least_squares`), residuals in units of their robust σ about the plain fit
    plain = np.linalg.lstsq(X, r, rcond=None)[0]
    e0 = r - X @ plain
    s = 1.4826 * float(np.median(np.abs(e0 - np.median(e0)))) + 1e-12
    Xt, rt = torch.from_numpy(X), torch.from_numpy(r)
    huber = LMOptions(max_iterations=50, rho=lambda s2: robust_rho(s2, "huber", HUBER_K),
                      weight=lambda s2: robust_weight(s2, "huber", HUBER_K))
    try:
        coef = least_squares(lambda c: (Xt @ c - rt) / s, torch.from_numpy(plain), huber,
                             jacobian_fn=lambda c: Xt / s).x.numpy()
    except SolverError:
        return None
    e = r - X @ coef
    w = robust_weight(torch.from_numpy((e / s) ** 2), "huber", HUBER_K).numpy()
    # The test, on the views' (Huber-weighted) means: an error a view's widths share is indistinguishable from
    # a trend with depth across few views, and a sandwich over few clusters is far too small (per-view offsets
    # alone, no trend, p < 1e-3 in 50 % of 4-view and 11 % of 10-view captures by the cluster-robust Wald χ²(2)).
    # The view means' regression on the same quadratic, F-tested on (2, G − 3) degrees of freedom, holds its level
    # there (p < 1e-3 in 0.0–0.2 % of 3,000 simulated null captures of 4–20 views, with or without offsets).
    G = len(groups)
    idx = np.searchsorted(groups, view)
    wsum = np.bincount(idx, weights=w, minlength=G)
    if G < 4 or bool((wsum <= 0).any()):
        return None
    rm = np.bincount(idx, weights=w * r, minlength=G) / wsum
    Xm = np.stack([np.bincount(idx, weights=w * X[:, k], minlength=G) / wsum for k in range(3)], 1)
    fit_m = np.linalg.lstsq(Xm, rm, rcond=None)[0]
    rss1 = float(((rm - Xm @ fit_m) ** 2).sum())
    rss0 = float(((rm - rm.mean()) ** 2).sum())
    dof = G - 3
    f_stat = max(rss0 - rss1, 0.0) / 2 / max(rss1 / dof, 1e-300)
    p = (1 + 2 * f_stat / dof) ** (-dof / 2)   # F(2, dof)'s upper tail, in closed form for 2 numerator dof
    tt = np.linspace((z5 - z50) / span, (z95 - z50) / span, 101)
    curve = coef[1] * tt + coef[2] * tt * tt
    amplitude = float(curve.max() - curve.min())
    noise = noise_px if noise_px is not None and math.isfinite(noise_px) and noise_px > 0 else s
    significant = bool(p < BLUR_TREND_ALPHA and amplitude >= BLUR_TREND_MIN_RATIO * noise)
    lo, hi = int(np.argmin(curve)), int(np.argmax(curve))
    depth = z50 + tt * span
    at = lambda i: f"{round(float(curve[i] + coef[0]), 2) + 0.0:+.2f} px at {depth[i]:.0f} mm"  # noqa: E731 (no -0.00)
    why = (f"the blur residuals trend with depth, which the thin-lens model does not explain: from {at(lo)} to "
           f"{at(hi)} (model − measured, over {z5:.0f}–{z95:.0f} mm; a change {amplitude / noise:.1f}× the "
           f"widths' noise of {noise:.2g} px; p = {p:.1g}, each view's widths sharing their errors)")
    return {"significant": significant, "p_value": p, "f_statistic": f_stat, "amplitude_px": amplitude, "noise_px": noise,
            "depth_mm": [float(z5), float(z95)], "why": why}
