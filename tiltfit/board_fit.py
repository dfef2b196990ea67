"""Fitting the target's shape beside the camera, and choosing how much of it the views support.

    fit_board(camera, obs, options, model)    -> FitResult with `board` set (that model fitted)
    select_board(camera, obs, options, ...)   -> FitResult with `board` set (model chosen by held-out error)
    held_out_rms(obs, options, model)         -> K-fold held-out error with that board model

The models themselves (`Board`, `BOARD_MODELS`) are in `tiltfit.board`, below the fit that uses them.
"""
from __future__ import annotations

import math
from dataclasses import replace

from .board import BOARD_MODELS, BOARD_TOLERANCE, MAX_BOARD_JACOBIAN_ENTRIES, Board
from .fit import FitError, fit_geometry
from .model import Observations
from .validate import held_out_rms as _held_out


def held_out_rms(obs: Observations, options, model: str, folds: int = 5, start=None) -> dict:
    """K-fold held-out reprojection RMS (px per corner) of a geometric calibration that fits the board as `model`:
    each fold fits lens and board on the other views, then only the poses of its own views with both held
    (`tiltfit.validate.held_out_rms` with a board). Returns that function's dict plus the model."""
    out = _held_out(obs, options, folds, start=start, board=model)
    out["board"] = model
    return out


def fit_board(camera, obs: Observations, options, model: str, mode: str = "unified", board: Board | None = None):
    """The geometric fit (`tiltfit.fit.fit_geometry`, distortion as `options` names it) with the board `model`
    fitted beside the camera; `board` (if given, of that model) starts it. The result's `board` holds it."""
    b = board.copy() if board is not None and board.model == model else Board(obs.points_mm, model)
    return fit_geometry(camera, obs, options, mode, board=b)


def select_board(camera, obs: Observations, options, mode: str = "unified", models=BOARD_MODELS, say=None,
                 folds: int = 5, flat=None):
    """Fit each board model and keep the simplest one the held-out views support.

    Each model in `models` is fitted on all views (distortion as `options.distortion` names it, principal point
    free when `options.free_principal_point` is True) and scored by its K-fold held-out error
    (`held_out_rms`): a richer model is chosen only where it predicts the held-out views better than every
    simpler one by more than `BOARD_TOLERANCE`. With fewer than 3 views no held-out error is computed (and the
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
        if size > MAX_BOARD_JACOBIAN_ENTRIES:
            entry["refused"] = (f"not fitted ({obs.n_views} views × {obs.points_mm.shape[0]} points × "
                                f"{entry['n_params']} parameters: a dense block of {size:.2g} entries)")
            continue
        try:
            fit = flat if (m == "flat" and flat is not None) else fit_board(camera.copy(), obs, quiet, m, mode)
            if fit.board is None:
                fit.board = Board(obs.points_mm, "flat")
        except (FitError, ValueError) as e:
            entry["refused"] = f"not fitted ({e})"
            continue
        fits[m] = fit
        entry["rms_px"] = math.sqrt(fit.rss["corners"] / max(fit.rss["n_corners"] // 2, 1))
        if obs.n_views >= 3 and len(models) > 1:
            try:
                reuse = m == "flat" and flat is not None and (flat.held_out or {}).get("folds") == folds
                entry["held_out"] = flat.held_out if reuse else held_out_rms(obs, quiet, m, folds,
                                                                             start=fit.camera)
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
    # Simplest first: a richer model is chosen where it beats every simpler one by the tolerance.
    chosen, best = None, math.inf
    for e in entries:
        if e["model"] not in fits:
            continue
        score = e.get("held_out_rms_px", math.inf)
        if chosen is None or score < (1 - BOARD_TOLERANCE) * best:
            chosen = e["model"]
        best = min(best, score)
    for e in entries:
        e["chosen"] = e["model"] == chosen
    return fits[chosen], entries
