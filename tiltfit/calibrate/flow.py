"""The calibration flow: named stages, each returning what it decided, the model choices gathered in one record.

    calibrate(obs, mode, init, options, init_sigma) -> FitResult

The stages, in order (`_calibrate`):
    views        the views with enough corners; whether the blur widths carry information
    geometry     the corners alone: distortion terms and principal point chosen on the data
                 (`tiltfit.calibrate.geometry_stage`)
    board        the target's shape, and the distortion chosen again beside it (`geometry_stage.fit_board_stage`)
    blur         the corner-and-blur fit, the joint fit's tilt tests, the blur model judged on the widths
                 (`tiltfit.calibrate.blur_stage`); a geometric calibration where the widths say nothing
    result       the fit to report with the choices' record, σ widened by what the choices leave open, the checks
    model tests  the nested-model tests and CALIB.json's `model_selection` (`tiltfit.calibrate.finish`)
    views' notes outliers and where each view is sharp
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

from tiltfit.calibrate.blur_checks import (BLUR_TREND_ALPHA, blur_misfit, blur_noise_px, blur_record,  # noqa: F401
                                           blur_trend, focus_beyond_infinity, out_of_range)  # (public here too)
from tiltfit.calibrate.blur_stage import BlurOutcome, blur_stage
from tiltfit.calibrate.finish import (add_choice_variance, add_sharp_lines, check_rms, flag_outliers,  # noqa: F401
                                      model_selection_record, sharp_line)  # (sharp_line: public here too)
from tiltfit.calibrate.fit import MODES, FitError, FitOptions, FitResult, with_deferred_sigma
from tiltfit.calibrate.geometry_stage import board_line, fit_board_stage, fit_geometry, geometry_with_principal_point
from tiltfit.calibrate.model import Observations, LensCamera
from tiltfit.calibrate.start import initialize
from tiltfit.detect.imaging import torch_threads
from tiltfit.select.nested import blur_is_informative, nested_model_tests, usable_views
from tiltfit.target.shape import describe_board, with_points


@dataclass(frozen=True)
class ModelChoices:
    """The model choices of one calibration, each made by one stage and recorded in its result.

    Attributes:
        distortion: the distortion terms fitted ("none", "k1", …).
        free_principal_point: whether the principal point is fitted; principal_point_test: its likelihood-ratio
            test (`geometry_with_principal_point`), or None where it was not tested.
        board: the target's fitted shape (`tiltfit.target.shape.Board`), or None (the target file's points);
            board_selection: the held-out test that chose its model; board_held_out: that model's held-out error.
        choice_variance: {"distortion" | "board": the spread of w and the principal point over the models an
            automatic choice could not tell apart}.
        tilt_axis_test, distortion_centre_test: the joint fit's tests (None where not made); axis_entries: the
            distortion models scored about the lens axis (`tiltfit.calibrate.distortion_centre`).
    """

    distortion: str
    free_principal_point: bool
    principal_point_test: dict | None = None
    board: object = None
    board_selection: list = field(default_factory=list)
    board_held_out: dict | None = None
    choice_variance: dict = field(default_factory=dict)
    tilt_axis_test: dict | None = None
    distortion_centre_test: dict | None = None
    axis_entries: list = field(default_factory=list)


def calibrate(obs: Observations, mode: str = "unified", init: LensCamera | None = None,
              options: FitOptions = FitOptions(), init_sigma: dict | None = None) -> FitResult:
    """Calibrate a tilt-lens camera from detected corners and blur widths of several views.

    Views with fewer than `options.min_corners` corners are skipped (`FitResult.skipped`). When the blur
    widths carry no information (none, or all below `options.blur_floor_px`) or the blur fit cannot determine
    U and d, the fit is geometric and those parameters are listed in `FitResult.undetermined`. Distortion
    terms (`options.distortion`) are fitted on the corners first; "auto" chooses them (`fit_geometry`).

    Args:
        obs: the observations (target points, corners, blur widths) of V views.
        mode: "unified", "tilt" or "joint" (module docstring).
        init: a camera whose lens state (w, U, d, θF, principal point, distortion) starts the fit; required for
            "tilt", where w, U, d are held at its values. Its poses are not used (they come from PnP).
        options: `FitOptions`.
        init_sigma: one-σ of `init`'s w_mm, U_mm, d_mm (e.g. the `sigma` of a stage-1 CALIB.json); in
            "tilt" mode they are propagated into θF and θL.
    Returns:
        FitResult.
    Raises:
        FitError: too few observations, no convergence, or a degenerate problem (one-line message).
    """
    # One torch thread: the fit's tensors are small (tens of thousands of rows, a few columns), and on a busy
    # machine OpenMP's spinning threads cost more than they give (`tiltfit.detect.imaging.torch_threads`): 14.6 s of
    # CPU instead of 1.3 s for 50 views with two threads under load (benchmarks/results/calib_scale.md).
    with torch_threads(1):
        return _calibrate(obs, mode, init, options, init_sigma)


def _calibrate(obs: Observations, mode: str, init: LensCamera | None, options: FitOptions,
               init_sigma: dict | None) -> FitResult:
    t0 = time.perf_counter()
    say = options.progress
    obs, skipped, options, blur_ok = _views(obs, mode, init, options)
    cam, geometry, choices = _geometry(obs, mode, init, options, blur_ok, say)
    options = replace(options, free_principal_point=choices.free_principal_point)
    noise_px = blur_noise_px(obs) if blur_ok else math.nan  # on the target file's points (`blur_noise_px`)
    cam, geometry, obs, choices = _board(cam, geometry, obs, mode, options, choices, say, defer_sigma=blur_ok)
    if blur_ok:
        blur = blur_stage(cam, obs, mode, init, init_sigma, options, choices, geometry, noise_px, say)
    else:
        blur = _geometric(obs, mode, options, cam, geometry, choices)
    result, choices = _result(blur, cam, mode, options, blur_ok, say)
    tests = nested_model_tests(
        result, blur.obs, mode, options, say, test_principal_point=choices.principal_point_test is None,
        test_theta_F="theta_F_deg" not in result.undetermined and blur_ok and not blur.misfit) \
        if options.model_selection else result.model_selection
    record = blur_record("U_mm" not in result.undetermined, blur.noise_px, blur.misfit, blur.trend) \
        if blur_ok and mode != "tilt" else None
    result.model_selection = model_selection_record(tests, choices, options, result, record)
    if blur_ok and "U_mm" not in result.undetermined and "theta_F_deg" not in result.undetermined:
        add_sharp_lines(result, blur.obs)
    result.skipped = skipped
    result.runtime_s = time.perf_counter() - t0
    _say_done(say, result, choices.distortion, blur_ok and not blur.misfit)
    return result


def _views(obs: Observations, mode: str, init, options: FitOptions):
    """The views with at least `options.min_corners` corners; returns (obs, skipped, options, whether the blur
    widths carry information)."""
    if mode not in MODES:
        raise ValueError(f"mode: expected one of {MODES}, got {mode!r}")
    if mode == "tilt" and init is None:
        raise FitError("the tilt fit (stage 2) needs the stage-1 calibration as init")
    if options.free_principal_point is None and not options.model_selection:
        options = replace(options, free_principal_point=False)  # no test, no reason to free it
    n_all = obs.n_views
    obs, skipped = usable_views(obs, options.min_corners, options.progress)
    if obs.n_views == 0:
        raise FitError(f"none of the {n_all} views has a board with at least {options.min_corners} corners")
    if options.progress:
        options.progress(f"{mode} fit of {obs.n_views} views, {int(obs.corner_mask.sum())} corners, "
                         f"{int(obs.blur_mask.sum())} blur widths")
    return obs, skipped, options, blur_is_informative(obs, options.blur_floor_px)


def _geometry(obs: Observations, mode: str, init, options: FitOptions, blur_ok: bool, say=None):
    """The start, and the geometric fit where there is anything to choose (distortion, principal point) or no
    blur to fit; the blur start is made after it (`tiltfit.calibrate.blur_stage`). Returns (camera to start the
    next stage from, geometric fit or None, choices)."""
    needs_geometry = not blur_ok or options.distortion != "none" or options.free_principal_point is None
    cam = initialize(obs, mode, init, options, blur=blur_ok and not needs_geometry)
    choices = ModelChoices(options.distortion, bool(options.free_principal_point))
    if not needs_geometry:
        return cam, None, choices
    geometry, pp_test = geometry_with_principal_point(cam, obs, options, mode, say)
    choices = replace(choices, distortion=geometry.distortion_model, principal_point_test=pp_test,
                      free_principal_point=pp_test["fitted"] if pp_test is not None else choices.free_principal_point,
                      choice_variance=geometry.choice_variance)
    return geometry.camera.copy(), geometry, choices


def _board(cam, geometry, obs: Observations, mode: str, options: FitOptions, choices: ModelChoices, say=None,
           defer_sigma: bool = False):
    """The target's shape (`options.board`; nothing to do for "flat"): a non-flat board replaces the geometric fit
    and the target points for the stages after it. Returns (camera, geometric fit, obs, choices). `defer_sigma`
    (a blur fit follows, which is reported unless it fails or is refused): the refitted geometric fit's per-view
    σ are made only where it is reported (`_result`)."""
    if options.board == "flat":
        return cam, geometry, obs, choices
    base = geometry if geometry is not None else fit_geometry(cam, obs, replace(options, distortion=choices.distortion),
                                                              mode, say)
    fitted, selection, held = fit_board_stage(base, obs, mode, options, choices.distortion, say, defer_sigma)
    choices = replace(choices, board=fitted.board, board_selection=selection, board_held_out=held,
                      choice_variance=fitted.choice_variance)
    if fitted.board.model == "flat":  # a flat board changes nothing
        return cam, geometry, obs, choices
    choices = replace(choices, distortion=fitted.distortion_model)
    return fitted.camera.copy(), fitted, with_points(obs, fitted.board.points()), choices


def _geometric(obs: Observations, mode: str, options: FitOptions, cam, geometry, choices) -> BlurOutcome:
    """The blur stage's outcome where the widths carry no information: U and d (θF) undetermined, said why."""
    undetermined = ["U_mm", "d_mm"] if mode != "tilt" else []
    if mode != "unified":
        undetermined.append("theta_F_deg")
    why = "no blur widths" if int(obs.blur_mask.sum()) == 0 else \
        f"all blur widths below {options.blur_floor_px:g} px (sharp images)"
    note = (f"{' and '.join(k.split('_')[0] for k in undetermined)} undetermined: {why}; "
            f"the calibration is geometric (focal length, principal point, distortion, poses)")
    return BlurOutcome(None, geometry, obs, choices, undetermined, [note], [])


