"""The calibration's blur stage: the corner-and-blur fit from the geometric one, the tests of the lens's tilt axis
and distortion centre (joint fit), and the judgement of the thin-lens blur model on the widths
(`tiltfit.calibrate.blur_checks`): where it does not describe them, U and d are undetermined and the calibration is
geometric.

    blur_stage(cam, obs, mode, init, init_sigma, options, choices, geometry, noise_px, say) -> BlurOutcome
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import torch

from tiltfit.calibrate.blur_checks import (blur_misfit, blur_noise_px, blur_trend, focus_below_floor,
                                           undetermined_focus_deferred)
from tiltfit.calibrate.blur_views import screen_blur_views
from tiltfit.calibrate.distortion_centre import with_distortion_centre
from tiltfit.calibrate.fit import FitError, FitOptions, FitResult, _fit_camera, _set_free, with_deferred_sigma
from tiltfit.calibrate.geometry_stage import fit_geometry, say_test
from tiltfit.calibrate.model import Observations, LensCamera, distortion_parameter_names
from tiltfit.calibrate.start import start_blur
from tiltfit.select.nested import blur_depends_on_depth, likelihood_ratio
from tiltfit.target.shape import with_points


@dataclass
class BlurOutcome:
    """What the blur stage decided.

    Attributes:
        result: the corner-and-blur fit, or None where the calibration is geometric (`geometry` then holds it).
        geometry: the geometric fit (the stage's own where it had to make one), or None.
        obs: the views the fit used (a view whose widths disagree left out; the board's fitted points).
        choices: the `ModelChoices` with the stage's decisions (board refitted beside the lens, tilt axis,
            distortion centre and terms about it).
        undetermined: keys the widths do not determine; notes, warnings: one line each.
        noise_px: the widths' measurement noise; misfit: why the blur model was refused, or None; trend:
            `blur_trend`'s dict or None.
    """

    result: FitResult | None
    geometry: FitResult | None
    obs: Observations
    choices: object
    undetermined: list = field(default_factory=list)
    notes: list = field(default_factory=list)
    warnings: list = field(default_factory=list)
    noise_px: float = math.nan
    misfit: str | None = None
    trend: dict | None = None


def blur_stage(cam: LensCamera, obs: Observations, mode: str, init, init_sigma, options: FitOptions, choices,
               geometry: FitResult | None, noise_px: float, say=None) -> BlurOutcome:
    """The blur fit (one view whose widths disagree with the others' left out, named), the tilt tests of the joint
    fit, then the judgement of the blur model (`judge_blur_model`)."""
    # the widths' noise is found on the target file's points (a fitted board's are no longer on exact lines)
    file_points = choices.board.nominal_mm if choices.board is not None else obs.points_mm
    noise_of = (lambda o: noise_px if o is obs else blur_noise_px(with_points(o, file_points)))
    board = choices.board
    # `undetermined` None: what the fit's σ leave undetermined is decided after the model is judged (a refused
    # model needs no per-view σ, which `_fit_blur` defers)
    result, undetermined, note, obs, outlier = screen_blur_views(
        lambda o: _fit_blur(cam.copy(), o, mode, init, init_sigma, options, choices.distortion, geometry, say,
                            board=board),
        obs, noise_of, accept=lambda r, o: blur_misfit(r, o, noise_of(o)) is None)
    notes = [outlier] if outlier else []
    if outlier:
        noise_px = blur_noise_px(with_points(obs, file_points))  # the outlier's widths inflated it
    if result is not None and result.board is not None:  # refitted beside the lens: its σ is in the lens's
        choices = replace(choices, board=result.board)
        obs = with_points(obs, result.board.points())
    notes += [note] if note else []
    fitted = result
    if result is not None and mode == "joint" and options.model_selection:
        with_deferred_sigma(result)  # σ as at once before the tests refit from it
        result, obs, choices = tilt_tests(result, obs, mode, options, init_sigma, choices, say)
    out = BlurOutcome(result, geometry, obs, choices, undetermined or [], notes, [], noise_px)
    if result is not None and mode != "tilt":
        out = judge_blur_model(out, cam, mode, options, say)
    if undetermined is None and out.result is not None:
        out.undetermined = undetermined_focus_deferred(fitted)
    if out.undetermined and out.geometry is not None and out.result is not None and len(out.undetermined) == 2:
        out.result = None  # neither focus parameter determined: report the geometric fit
    if out.result is not None:  # reported: its per-view σ (`_fit_blur` deferred them)
        with_deferred_sigma(out.result)
    return out


def tilt_tests(result: FitResult, obs: Observations, mode: str, options: FitOptions, init_sigma, choices, say=None):
    """The joint fit's tests of the lens: its tilt axis (a lens tilted about a turned axis misfits the tilt about x;
    tested before the model is judged) and the centre of its distortion (about its own axis, where the tilt axis
    is tested again: the distortion's centre then says where the lens tilts). Not in the tilt stage: its held
    stage-1 U and d misfit a tilted lens, which a free axis would absorb. Returns (fit, obs, choices)."""
    result, axis_test = _with_tilt_axis(result, obs, mode, options, init_sigma, say)
    centre_test, distortion, axis_entries, board = None, choices.distortion, [], choices.board
    if options.distortion_centre == "auto":
        shaped = board if board is not None and board.model != "flat" else None
        result, centre_test, distortion, axis_entries = with_distortion_centre(
            result, obs, mode, options, init_sigma, distortion, options.distortion == "auto", shaped, say)
        if shaped is not None and getattr(result, "board", None) is not None:  # refitted about the axis
            board = result.board
            obs = with_points(obs, board.points())
    if centre_test is not None and centre_test["fitted"] and not axis_test.get("fitted"):
        result, axis_test = _with_tilt_axis(result, obs, mode, options, init_sigma, say)
    return result, obs, replace(choices, tilt_axis_test=axis_test, distortion_centre_test=centre_test,
                                distortion=distortion, axis_entries=axis_entries, board=board)


def judge_blur_model(out: BlurOutcome, cam: LensCamera, mode: str, options: FitOptions, say=None) -> BlurOutcome:
    """Whether the thin-lens blur model describes the widths (`blur_misfit`; a tilted lens is a thin lens too, so
    an untilted fit that misfits or trends is judged with θF freed), whether U rests on widths below the detector's
    floor, and whether the residuals trend with depth. The tilt stage holds stage 1's U and d, which the lens's
    tilt moves (hinge rule): its residuals judge that approximation, not the thin-lens model, so it is not judged.
    Where the model is refused, U and d (and θF) are undetermined and the geometric fit is reported."""
    result, obs, noise = out.result, out.obs, out.noise_px
    misfit = blur_misfit(result, obs, noise)
    trend = None if misfit else blur_trend(result, obs, noise)
    if (misfit or (trend and trend["significant"])) and mode == "unified" and options.model_selection:
        tilted = _with_theta_F(result, obs, options)
        if tilted is not None:
            misfit = blur_misfit(tilted, obs, noise)
            trend = None if misfit else blur_trend(tilted, obs, noise)
    head = "the thin-lens blur model does not describe this lens"
    if not misfit:
        floor = focus_below_floor(result, obs, options, mode)
        if floor:
            head, misfit, trend = "the blur widths do not determine the focus", floor, None
    if trend and trend["significant"]:
        out.warnings.append(trend["why"] + "; U and d may be biased by it")
    out.misfit, out.trend = misfit, trend
    if misfit:
        out.warnings.append(f"{head}: {misfit}; U and d are not reported and the tilt is not tested (calibration "
                            f"from the corners only)")
        out.undetermined = ["U_mm", "d_mm"] + (["theta_F_deg"] if mode != "unified" else [])
        if out.geometry is None:
            out.geometry = fit_geometry(cam, obs, replace(options, distortion=out.choices.distortion), mode, say)
        out.result = None
    return out


MAX_OFFSET_CORRELATION = 0.99  # |multiple correlation| of the blur offset with (1/U, d) above which it is held


def _offset_correlation(result: FitResult) -> float:
    """Multiple correlation of the fitted blur offset with 1/U and log d: near 1 when blur widths all lie on
    one side of the plane of focus, where an offset and a change of U explain the data equally well."""
    names = result.parameter_names
    if "blur_offset_px" not in names:
        return 0.0
    idx = [names.index(n) for n in ("inv_U_per_m", "d_scaled") if n in names]
    if not idx:
        return 0.0
    if result.covariance is None:  # not computed (`FitOptions.uncertainties` off)
        return math.nan
    C = result.covariance.submatrix([names.index("blur_offset_px")] + idx)
    c_oo = float(C[0, 0])
    c_ol = C[0, 1:]
    C_ll = C[1:, 1:]
    try:
        r2 = float(c_ol @ torch.linalg.solve(C_ll, c_ol)) / c_oo
    except RuntimeError:
        return 1.0
    return math.sqrt(min(max(r2, 0.0), 1.0))


def _with_tilt_axis(base: FitResult, obs: Observations, mode: str, options: FitOptions, init_sigma, say=None):
    """The tilt axis's direction φ freed (a tilt-shift lens's rotation) and tested against `base`, the tilt about
    the camera x axis (`likelihood_ratio`, 1 degree of freedom): the freed fit replaces `base` only where the
    test justifies it. Returns (fit, test entry)."""
    cam = base.camera.copy()
    cam.free("phi")
    try:
        alt = _fit_camera(cam, obs, replace(options, model_selection=False, progress=None), init_sigma, mode=mode)
    except FitError as e:
        return base, {"error": str(e), "justified": None, "fitted": False}
    entry = likelihood_ratio(base, alt, 1, options.alpha)
    entry["tilt_axis_deg_full"] = alt.values["tilt_axis_deg"]
    entry["fitted"] = entry["justified"]
    say_test(say, "the tilt axis's direction", entry,
              f"φ = {alt.values['tilt_axis_deg']:.2f} ± {alt.sigma['tilt_axis_deg']:.2g}°" if entry["justified"]
              else "held at 0 (tilt about the camera x axis)")
    return (alt if entry["justified"] else base), entry


def _with_theta_F(base: FitResult, obs: Observations, options: FitOptions) -> FitResult | None:
    """The fit with θF freed as well (the θF test's alternative), or None where it fails: a capture through a
    tilted lens misfits the untilted model (and its residuals trend with depth), which the θF test is there to
    find, not to be warned about; `blur_misfit` and `blur_trend` judge this fit instead."""
    cam = base.camera.copy()
    cam.free("theta_F")
    try:
        return _fit_camera(cam, obs, replace(options, model_selection=False, progress=None), mode="joint")
    except FitError:
        return None


def _fit_blur(cam: LensCamera, obs: Observations, mode: str, init, init_sigma, options: FitOptions,
              distortion: str, geometry: FitResult | None, say=None, board=None):
    """The corner-and-blur fit from `cam` (distortion terms `distortion` free); returns (result or None,
    undetermined keys, note or None). None where the blur fit failed and there is a geometric fit to report
    instead (made here if needed); raises where the widths vary with depth and still did not fit. The result's
    per-view σ are deferred (`with_deferred_sigma`), and its undetermined keys None: `undetermined_focus_deferred`
    decides them after the blur model is judged (`blur_stage`)."""
    if geometry is not None:
        start_blur(cam, obs, mode, init)
    if say:
        s = cam.summary()
        say(f"start: w {s['w_mm']:.3f} mm, U {s['U_mm']:.1f} mm, d {s['d_mm']:.2f} mm, θF {s['theta_F_deg']:.2f}°")
    _set_free(cam, mode, bool(options.free_principal_point))
    cam.free(*distortion_parameter_names(distortion))
    start = cam.copy()
    sigma_init = init_sigma if mode == "tilt" else None
    result = held = None
    try:
        if options.blur_offset and mode != "tilt":
            # where the start is one-sided too, the fit with the offset held is likely the one kept: made first
            if _one_sided(start, obs.points_mm, obs):
                held = _held_first(start, obs, options, sigma_init, say, mode, board)
            if held is not None and _one_sided(held.camera, _points(held, obs), obs):
                if say:
                    say("blur offset held at 0 (every width's point on one side of the plane of focus)")
                return held, None, None
            cam.free("blur_offset")
            try:
                result = _fit_camera(cam, obs, options, sigma_init, say, mode=mode, board=_board_copy(board),
                                     defer_sigma=True)
                if _offset_correlation(with_deferred_sigma(result)) > MAX_OFFSET_CORRELATION:
                    raise FitError("the blur offset is not separable from U and d: the depths do not "
                                   "straddle the plane of focus")
            except FitError as e:
                if say:
                    say(f"blur offset held at 0 ({e})")
                if result is None and held is not None:  # the fit with it held from `start`: made above
                    return held, None, None
                # warm start: the fit with the offset, the offset held at 0 (the same minimum, fewer iterations)
                cam, board = (start.copy(), board) if result is None else _offset_held(result, start)
                result = None
        if result is None:
            result = _fit_camera(cam, obs, options, sigma_init, say, mode=mode, board=_board_copy(board),
                                 defer_sigma=True)
        return result, None, None
    except FitError as e:
        if geometry is None:
            # No geometric fit to fall back on: make one where the widths say nothing about focus (the same
            # blur at every depth: a soft lens, detector blur); widths that vary with depth should have
            # fitted, and the tilt stage fits the blur alone.
            if mode == "tilt" or blur_depends_on_depth(start, obs):
                raise
        return None, ["U_mm", "d_mm"], f"U and d undetermined: the blur fit failed ({e}); the calibration is geometric"


def _held_first(start: LensCamera, obs: Observations, options: FitOptions, sigma_init, say, mode: str, board):
    """The blur fit from `start` with the offset held at 0 (`_fit_blur`'s fit where the offset is refused), or
    None where it fails (the fit with the offset free is then tried as before)."""
    try:
        return _fit_camera(start.copy(), obs, options, sigma_init, say, mode=mode, board=_board_copy(board),
                           defer_sigma=True)
    except FitError:
        return None


def _points(fit: FitResult, obs: Observations) -> torch.Tensor:
    """The board points `fit` saw: its fitted board's, else `obs`'s."""
    return fit.board.points() if fit.board is not None else obs.points_mm


def _one_sided(cam: LensCamera, points: torch.Tensor, obs: Observations) -> bool:
    """Whether every blur width's point (`points`, posed by `cam`) lies on one side of `cam`'s plane of focus
    (`Lens.focus_plane`). There the thin-lens width is w d |1/z_F − 1/z| without the modulus's kink, so a constant
    offset's column is a combination of U's and d's: a fit there is also a minimum of the fit with the offset
    free, whose covariance is singular there (the offset is refused: not separable from U and d)."""
    with torch.no_grad():
        m, U = cam.lens.focus_plane()  # m · p = U on the plane (camera frame)
        p_cam = cam.to_camera(points.to(cam.rvec.dtype))[obs.blur_mask]
        side = U - p_cam @ torch.as_tensor(m, dtype=p_cam.dtype)
    return bool(side.numel() > 0 and ((side > 0).all() or (side < 0).all()))


def _offset_held(fitted: FitResult, start: LensCamera):
    """(camera, board) of a fit with the blur offset free, as the start of the same fit with it held at 0:
    `start`'s free parameters, `fitted`'s values."""
    cam = start.copy()
    with torch.no_grad():
        for name, p in fitted.camera.named_parameters():
            getattr(cam, name).copy_(p)
        cam.blur_offset_px.zero_()
    return cam, fitted.board


def _board_copy(board):
    """A fitted non-flat board to refit beside the lens (its parameters' uncertainty then stays in the lens's σ,
    not profiled out as known), or None."""
    return board.copy() if board is not None and board.model != "flat" else None
