"""Fitting the target's shape beside the camera, and choosing how much of it the views support.

    fit_board(camera, obs, options, model)    -> FitResult with `board` set (that model fitted)
    select_board(camera, obs, options, ...)   -> FitResult with `board` set (model chosen by held-out error)
    held_out_rms(obs, options, model)         -> K-fold held-out error with that board model
    held_out_gain(simple, rich, obs)          -> a richer model's held-out gain in standard errors over the views
                                                 (`tiltfit.select.held_out`'s, shared with the distortion's choice)
    sigma_ratio(fit, flat)                    -> how much a board model inflates the lens's σ over the flat board's

The models themselves (`Board`, `BOARD_MODELS`) are in `tiltfit.target.shape`, below the fit that uses them.
"""
from __future__ import annotations

import math
from dataclasses import replace

from tiltfit.target.shape import (BOARD_GAIN_Z, BOARD_MODELS, BOARD_TOLERANCE, MAX_BOARD_JACOBIAN_ENTRIES,
                    MIN_CORNERS_PER_BOARD_PARAMETER, Board, free_board_at)
from tiltfit.calibrate.fit import FitError, fit_geometry, per_corner_rms_px
from tiltfit.calibrate.model import Observations
from tiltfit.select.held_out import choice_variance, held_out_gain
from tiltfit.select.held_out import held_out_rms as _held_out


def held_out_rms(obs: Observations, options, model: str, folds: int = 5, start=None, fitted=None) -> dict:
    """K-fold held-out reprojection RMS (px per corner) of a geometric calibration that fits the board as `model`:
    each fold fits lens and board on the other views, then only the poses of its own views with both held
    (`tiltfit.select.held_out.held_out_rms` with a board). `fitted` (the board of `model` fitted with `start` on
    all views) starts each fold's board where the folds start from that fit (`options.held_out_start` "fit").
    Returns that function's dict plus the model."""
    warm = fitted is not None and fitted.model == model and options.held_out_start == "fit"
    out = _held_out(obs, options, folds, start=start, board=fitted if warm else model)
    out["board"] = model
    return out


def fit_board(camera, obs: Observations, options, model: str, mode: str = "unified", board: Board | None = None):
    """The geometric fit (`tiltfit.calibrate.fit.fit_geometry`, distortion as `options` names it) with the board `model`
    fitted beside the camera; `board` (if given, of that model) starts it. The result's `board` holds it."""
    b = board.copy() if board is not None and board.model == model else Board(obs.points_mm, model)
    return fit_geometry(camera, obs, options, mode, board=b)


