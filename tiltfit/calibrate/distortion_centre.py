"""Where a tilted lens's distortion is centred, and which terms it needs (issue 33 §1).

A real lens's radial distortion is symmetric about its own axis (`renderer.Lens.distortion_centre` "lens_axis"),
which a tilt θL turns away from the principal point by w tan θL. About the principal point the same mapping is
not radial: a sensor-centred model imitates it with decentring (p1, p2) and higher terms (k3), and fits the
views nearly as well, with a biased θL. So the centre and the terms are chosen together, after the corner-and-
blur fit has measured θL (the corners alone hardly see the tilt):

1. the lens-axis fit with the base fit's terms reaches its own optimum: besides the base fit's values it is
   started where the lens axis says, the decentring terms dropped and the radial ones refitted about the axis on
   the corners with the tilt held, then fitted in full; the better of the two is kept;
2. under `--distortion auto`, each model with no more terms than the sensor-centred choice is scored about the
   lens axis by its K-fold held-out error (θF and φ held at the fit's in every fold), beside the sensor-centred
   choice scored the same way; the fewest terms within `HELD_OUT_TOLERANCE` of the smallest error win (at equal
   terms, the smaller error);
3. the lens axis replaces the principal point only where its fit (with the chosen terms) is also better than the
   sensor-centred fit with those terms by the likelihood-ratio test, the choice of centre charged one parameter
   (`likelihood_ratio`, χ²(1) and BIC): an untilted lens keeps the usual model.
"""
from __future__ import annotations

import math
from dataclasses import replace

import torch

from renderer.cameras.distortion import MODEL_TERMS, MODELS as DISTORTION_MODELS

from tiltfit.calibrate.fit import FitError, FitOptions, FitResult, _fit_camera, fit_geometry, per_corner_rms_px
from tiltfit.target.shape import with_points
from tiltfit.calibrate.model import Observations, LensCamera, distortion_parameter_names
from tiltfit.select.nested import likelihood_ratio

#: The radial terms kept when the lens-axis fit is started afresh (decentring and k3 imitate the axis's offset).
_RADIAL = ("dist_k1", "dist_k2")


def _log_rss(fit: FitResult) -> float:
    """Σ_g n_g log RSS_g over the corner and blur groups: twice the negative log-likelihood up to a constant
    (the likelihood-ratio statistic is its difference, `tiltfit.select.stats.nested_test`)."""
    return sum(fit.rss[f"n_{g}"] * math.log(max(fit.rss[g], 1e-300)) for g in ("corners", "blur")
               if fit.rss.get(f"n_{g}", 0) > 0)


def _with_terms(camera: LensCamera, model: str, centre: str, keep: tuple | None = None) -> LensCamera:
    """A copy of `camera` (its free parameters as they are) with the distortion about `centre` and only `model`'s
    terms free; the other coefficients, and those not in `keep` (names) where given, set to 0."""
    cam = camera.copy()
    cam.distortion_centre = centre
    free = set(distortion_parameter_names(model))
    with torch.no_grad():
        for name in cam.parameter_names("distortion"):
            if name not in free or (keep is not None and name not in keep):
                getattr(cam, name).zero_()
    cam.freeze("distortion")
    if free:
        cam.free(*sorted(free))
    return cam


def _board_of(fit: FitResult, board):
    """The board `fit` was made with: its own fitted one, else `board` (held as fitted before it), else None."""
    own = getattr(fit, "board", None)
    return own if own is not None else board


def _fit_about(base: FitResult, obs: Observations, mode: str, options: FitOptions, init_sigma, model: str,
               centre: str, board=None) -> FitResult:
    """The corner-and-blur fit with `model`'s terms about `centre`, the best of two starts: `base`'s values, and
    (about the lens axis) the radial terms refitted on the corners with the tilt held, the others dropped.
    `obs` holds the target file's points where `board` (a fitted `tiltfit.target.shape.Board`, or None) is given: the
    board is then refitted with the lens (the shape fitted with the other centre may have absorbed some of
    the distortion's offset)."""
    quiet = replace(options, model_selection=False, progress=None)
    board = _board_of(base, board)
    starts = [(_with_terms(base.camera, model, centre), board)]
    if centre == "lens_axis":
        cam = _with_terms(base.camera, model, centre, keep=_RADIAL)
        try:
            geometry = fit_geometry(cam, obs, replace(quiet, distortion=model), mode="unified",
                                    board=None if board is None else board.copy())
            fresh = geometry.camera.copy()
            for name, p in cam.named_parameters():  # the full fit frees what the base fit freed
                getattr(fresh, name).requires_grad_(p.requires_grad)
            fresh.distortion_centre = centre
            starts.append((fresh, geometry.board))
        except FitError:
            pass
    best, error = None, None
    for cam, shape in starts:
        try:
            fit = _fit_camera(cam, obs, quiet, init_sigma, mode=mode, board=None if shape is None else shape.copy())
        except FitError as e:
            error = e
            continue
        if best is None or _log_rss(fit) < _log_rss(best):
            best = fit
    if best is None:
        raise error
    return best


