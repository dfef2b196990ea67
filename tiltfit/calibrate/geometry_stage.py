"""The calibration's corner-only stages: the geometric fit with its distortion terms and principal point chosen on
the data, and the target's shape (`tiltfit.target.shape`) with the distortion chosen again beside it.

    fit_geometry(camera, obs, options, mode)            -> FitResult (distortion "auto": chosen by held-out error)
    geometry_with_principal_point(camera, obs, ...)     -> (FitResult, principal-point test or None)
    fit_board_stage(geometry, obs, mode, options, ...)  -> (FitResult with the board, its selection, held-out)
"""
from __future__ import annotations

import math
from dataclasses import replace

import torch

from tiltfit.calibrate import fit as _core
from tiltfit.calibrate.fit import FitError, FitOptions, FitResult
from tiltfit.calibrate.model import Observations, LensCamera
from tiltfit.select.board import select_board
from tiltfit.select.held_out import DISTORTION_MODELS, select_distortion
from tiltfit.select.nested import likelihood_ratio


def fit_geometry(camera: LensCamera, obs: Observations, options: FitOptions, mode: str = "unified",
                 say=None, hold_distortion: bool = False) -> FitResult:
    """`tiltfit.calibrate.fit.fit_geometry`, with `options.distortion` "auto" choosing the terms by their held-out error
    (`tiltfit.select.held_out.select_distortion`; the choice is in `FitResult.distortion_selection`)."""
    if options.distortion == "auto" and not hold_distortion:
        return select_distortion(camera, obs, options, mode, say, folds=options.held_out_folds)
    return _core.fit_geometry(camera, obs, options, mode, say, hold_distortion)


def geometry_with_principal_point(camera: LensCamera, obs: Observations, options: FitOptions, mode: str,
                                   say=None) -> tuple[FitResult, dict | None]:
    """The geometric fit, with the principal point free where the views support it.

    `options.free_principal_point` True or False: as given (no test). None: fitted free (held if that fit
    fails: views that cannot locate it), then tested against the same fit with it held at the image centre
    (`likelihood_ratio`, 2 degrees of freedom, on the corners); kept free only when the test justifies it.
    Returns (fit, test entry or None).
    """
    if options.free_principal_point is not None:
        return fit_geometry(camera, obs, options, mode, say), None
    try:
        free = fit_geometry(camera, obs, replace(options, free_principal_point=True), mode, say)
    except FitError as e:
        if say:
            say(f"principal point held at the image centre (fitting it failed: {e})")
        fit = fit_geometry(camera, obs, replace(options, free_principal_point=False), mode, say)
        return fit, {"error": str(e), "justified": None, "fitted": False}
    cam = free.camera.copy()
    with torch.no_grad():
        cam.pp_scaled.zero_()
    held_opts = replace(options, free_principal_point=False, distortion=free.distortion_model)
    try:
        held = fit_geometry(cam, obs, held_opts, mode)
    except FitError as e:
        return free, {"error": str(e), "justified": True, "fitted": True}
    entry = likelihood_ratio(held, free, 2, options.alpha)
    entry["principal_point_px_full"] = free.values["principal_point_px"]
    entry["fitted"] = entry["justified"]
    say_test(say, "principal_point", entry, "fitted" if entry["justified"] else "held at the image centre")
    if entry["justified"]:
        return free, entry
    held.distortion_selection = free.distortion_selection
    held.choice_variance = {k: dict(v, principal_point_px=[0.0, 0.0]) for k, v in free.choice_variance.items()}
    return held, entry


def fit_board_stage(geometry: FitResult, obs: Observations, mode: str, options: FitOptions, distortion: str, say=None,
                    defer_sigma: bool = False):
    """The target's shape as `options.board` says (`tiltfit.target.shape`): a named model fitted, or "auto" chosen by
    the held-out error against the flat board's fit `geometry`. Returns (geometric fit with `board` set, the
    selection's entries, the chosen model's held-out error or None). `defer_sigma`: a distortion chosen again
    with the board gets its per-view σ only when asked (`select_distortion`; a blur fit follows)."""
    opts = replace(options, distortion=distortion)
    if options.board == "auto":
        fit, entries = select_board(geometry.camera, obs, opts, mode, say=say, folds=options.held_out_folds,
                                    flat=geometry)
        held = next((e.get("held_out") for e in entries if e.get("chosen")), None)
    else:
        fit, entries = select_board(geometry.camera, obs, opts, mode, models=(options.board,), say=say)
        held = None
    fit.distortion_selection = geometry.distortion_selection
    fit.held_out = geometry.held_out
    fit.distortion_model = distortion
    board_var = fit.choice_variance.get("board")
    fit.choice_variance = dict(geometry.choice_variance)
    if options.distortion == "auto" and fit.board.model != "flat":
        fit, held = _redistort(fit, obs, mode, opts, held, say, defer_sigma)
        fit.held_out = held
    if board_var:
        fit.choice_variance = dict(fit.choice_variance, board=board_var)
    return fit, entries, held