def select_board(camera, obs: Observations, options, mode: str = "unified", models=BOARD_MODELS, say=None,
                 folds: int = 5, flat=None):
    """Fit each board model and keep the simplest one the held-out views support.

    Each model in `models` is fitted on all views (distortion as `options.distortion` names it, principal point
    free when `options.free_principal_point` is True) and scored by its K-fold held-out error
    (`held_out_rms`): a richer model is chosen only where it predicts the held-out views better than every
    simpler one by more than `BOARD_TOLERANCE`, better than the model it displaces by `BOARD_GAIN_Z` standard
    errors over the views: `_choose`. The spread of the lens over the models the held-out views cannot tell apart
    is the chosen fit's `choice_variance["board"]` (`tiltfit.select.held_out.choice_variance`). A model with fewer than `MIN_CORNERS_PER_BOARD_PARAMETER` corners per parameter is not
    tried (asked for by name, it is fitted). With fewer than 3 views no held-out error is computed (and the
    flat board is kept when it is among `models`); a model whose dense Jacobian block would exceed
    `MAX_BOARD_JACOBIAN_ENTRIES` is refused.

    Args:
        camera: the starting camera (e.g. the flat geometric fit's).
        flat: the flat fit already made (a `FitResult`), or None.
    Returns:
        (FitResult of the chosen model with `board` set, [{model, n_params, rms_px, held_out_rms_px | refused,
        chosen}]).
    """
    entries, fits = [], {}
    quiet = replace(options, progress=None, model_selection=False)
    for m in models:
        entry = {"model": m, "n_params": Board(obs.points_mm, m).n_params}
        entries.append(entry)
        size = obs.n_views * obs.points_mm.shape[0] * 3 * entry["n_params"]
        corners = int(obs.corner_mask.sum())
        if len(models) > 1 and corners < MIN_CORNERS_PER_BOARD_PARAMETER * entry["n_params"]:
            entry["refused"] = (f"not tried: too few corners for its parameters ({corners} corners for "
                                f"{entry['n_params']}; at least {MIN_CORNERS_PER_BOARD_PARAMETER:g} a parameter)")
            continue
        if size > MAX_BOARD_JACOBIAN_ENTRIES:
            entry["refused"] = (f"not fitted ({obs.n_views} views × {obs.points_mm.shape[0]} points × "
                                f"{entry['n_params']} parameters: a dense block of {size:.2g} entries)")
            continue
        try:
            # warm start: each model from the richest one fitted before it (its lens, and its points as the free
            # board's start)
            prev = fits[next(reversed(fits))] if fits else None
            start_board = free_board_at(prev.board) if m == "free" and prev is not None and prev.board is not None \
                else None
            fit = flat if (m == "flat" and flat is not None) else fit_board(
                (prev.camera if prev is not None else camera).copy(), obs, quiet, m, mode, board=start_board)
            if fit.board is None:
                fit.board = Board(obs.points_mm, "flat")
        except (FitError, ValueError) as e:
            entry["refused"] = f"not fitted ({e})"
            continue
        fits[m] = fit
        entry["rms_px"] = per_corner_rms_px(fit.rss)
        if obs.n_views >= 3 and len(models) > 1:
            try:
                reuse = m == "flat" and flat is not None and (flat.held_out or {}).get("folds") == folds
                entry["held_out"] = flat.held_out if reuse else held_out_rms(obs, quiet, m, folds,
                                                                             start=fit.camera, fitted=fit.board)
                entry["held_out_rms_px"] = entry["held_out"]["rms_px"]
            except FitError as e:
                entry["refused"] = f"held-out error not computed ({e})"
                fits.pop(m)
        if say and "refused" not in entry:
            say(f"board {m}: RMS {entry['rms_px']:.4f} px per corner"
                + (f", held-out {entry['held_out_rms_px']:.4f} px" if "held_out_rms_px" in entry else ""))
    if not fits:
        raise FitError("no board model could be fitted: " + "; ".join(f"{e['model']}: {e.get('refused')}"
                                                                       for e in entries))
    chosen = _choose(entries, fits, obs)
    for e in entries:
        e["chosen"] = e["model"] == chosen
    var = choice_variance({e["model"]: (fits[e["model"]].values, e.get("held_out")) for e in entries
                           if e["model"] in fits}, chosen, obs, BOARD_GAIN_Z)
    fits[chosen].choice_variance = dict(fits[chosen].choice_variance, **({"board": var} if var else {}))
    return fits[chosen], entries


def _choose(entries: list, fits: dict, obs: Observations) -> str:
    """The simplest fitted model no richer one displaces. A richer model displaces the one chosen so far where
    (1) its held-out error beats every simpler one's by `BOARD_TOLERANCE`, (2) its gain over the chosen one is
    `BOARD_GAIN_Z` standard errors over the views (`held_out_gain`). An entry that fails (2) says why under
    `not_chosen`. `sigma_ratio` (the lens's σ with it over the flat board's) is recorded, not used: as a rule it
    refused warp on one quarter of industrial_ds1 (3.6×) where the three others chose it, a 20-40 px flip of the
    principal point (benchmarks/results/small_boards.md); what the choice leaves open is in σ (`choice_variance`)."""
    chosen, best = None, math.inf
    flat = fits.get("flat")
    for e in entries:
        if e["model"] not in fits:
            continue
        score = e.get("held_out_rms_px", math.inf)
        if chosen is None:
            chosen = e["model"]
        elif score < (1 - BOARD_TOLERANCE) * best:
            prev = next(x for x in entries if x["model"] == chosen)
            gain = held_out_gain(prev.get("held_out"), e.get("held_out"), obs)
            if gain is not None:
                e["gain_z"] = gain
            ratio = sigma_ratio(fits[e["model"]], flat) if flat is not None else None
            if ratio is not None:
                e["sigma_ratio"] = ratio
            if gain is not None and gain < BOARD_GAIN_Z:
                e["not_chosen"] = (f"its held-out gain over {chosen} is {gain:.2g} standard errors over the views "
                                   f"(at least {BOARD_GAIN_Z:g} needed)")
            else:
                chosen = e["model"]
        best = min(best, score)
    return chosen


def sigma_ratio(fit, flat) -> float | None:
    """The largest ratio of the lens's σ (focal length, cx, cy) in `fit` to those in `flat` (the flat board's fit
    on the same views), or None where either has no σ (principal point held: the focal length alone)."""
    def lens_sigma(f):
        s = f.sigma or {}
        pp = s.get("principal_point_px") or [math.nan, math.nan]
        return [s.get("w_mm", math.nan), *pp]

    ratios = [a / b for a, b in zip(lens_sigma(fit), lens_sigma(flat))
              if math.isfinite(a) and math.isfinite(b) and b > 0 and a > 0]
    return max(ratios) if ratios else None