def _result(blur: BlurOutcome, cam, mode: str, options: FitOptions, blur_ok: bool, say=None):
    """The fit to report (the blur fit, or the geometric one) with the choices recorded in it, σ widened by what
    the automatic choices leave open, what it cannot determine and the notes and warnings of every stage; raises
    FitError where a view reprojects too badly. Returns (result, choices)."""
    choices, obs = blur.choices, blur.obs
    geometry = blur.geometry
    if blur.result is None and geometry is None:
        geometry = fit_geometry(cam, obs, replace(options, distortion=choices.distortion), mode, say)
    result = blur.result if blur.result is not None else with_deferred_sigma(geometry)
    result.mode, result.distortion_model = mode, choices.distortion
    result.free_principal_point = choices.free_principal_point
    notes, warnings = list(blur.notes), list(blur.warnings)
    if geometry is not None:
        result.distortion_selection, result.held_out = _distortion_record(result, geometry, choices)
    if choices.board is not None:
        notes += _record_board(result, choices, options)
        choices = replace(choices, board=result.board)
    add_choice_variance(result, choices.choice_variance, choices.free_principal_point)
    undetermined = list(blur.undetermined)
    undetermined += [k for k in out_of_range(result) if k not in undetermined]
    beyond = focus_beyond_infinity(result)
    if beyond:
        undetermined += [k for k in ("U_mm",) if k not in undetermined]
        notes.append(beyond)
    result.undetermined = undetermined
    more_notes, more_warnings = _distortion_notes(result, obs, options, choices.distortion)
    notes += more_notes
    warnings += more_warnings
    if undetermined and blur_ok and not blur.misfit and not any("undetermined" in n for n in notes):
        notes.append(f"{' and '.join(k.split('_')[0] for k in undetermined)} undetermined: the blur widths "
                     f"do not constrain them (1/U or d within 2σ of 0, or outside their physical range)")
    check_rms(result, options, choices.distortion)
    outliers = flag_outliers(result, options.outlier_factor)
    if outliers:
        notes.append(f"outlier views (RMS above {options.outlier_factor:g}× the median): {', '.join(outliers)}")
    result.notes, result.warnings = notes, warnings
    return result, choices