def _redistort(fit: FitResult, obs: Observations, mode: str, options: FitOptions, held, say=None,
               defer_sigma: bool = False):
    """The distortion model chosen again with the board as fitted (a flat board's misfit had asked for terms the
    fitted shape explains): `select_distortion` with the board fitted beside each model and refitted in each
    fold, so that the held-out errors it prints and records are those of the whole calibration (a choice made
    on the points fitted to all views scored the board on the views it was fitted to). `fit` and `held` (its
    held-out error, from the board's selection) are reused for its own model. Returns (fit, held-out dict)."""
    flat_entries = list(fit.distortion_selection or [])
    known = {fit.distortion_model: (fit, held)} if held is not None else {}
    # The candidates: the model chosen with the flat board and those with fewer terms (a board's shape explains
    # misfit that asked for terms; it does not determine terms the flat board's views could not).
    # Richer models refused with the flat board only because their projection was too uncertain are tried again:
    # the flat board's misfit inflates their σ (GoPro, 12 views: rational5 ±37 px with the flat board, ±5 px
    # with the free one).
    from tiltfit.select.held_out import PROJECTION_REFUSAL

    models = DISTORTION_MODELS[:DISTORTION_MODELS.index(fit.distortion_model) + 1]
    models += tuple(e["model"] for e in flat_entries if e["model"] not in models
                    and str(e.get("refused", "")).startswith(PROJECTION_REFUSAL))
    # ... and richer models the flat board's held-out views could not tell from the best (weight of their
    # model-choice variance above exp(-4.5), z < 3): with the board they may be chosen, and they stay in σ.
    close = ((fit.choice_variance or {}).get("distortion") or {}).get("weights", {})
    models += tuple(m for m in DISTORTION_MODELS if m not in models and close.get(m, 0.0) > math.exp(-4.5))
    models = tuple(m for m in DISTORTION_MODELS if m in models)
    try:
        sel = select_distortion(fit.camera, obs, options, mode, say, folds=options.held_out_folds, board=fit.board,
                                known=known, models=models, defer_sigma=defer_sigma)
    except FitError:
        return fit, held
    new, old = sel.distortion_model, fit.distortion_model
    # The richer models keep their entries from the flat board's choice (marked so).
    sel.distortion_selection += [dict(e, chosen=False, board="flat") for e in flat_entries
                                 if e["model"] not in models]
    if say and new != old:
        say(f"distortion chosen again with the board as fitted: {new} (was {old}); held-out "
            f"{sel.held_out['rms_px']:.4f} px per corner")
    sel.distortion_model = new
    return sel, sel.held_out if sel.held_out is not None else held


def board_line(board) -> str:
    """', sag ... ± ...' of a fitted board for the notes (values rounded to their σ)."""
    from tiltfit.report.summary import with_sigma

    s = board.summary()
    if board.model == "warp" and "sigma" in s:
        return ": " + ", ".join(f"{k} {with_sigma(s['parameters'][k], s['sigma'][k])}" for k in s["parameters"])
    spread = (f" (median σ of a point's coordinates {float(board.sigma.median()):.2g} mm)"
              if board.sigma is not None and len(board.sigma) else "")
    return (f": points moved up to {s['max_offset_in_plane_mm']:.2g} mm in the board's plane and "
            f"{s['max_offset_out_of_plane_mm']:.2g} mm out of it{spread}")


def say_test(say, label: str, entry: dict, outcome: str) -> None:
    """The progress line of a likelihood-ratio test (`likelihood_ratio`'s entry) and what it decided."""
    if say:
        say(f"model selection: freeing {label} is {'justified' if entry['justified'] else 'not justified'} "
            f"(Λ = {entry['lr_statistic']:.3g}, p = {entry['p_value']:.3g}, ΔBIC = {entry['delta_bic']:.3g}): "
            + outcome)