def _held_out(fit: FitResult, obs: Observations, options: FitOptions, model: str, board=None) -> dict:
    """`validate.held_out_rms` of `model` about `fit`'s centre (θF and φ held at `fit`'s in every fold), its lens
    (and board, refitted in each fold, where there is one) started from the geometric fit on all views."""
    from tiltfit.select.held_out import held_out_rms

    opts = replace(options, model_selection=False, progress=None, distortion=model)
    board = _board_of(fit, board)
    geometry = fit_geometry(fit.camera, obs, opts, mode="unified", board=None if board is None else board.copy())
    geometry.camera.distortion_centre = fit.camera.distortion_centre
    return held_out_rms(obs, opts, options.held_out_folds, start=geometry.camera, board=geometry.board)


def with_distortion_centre(base: FitResult, obs: Observations, mode: str, options: FitOptions, init_sigma,
                           model: str, choose_terms: bool, board=None, say=None):
    """Test the lens axis as the distortion's centre against `base` (about the principal point, `model`'s terms),
    and with `choose_terms` choose the terms with it (module docstring). Returns (fit, entry or None where there
    is no distortion to centre, the distortion model of the fit returned, the lens-axis held-out entries to add
    to the distortion selection). `board`: the target's fitted shape (a non-flat `tiltfit.target.shape.Board`) that
    `obs`'s points are, or None; every fit here refits it (from the target file's points), and a lens-axis fit
    returned carries its own."""
    from tiltfit.select.held_out import HELD_OUT_TOLERANCE

    if base.camera.distortion_centre == "lens_axis" or not bool(base.camera.distortion.detach().any()) \
            or model not in MODEL_TERMS or not MODEL_TERMS[model]:
        return base, None, model, []
    if board is not None:
        obs = with_points(obs, board.nominal_mm)
    try:
        alt = _fit_about(base, obs, mode, options, init_sigma, model, "lens_axis", board)
    except FitError as e:
        return base, {"error": str(e), "justified": None, "fitted": False, "chosen": "sensor"}, model, []
    restricted, full, terms, entries, scores, held_centre = base, alt, model, [], {}, None
    if choose_terms and obs.n_views >= 3:
        fits = {("lens_axis", model): alt}
        try:
            scores[("sensor", model)] = _held_out(base, obs, options, model, board)["rms_px"]
        except FitError:
            pass
        for m in DISTORTION_MODELS:
            if not MODEL_TERMS[m] or len(MODEL_TERMS[m]) > len(MODEL_TERMS[model]):
                continue
            try:
                fit = fits.get(("lens_axis", m)) or _fit_about(alt, obs, mode, options, init_sigma, m, "lens_axis")
                fits[("lens_axis", m)] = fit
                held = _held_out(fit, obs, options, m)
                scores[("lens_axis", m)] = held["rms_px"]
            except FitError:
                continue
            entries.append({"model": m, "centre": "lens_axis", "n_terms": len(MODEL_TERMS[m]),
                            "rms_px": per_corner_rms_px(fit.rss),
                            "held_out_rms_px": held["rms_px"], "held_out": held, "chosen": False})
        if ("sensor", model) in scores and len(scores) > 1:
            best = min(scores.values())
            within = [k for k in scores if scores[k] <= (1 + HELD_OUT_TOLERANCE) * best]
            held_centre, terms = min(within, key=lambda k: (len(MODEL_TERMS[k[1]]), scores[k]))
            if say:
                say("distortion centre and terms by held-out error: " + ", ".join(
                    f"{m} about the {'lens axis' if c == 'lens_axis' else 'principal point'} {v:.4f} px"
                    for (c, m), v in sorted(scores.items(), key=lambda kv: kv[1])))
            if held_centre == "sensor":
                terms = model
            elif terms != model:
                full = fits[("lens_axis", terms)]
                try:  # the sensor-centred fit with the same terms: the test compares centres, not terms
                    restricted = _fit_about(base, obs, mode, options, init_sigma, terms, "sensor", board)
                except FitError:
                    restricted, full, terms = base, alt, model
    entry = likelihood_ratio(restricted, full, 1, options.alpha)
    entry["theta_L_deg_full"] = full.values["theta_L_deg"]
    entry["model"] = terms
    if scores:
        entry["held_out_rms_px"] = {f"{c} {m}": v for (c, m), v in scores.items()}
        entry["held_out_choice"] = held_centre
    # With held-out errors, both must prefer the lens axis: the test (this centre fits better than chance would
    # make one more parameter) and the held-out error (it predicts new views better with these terms).
    justified = bool(entry["justified"]) and held_centre in (None, "lens_axis")
    entry["fitted"] = justified
    entry["chosen"] = "lens_axis" if justified else "sensor"
    if say:
        say(f"model selection: freeing the distortion's centre (the lens axis) is "
            f"{'justified' if justified else 'not justified'} (Λ = {entry['lr_statistic']:.3g}, p = "
            f"{entry['p_value']:.3g}, ΔBIC = {entry['delta_bic']:.3g}, {terms}): distortion about the "
            + ("lens axis" if justified else "principal point"))
    if not justified:
        return base, entry, model, entries
    for e in entries:
        e["chosen"] = e["model"] == terms
    return full, entry, terms, entries