def _distortion_record(result: FitResult, geometry: FitResult, choices: ModelChoices):
    """(distortion_selection, held_out) of the reported fit: the geometric fit's choice (its held-out error computed
    with the principal point as decided), and the models scored about the lens axis where they were."""
    selection, held_out = geometry.distortion_selection, geometry.held_out
    if choices.axis_entries and selection:
        about_axis = result.camera.distortion_centre == "lens_axis"
        selection = [dict(e, chosen=bool(e.get("chosen")) and not about_axis) for e in selection] + \
            choices.axis_entries
        if about_axis:
            held_out = next(e["held_out"] for e in choices.axis_entries if e["chosen"])
    return selection, held_out


def _record_board(result: FitResult, choices: ModelChoices, options: FitOptions) -> list:
    """The fit's own board (refitted with the lens in the blur fit; a test's refit held it as it was) and its
    selection put in `result`; returns the note that says which board was fitted (none for a flat board)."""
    result.board = result.board if result.board is not None else choices.board
    result.board_selection = choices.board_selection
    board = result.board
    if board.model == "flat":
        return []
    result.held_out = choices.board_held_out  # the distortion test's held-out error had the flat board
    head = f"board auto: {describe_board(choices.board_selection)}" if options.board == "auto" else \
        f"board {board.model}"
    return [head + board_line(board)]


