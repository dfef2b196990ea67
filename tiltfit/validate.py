"""Held-out reprojection error: how well a calibration predicts views it was not fitted on.

The fit RMS measures how well the model explains the corners it was fitted to; with many parameters
(distortion terms) it always drops. The held-out error is the honest one: split the views into K folds;
for each fold fit the lens (w, principal point, distortion, as the full fit did) on the other views, then
hold that lens fixed and fit only each held-out view's pose; the RMS of those views' residuals is what the
lens predicts. Blur widths are not used (geometry only).

    held_out_rms(obs, options, folds=5) -> {"rms_px", "per_view_px", "folds"}
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from .fit import FitError, FitOptions, fit_geometry, initialize, without_blur
from .model import Observations


def predict_views(camera, obs: Observations, options: FitOptions = FitOptions()):
    """Fit only the poses of `obs`'s views with `camera`'s lens held (w, U, d, θF, principal point,
    distortion); returns the FitResult (its RMS is the prediction error)."""
    held = replace(options, distortion="none", free_principal_point=False, model_selection=False, progress=None,
                   max_rms_px=None)
    cam = initialize(obs, "tilt", init=camera, options=held, blur=False)
    return fit_geometry(cam, without_blur(obs), held, mode="tilt", hold_distortion=True)


def held_out_rms(obs: Observations, options: FitOptions = FitOptions(), folds: int = 5,
                 distortion: str | None = None) -> dict:
    """K-fold held-out reprojection RMS (pixels) of a geometric calibration with `options`' settings.

    Args:
        obs: all views (views with too few corners should already be removed).
        options: the fit's settings (distortion model, principal point); "auto" is resolved once per fold.
        folds: K (views are dealt round-robin into folds; at most one fold per view).
        distortion: overrides options.distortion (e.g. the model the full fit chose).
    Returns:
        {"rms_px": RMS over all held-out corners, "per_view_px": [...] in obs order, "folds": K}.
    """
    V = obs.n_views
    K = max(2, min(int(folds), V))
    if V < 3:
        raise FitError(f"held-out error needs at least 3 views, got {V}")
    opts = replace(options, model_selection=False, progress=None, max_rms_px=None,
                   distortion=distortion or options.distortion)
    per_view = [math.nan] * V
    sq, n = 0.0, 0
    for k in range(K):
        test = [v for v in range(V) if v % K == k]
        train = [v for v in range(V) if v % K != k]
        tr = obs.subset(train)
        cam = initialize(tr, "unified", options=opts, blur=False)  # geometry only: the lens mode does not enter
        fit = fit_geometry(cam, tr, opts, mode="unified")
        pred = predict_views(fit.camera, obs.subset(test), opts)
        sq += pred.rss["corners"]
        n += pred.rss["n_corners"]
        for v, view in zip(test, pred.views):
            per_view[v] = view["rms_reprojection_px"]
    return {"rms_px": math.sqrt(sq / max(n, 1)), "per_view_px": per_view, "folds": K,
            "median_view_px": float(np.nanmedian(per_view))}
