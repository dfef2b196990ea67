"""Which model the data support: nested-model tests between fits, and the checks that decide whether the blur
widths can be fitted at all.

    likelihood_ratio(restricted, full, k, alpha)        -> the test's numbers and a verdict
    nested_model_tests(base, obs, mode, options, ...)    -> {θF, principal point: that test re-fitted}
    usable_views(obs, min_corners)                       -> (observations kept, [{image, reason}])
    blur_is_informative(obs, floor_px)                   -> whether the widths can say anything about U and d
    blur_depends_on_depth(camera, obs, alpha)            -> whether they vary with depth beyond their scatter

The likelihood-ratio statistic Λ = Σ_g n_g ln(RSS_g,restricted / RSS_g,full) (Gaussian, each group's variance
profiled out) is compared with χ²(k), and AIC/BIC differences are reported. A parameter is "justified" when the
test rejects the restricted model at level `alpha` and BIC prefers the larger one.
"""
from __future__ import annotations

import math
from dataclasses import replace

import torch

from tiltfit.calibrate.fit import FitError, FitOptions, FitResult, _fit_camera, without_blur
from tiltfit.calibrate.model import Observations, LensCamera
from tiltfit.select.stats import nested_test


def likelihood_ratio(restricted: FitResult, full: FitResult, k: int, alpha: float = 0.01) -> dict:
    """Test a restricted fit against a fuller one (k extra parameters) over the corner and blur groups
    (`tiltfit.select.stats.nested_test`). ΔBIC uses all of the fit's residuals."""
    groups = [(full.rss[f"n_{g}"], restricted.rss[g], full.rss[g]) for g in ("corners", "blur")]
    out = nested_test(groups, k, alpha)
    # The fit's residual count (corners and blur widths with their own σ) sets the BIC penalty.
    out["delta_bic"] = out["lr_statistic"] - k * math.log(full.n_residuals)
    out["justified"] = bool(out["p_value"] < alpha and out["delta_bic"] > 0)
    return out


def nested_model_tests(base: FitResult, obs: Observations, mode: str, options: FitOptions, say=None,
                     test_theta_F: bool = True, test_principal_point: bool = True) -> dict:
    """Re-fit with θF (and the principal point) switched and test which state the data support."""
    out = {}
    quiet = replace(options, model_selection=False)
    sigma = (base.noise["sigma_corner_px"], base.noise["sigma_blur_px"])
    if base.rss.get("n_blur", 0) == 0:
        obs = without_blur(obs)
    # With the tilt axis's direction freed (`calibration._with_tilt_axis`), no tilt leaves no axis: both go.
    tilt = ("theta_F", "phi") if base.camera.phi.requires_grad else ("theta_F",)
    tests = [("theta_F", tilt, len(tilt))] if test_theta_F else []
    if test_principal_point:
        tests.append(("principal_point", ("principal_point",), 2))
    for label, names, k in tests:
        cam = base.camera.copy()
        stored = cam.parameter_names(*names)
        is_free = all(getattr(cam, s).requires_grad for s in stored)
        if is_free:
            cam.freeze(*names)
            with torch.no_grad():
                for s in stored:
                    getattr(cam, s).zero_()
        else:
            cam.free(*names)
        try:
            alt = _fit_camera(cam, obs, quiet, sigma=sigma, mode=mode)
        except FitError as e:
            out[label] = {"error": str(e), "justified": None}
            continue
        full, restricted = (base, alt) if is_free else (alt, base)
        entry = likelihood_ratio(restricted, full, k, options.alpha)
        entry["fitted"] = is_free
        if label == "theta_F":
            entry["theta_F_deg_full"] = full.values["theta_F_deg"]
        else:
            entry["principal_point_px_full"] = full.values["principal_point_px"]
        out[label] = entry
        if say:
            verdict = "justified" if entry["justified"] else "not justified"
            held = (f"; this {mode} fit holds θF at 0 (freed it would be {entry['theta_F_deg_full']:.3g}°; the "
                    "joint and tilt fits fit it)" if label == "theta_F"
                    else f"; this fit holds {label}") if entry["justified"] and not is_free else ""
            say(f"model selection: freeing {label} is {verdict} (Λ = {entry['lr_statistic']:.3g}, "
                f"p = {entry['p_value']:.3g}, ΔBIC = {entry['delta_bic']:.3g}){held}")
    return out


def usable_views(obs: Observations, min_corners: int, say=None) -> tuple[Observations, list]:
    """Drop views with fewer than `min_corners` corners; returns (observations kept, [{image, reason}])."""
    n = obs.corner_mask.sum(-1)
    keep = [v for v in range(obs.n_views) if int(n[v]) >= min_corners]
    skipped = [{"image": obs.names[v], "reason": f"{int(n[v])} corners found, at least {min_corners} needed"}
               for v in range(obs.n_views) if int(n[v]) < min_corners]
    for sk in skipped:
        if say:
            say(f"warning: skipping {sk['image']}: {sk['reason']}")
    return (obs if len(keep) == obs.n_views else obs.subset(keep)), skipped


def blur_is_informative(obs: Observations, floor_px: float = 1.0) -> bool:
    """Whether the blur widths can say anything about U and d: at least 3 of them, and some above `floor_px`
    (below it a detector's width is its own resolution, not defocus)."""
    b = obs.blur_px[obs.blur_mask]
    return b.numel() >= 3 and float(b.max()) >= floor_px


def blur_depends_on_depth(camera: LensCamera, obs: Observations, alpha: float = 1e-3) -> bool:
    """Whether the blur widths vary with the corners' place in the camera frame beyond their scatter: a
    likelihood-ratio test (χ², 4 degrees of freedom) of widths regressed on (1, 1/z, 1/z², x/z, y/z)
    (defocus on either side of a plane of focus, tilted or not) against a constant, at level `alpha`, with
    `camera`'s poses. Widths the same at every depth (a soft lens, detector blur) say nothing about U and d."""
    m = obs.blur_mask
    b = obs.blur_px[m].double()
    if b.numel() < 10:
        return False
    with torch.no_grad():
        X = camera.to_camera(obs.points_mm.to(camera.rvec.dtype))[m]
    iz = 1.0 / X[:, 2].clamp_min(1e-9)
    iz = iz / iz.mean()
    A = torch.stack([torch.ones_like(iz), iz, iz**2, X[:, 0] / X[:, 2], X[:, 1] / X[:, 2]], -1).double()
    coef = torch.linalg.lstsq(A, b[:, None]).solution
    rss1 = float(((A @ coef)[:, 0] - b).pow(2).sum())
    rss0 = float((b - b.mean()).pow(2).sum())
    if rss1 <= 0:
        return rss0 > 0
    return nested_test([(b.numel(), rss0, rss1)], A.shape[1] - 1, alpha)["p_value"] < alpha
