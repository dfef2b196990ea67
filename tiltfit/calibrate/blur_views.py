"""One view whose blur widths disagree with the other views' (issue 33 §3): found, named, and left out of the
blur fit; its corners stay in the calibration.

A sharp photo of very low contrast (0.3 % of an 8-bit range is under one grey level) still gives good corners
through sub-pixel fitting, but its blur widths are the detector's answer to a staircase: all near 0 px, or
random. Fitted with the other views' widths, such a view drags U and d, makes the thin-lens blur model look wrong
for the whole lens, or stops the blur fit from converging.

The test is leave-one-view-out: the most suspect view's widths are left out, the blur model is fitted to the
other views, and the view is an outlier when its widths miss that fit's prediction by more than
`BLUR_VIEW_OUTLIER_FACTOR` times both the other views' median residual and the widths' measurement noise (a
view's widths from the same lens and detector scatter like the others' about one thin lens). Where the fit with
every view failed and the fit without the suspect succeeds, the suspect is the view that stopped it.

It is run only where the fit with every view is in trouble (`needs_screening`), so that clean data costs no
extra fit.
"""
from __future__ import annotations

import math
from typing import Callable

import numpy as np
import torch

from tiltfit.calibrate.fit import FitError
from tiltfit.calibrate.model import Observations, residuals

#: A view's blur residual (RMS, px) above this many times the other views' median residual and the widths'
#: noise is an outlier. Good views of one lens differ by up to about 5× on the shipped real sets (industrial_ds1:
#: 0.12–0.35 px under one fit, 0.71 px on a view with glare); a view of 0.3 %-contrast widths misses by 10–20×.
BLUR_VIEW_OUTLIER_FACTOR = 8.0
#: Suspect views refitted without their widths when the fit with all views failed (each costs one blur fit).
MAX_SUSPECTS = 2
#: The fewest other views with blur widths that a view is compared with.
MIN_OTHER_VIEWS = 2


def per_view_blur_rms(camera, obs: Observations) -> np.ndarray:
    """(V,) RMS blur residual of each view under `camera`, px (NaN where a view has no widths)."""
    with torch.no_grad():
        r = residuals(camera, obs).blur_px
    m = obs.blur_mask
    out = np.full(obs.n_views, math.nan)
    for v in range(obs.n_views):
        if bool(m[v].any()):
            out[v] = float(r[v][m[v]].pow(2).mean().sqrt())
    return out


def without_blur_of(obs: Observations, view: int) -> Observations:
    """The same observations with view `view`'s blur widths left out (its corners kept)."""
    blur = obs.blur_px.clone()
    blur[view] = math.nan
    out = Observations(obs.points_mm, obs.corners_px, blur, obs.image_size_px, obs.pixel_pitch_mm, list(obs.names))
    if hasattr(obs, "skipped"):
        out.skipped = obs.skipped
    return out


def _others_median(values: np.ndarray, v: int) -> float:
    others = np.delete(values, v)
    others = others[np.isfinite(others)]
    return float(np.median(others)) if len(others) else math.nan


def needs_screening(result, obs: Observations, noise_px: float) -> bool:
    """Whether the blur fit with every view (`result`, None where it failed) may have been spoiled by one view:
    it failed, its residuals exceed `BLUR_VIEW_OUTLIER_FACTOR` × the widths' noise overall, or one view's exceed
    that many times the other views' median."""
    if int((obs.blur_mask.sum(-1) > 0).sum()) < MIN_OTHER_VIEWS + 1:
        return False
    if result is None:
        return True
    rms = per_view_blur_rms(result.camera, obs)
    with torch.no_grad():
        overall = float(residuals(result.camera, obs).blur_px[obs.blur_mask].pow(2).mean().sqrt())
    if math.isfinite(noise_px) and overall > BLUR_VIEW_OUTLIER_FACTOR * noise_px:
        return True
    return any(rms[v] > BLUR_VIEW_OUTLIER_FACTOR * _others_median(rms, v) for v in range(len(rms))
               if math.isfinite(rms[v]))


def suspects(result, obs: Observations) -> list[int]:
    """Views ordered by how much their widths stand out, most suspect first (at most `MAX_SUSPECTS`).

    With a fit: its per-view residual against the other views' median. Without one (the fit failed): how far the
    view's median width and its widths' spread lie from the other views' (a model-free score)."""
    has = [v for v in range(obs.n_views) if bool(obs.blur_mask[v].any())]
    if result is not None:
        rms = per_view_blur_rms(result.camera, obs)
        score = {v: rms[v] / max(_others_median(rms, v), 1e-9) for v in has}
    else:
        b = obs.blur_px.numpy()
        med = np.array([np.nanmedian(b[v]) if v in has else math.nan for v in range(obs.n_views)])
        mad = np.array([np.nanmedian(np.abs(b[v] - med[v])) if v in has else math.nan for v in range(obs.n_views)])
        score = {}
        for v in has:
            m, s = _others_median(med, v), _others_median(mad, v)
            score[v] = max(abs(med[v] - m) / max(s, 1e-3), mad[v] / max(s, 1e-3), s / max(mad[v], 1e-3))
    return sorted(has, key=lambda v: -score[v])[:MAX_SUSPECTS]


def screen_blur_views(fit: Callable, obs: Observations, noise_px: Callable, accept: Callable | None = None):
    """The blur fit with a view whose widths disagree with the others' left out, naming it.

    Args:
        fit: obs -> (result or None, undetermined keys (None: decided by the caller), note or None); raises
            FitError (`calibration._fit_blur` with everything else bound). Called with every view first, then
            without each suspect's widths.
        obs: the observations; noise_px: obs -> the widths' measurement noise σ, px (`calibration.blur_noise_px`;
            the outlier is judged against the other views' noise, not a pooled one it inflates).
        accept: (result, obs) -> whether the blur model fitted without a suspect's widths describes the lens
            (`calibration.blur_misfit` is None); a view is left out only then: where the model is refused with or
            without it (widths at a detector's floor in every view), that view did not sink the fit, and every
            view's widths stay (the refusal and its noise are the whole set's) [None: no such check].
    Returns:
        (result, undetermined, note, observations used (the outlier's widths left out), line naming the view or
        None).
    Raises:
        FitError: the fit with every view failed and no single view's widths were the cause.
    """
    failure = None
    try:
        first = fit(obs)
    except FitError as e:
        first, failure = (None, ["U_mm", "d_mm"], None), e
    if not needs_screening(first[0], obs, noise_px(obs)):
        if failure is not None:
            raise failure
        return (*first, obs, None)
    for v in suspects(first[0], obs):
        kept = without_blur_of(obs, v)
        try:
            alt = fit(kept)
        except FitError:
            continue
        if alt[0] is None:
            continue
        rms = per_view_blur_rms(alt[0].camera, obs)
        others = _others_median(rms, v)
        noise = noise_px(kept)
        bar = BLUR_VIEW_OUTLIER_FACTOR * max(others, noise if math.isfinite(noise) else 0.0)
        rescued = first[0] is None
        if (rms[v] > bar or rescued) and (accept is None or accept(alt[0], kept)):
            why = (f"the blur fit with them {'did not converge' if failure is not None else 'failed'}; "
                   if rescued else "")
            line = (f"{obs.names[v]}: its blur widths disagree with the other views' ({why}RMS {rms[v]:.3g} px from "
                    f"the blur fitted to the others, whose median is {others:.3g} px); left out of the blur fit, "
                    f"its corners kept")
            return (*alt, kept, line)
    if failure is not None:
        raise failure
    return (*first, obs, None)