def _distortion_notes(result: FitResult, obs: Observations, options: FitOptions, distortion: str):
    """(notes, warnings) about the distortion: the automatic choice's line, or for a model asked for by name a
    radial mapping that folds inside the image; raises FitError where the views do not determine a named model's
    coefficients."""
    from tiltfit.select.held_out import describe_choice, radial_fold, undetermined_distortion

    if options.distortion == "auto" and result.distortion_selection:
        return [f"distortion auto: {describe_choice(result.distortion_selection)}"], []
    if distortion == "none":
        return [], []
    if options.uncertainties:
        why = undetermined_distortion(result, distortion, obs.n_views)
        if why:
            raise FitError(why)
    fold = radial_fold(result.camera, obs)
    return [], ([f"distortion {distortion}: {fold}; undistorting the photos folds over near their border (the "
                 f"automatic choice refuses such a model)"] if fold else [])


def _say_done(say, result: FitResult, distortion: str, blur_used: bool) -> None:
    """The calibration's last progress line: runtime, lens values with σ, distortion."""
    if not say:
        return
    v, s = result.values, result.sigma
    focus = ", ".join(f"{k} {v[k]:.4g} ± {s[k]:.2g} mm" for k in ("U_mm", "d_mm") if k not in result.undetermined)
    say(f"done in {result.runtime_s:.2f} s: w {v['w_mm']:.4f} ± {s['w_mm']:.2g} mm"
        + (f", {focus}" if focus else "")
        + (f", θF {v['theta_F_deg']:.3f} ± {s['theta_F_deg']:.2g}°, θL {v['theta_L_deg']:.3f} ± "
           f"{s['theta_L_deg']:.2g}° (paper's (1): {v['theta_L_paper_deg']:.3f}°)" if blur_used else "")
        + f", distortion {distortion}")
