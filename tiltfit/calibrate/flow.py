"""The calibration flow: the geometric fit with the principal point and distortion chosen on the data, then the
blur fit and its checks (focus undetermined, physical ranges, a blur model that does not describe the lens).

Built on the fit of `tiltfit.calibrate.fit`, its start (`tiltfit.calibrate.start`), the nested-model tests of `tiltfit.select.nested` and
the held-out validation of `tiltfit.select.held_out`:

    calibrate(obs, mode, init, options, init_sigma) -> FitResult
    fit_geometry(camera, obs, options, mode)         -> FitResult   (corners only; distortion "auto" chosen by
                                                                     its held-out error)
"""
from __future__ import annotations

import math
import time
from dataclasses import replace

import numpy as np
import torch

from tiltfit.calibrate import fit as _core
from tiltfit.calibrate.fit import MODES, FitError, FitOptions, FitResult, _fit_camera, _set_free
from tiltfit.detect.imaging import torch_threads
from tiltfit.calibrate.model import (Observations, LensCamera, distortion_parameter_names, residuals, robust_rho,
                    robust_weight)
from tiltfit.target.shape import describe_board, with_points
from tiltfit.calibrate.blur_views import screen_blur_views
from tiltfit.select.board import select_board
from tiltfit.calibrate.distortion_centre import with_distortion_centre
from tiltfit.select.nested import blur_depends_on_depth, blur_is_informative, likelihood_ratio, nested_model_tests, usable_views
from tiltfit.calibrate.start import initialize, start_blur
from tiltfit.solve import LMOptions, SolverError, least_squares
from tiltfit.select.held_out import DISTORTION_MODELS, select_distortion


def fit_geometry(camera: LensCamera, obs: Observations, options: FitOptions, mode: str = "unified",
                 say=None, hold_distortion: bool = False) -> FitResult:
    """`tiltfit.calibrate.fit.fit_geometry`, with `options.distortion` "auto" choosing the terms by their held-out error
    (`tiltfit.select.held_out.select_distortion`; the choice is in `FitResult.distortion_selection`)."""
    if options.distortion == "auto" and not hold_distortion:
        return select_distortion(camera, obs, options, mode, say, folds=options.held_out_folds)
    return _core.fit_geometry(camera, obs, options, mode, say, hold_distortion)


def _geometry_with_principal_point(camera: LensCamera, obs: Observations, options: FitOptions, mode: str,
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
    _say_test(say, "principal_point", entry, "fitted" if entry["justified"] else "held at the image centre")
    if entry["justified"]:
        return free, entry
    held.distortion_selection = free.distortion_selection
    held.choice_variance = {k: dict(v, principal_point_px=[0.0, 0.0]) for k, v in free.choice_variance.items()}
    return held, entry


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


def _flag_outliers(result: FitResult, factor: float) -> list:
    rms = [v["rms_reprojection_px"] for v in result.views if math.isfinite(v["rms_reprojection_px"])]
    if len(rms) < 3:
        return []
    med = float(np.median(rms))
    out = []
    for v in result.views:
        v["outlier"] = bool(math.isfinite(v["rms_reprojection_px"]) and v["rms_reprojection_px"] > factor * med
                            and v["rms_reprojection_px"] > 0.7)
        if v["outlier"]:
            out.append(v["image"])
    return out


def _undetermined_focus(result: FitResult) -> list:
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


def _focus_beyond_infinity(result: FitResult) -> str | None:
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
    if mode not in MODES:
        raise ValueError(f"mode: expected one of {MODES}, got {mode!r}")
    if mode == "tilt" and init is None:
        raise FitError("the tilt fit (stage 2) needs the stage-1 calibration as init")
    if options.free_principal_point is None and not options.model_selection:
        options = replace(options, free_principal_point=False)  # no test, no reason to free it
    t0 = time.perf_counter()
    say = options.progress
    n_all = obs.n_views
    obs, skipped = usable_views(obs, options.min_corners, say)
    if obs.n_views == 0:
        raise FitError(f"none of the {n_all} views has a board with at least {options.min_corners} corners")
    if say:
        say(f"{mode} fit of {obs.n_views} views, {int(obs.corner_mask.sum())} corners, "
            f"{int(obs.blur_mask.sum())} blur widths")
    blur_ok = blur_is_informative(obs, options.blur_floor_px)
    # The geometric fit (distortion, principal point) comes first where there is anything to choose; the blur
    # start is made after it (below).
    needs_geometry = not blur_ok or options.distortion != "none" or options.free_principal_point is None
    cam = initialize(obs, mode, init, options, blur=blur_ok and not needs_geometry)
    notes, warnings, undetermined = [], [], []
    geometry = pp_test = None
    distortion = options.distortion
    free_pp = bool(options.free_principal_point)
    if needs_geometry:
        geometry, pp_test = _geometry_with_principal_point(cam, obs, options, mode, say)
        distortion = geometry.distortion_model
        free_pp = pp_test["fitted"] if pp_test is not None else free_pp
        cam = geometry.camera.copy()
    options = replace(options, free_principal_point=free_pp)
    board, board_selection, board_held_out = None, [], None
    choice = geometry.choice_variance if geometry is not None else {}
    # The widths' noise is found along the target's rows and columns: on the target file's points (a fitted
    # board's points no longer lie on exact lines, and the noise would not be found at all).
    blur_noise = blur_noise_px(obs) if blur_ok else math.nan
    file_points = obs.points_mm
    if options.board != "flat":
        base = geometry if geometry is not None else fit_geometry(cam, obs, replace(options, distortion=distortion),
                                                                    mode, say)
        fitted, board_selection, board_held_out = _fit_board(base, obs, mode, options, distortion, say)
        board = fitted.board
        choice = fitted.choice_variance
        if board.model != "flat":  # the rest of the fit sees the target as fitted; a flat board changes nothing
            geometry, distortion = fitted, fitted.distortion_model
            obs = with_points(obs, board.points())
            cam = geometry.camera.copy()
    result = None
    misfit = axis_test = centre_test = trend = None
    axis_entries = []  # the distortion models scored about the lens axis (`tiltfit.calibrate.distortion_centre`)
    if blur_ok:
        # One view's widths may disagree with the others' (a sharp photo of very low contrast): left out, named.
        noise_of = (lambda o: blur_noise if o is obs else blur_noise_px(with_points(o, file_points)))
        result, undetermined, note, obs, outlier = screen_blur_views(
            lambda o: _fit_blur(cam.copy(), o, mode, init, init_sigma, options, distortion, geometry, say, board=board),
            obs, noise_of, accept=lambda r, o: blur_misfit(r, o, noise_of(o)) is None)
        if outlier:
            notes.append(outlier)
            blur_noise = blur_noise_px(with_points(obs, file_points))  # the outlier's widths inflated it
        if result is not None and result.board is not None:  # refitted beside the lens: its σ is in the lens's
            board = result.board
            obs = with_points(obs, board.points())
        if note:
            notes.append(note)
        if result is not None and mode == "joint" and options.model_selection:
            # A lens tilted about a turned axis misfits the tilt about x: test the axis before judging the model.
            # (Not in the tilt stage: its held stage-1 U and d misfit a tilted lens, which a free axis would
            # absorb.)
            result, axis_test = _with_tilt_axis(result, obs, mode, options, init_sigma, say)
            # A tilted lens's distortion may be about its own axis: test that centre (and, where it is chosen, the
            # tilt axis again: the distortion's centre then says where the lens tilts).
            if options.distortion_centre == "auto":
                shaped = board if board is not None and board.model != "flat" else None
                result, centre_test, distortion, axis_entries = with_distortion_centre(
                    result, obs, mode, options, init_sigma, distortion, options.distortion == "auto", shaped, say)
                if shaped is not None and getattr(result, "board", None) is not None:  # refitted about the axis
                    board = result.board
                    obs = with_points(obs, board.points())
            if centre_test is not None and centre_test["fitted"] and not axis_test.get("fitted"):
                result, axis_test = _with_tilt_axis(result, obs, mode, options, init_sigma, say)        # The tilt stage holds stage 1's U and d, which the lens's tilt moves (hinge rule): its residuals judge
        # that approximation, not the thin-lens model.
        if result is not None and mode != "tilt":
            misfit = blur_misfit(result, obs, blur_noise)
            trend = None if misfit else blur_trend(result, obs, blur_noise)
            if (misfit or (trend and trend["significant"])) and mode == "unified" and options.model_selection:
                tilted = _with_theta_F(result, obs, options)  # a tilted lens is a thin lens too
                if tilted is not None:
                    misfit = blur_misfit(tilted, obs, blur_noise)
                    trend = None if misfit else blur_trend(tilted, obs, blur_noise)
            head = "the thin-lens blur model does not describe this lens"
            if not misfit:
                floor = focus_below_floor(result, obs, options, mode)
                if floor:
                    head, misfit, trend = "the blur widths do not determine the focus", floor, None
            if trend and trend["significant"]:
                warnings.append(trend["why"] + "; U and d may be biased by it")
            if misfit:
                warnings.append(f"{head}: {misfit}; U and d are not reported and the tilt is not tested (calibration "
                                f"from the corners only)")
                undetermined = ["U_mm", "d_mm"] + (["theta_F_deg"] if mode != "unified" else [])
                if geometry is None:
                    geometry = fit_geometry(cam, obs, replace(options, distortion=distortion), mode, say)
                result = None
        if undetermined and geometry is not None and result is not None and len(undetermined) == 2:
            result = None  # neither focus parameter determined: report the geometric fit
    else:
        undetermined = ["U_mm", "d_mm"] if mode != "tilt" else []
        if mode != "unified":
            undetermined.append("theta_F_deg")
        why = "no blur widths" if int(obs.blur_mask.sum()) == 0 else \
            f"all blur widths below {options.blur_floor_px:g} px (sharp images)"
        notes.append(f"{' and '.join(k.split('_')[0] for k in undetermined)} undetermined: {why}; "
                     f"the calibration is geometric (focal length, principal point, distortion, poses)")
    if result is None:
        if geometry is None:
            geometry = fit_geometry(cam, obs, replace(options, distortion=distortion), mode, say)
        result = geometry
    result.mode = mode
    result.distortion_model = distortion
    if geometry is not None:
        result.distortion_selection = geometry.distortion_selection
        result.held_out = geometry.held_out  # computed with the principal point as decided (geometry only)
        if axis_entries and result.distortion_selection:
            about_axis = result.camera.distortion_centre == "lens_axis"
            result.distortion_selection = [dict(e, chosen=bool(e.get("chosen")) and not about_axis)
                                           for e in result.distortion_selection] + axis_entries
            if about_axis:
                result.held_out = next(e["held_out"] for e in axis_entries if e["chosen"])
    if board is not None:
        # the fit's own board (refitted with the lens in the blur fit); a test's refit held it as it was
        result.board = result.board if result.board is not None else board
        result.board_selection = board_selection
        board = result.board
        if board.model != "flat":
            result.held_out = board_held_out  # the distortion test's held-out error had the flat board
            head = f"board auto: {describe_board(board_selection)}" if options.board == "auto" else f"board {board.model}"
            notes.append(head + _board_line(board))
    result.free_principal_point = free_pp
    _add_choice_variance(result, choice, free_pp)
    undetermined += [k for k in _out_of_range(result) if k not in undetermined]
    beyond = _focus_beyond_infinity(result)
    if beyond:
        undetermined += [k for k in ("U_mm",) if k not in undetermined]
        notes.append(beyond)
    result.undetermined = undetermined
    if options.distortion == "auto" and result.distortion_selection:
        from tiltfit.select.held_out import describe_choice

        notes.append(f"distortion auto: {describe_choice(result.distortion_selection)}")
    elif distortion != "none":
        from tiltfit.select.held_out import radial_fold

        if options.uncertainties:
            from tiltfit.select.held_out import undetermined_distortion

            undetermined_why = undetermined_distortion(result, distortion, obs.n_views)
            if undetermined_why:
                raise FitError(undetermined_why)
        fold = radial_fold(result.camera, obs)
        if fold:
            warnings.append(f"distortion {distortion}: {fold}; undistorting the photos folds over near their border "
                            f"(the automatic choice refuses such a model)")
    if undetermined and blur_ok and not misfit and not any("undetermined" in n for n in notes):
        notes.append(f"{' and '.join(k.split('_')[0] for k in undetermined)} undetermined: the blur widths "
                     f"do not constrain them (1/U or d within 2σ of 0, or outside their physical range)")
    _check_rms(result, options, distortion)
    outliers = _flag_outliers(result, options.outlier_factor)
    if outliers:
        notes.append(f"outlier views (RMS above {options.outlier_factor:g}× the median): {', '.join(outliers)}")
    if options.model_selection:
        result.model_selection = nested_model_tests(
            result, obs, mode, options, say, test_theta_F="theta_F_deg" not in undetermined and blur_ok and not misfit,
            test_principal_point=pp_test is None)
        if pp_test is not None:
            result.model_selection["principal_point"] = pp_test
        if axis_test is not None:
            result.model_selection["tilt_axis"] = axis_test
        if centre_test is not None:
            result.model_selection["distortion_centre"] = centre_test
    if blur_ok and mode != "tilt":
        result.model_selection["blur"] = _blur_record("U_mm" not in undetermined, blur_noise, misfit, trend)
    if options.distortion == "auto" and result.distortion_selection:
        from tiltfit.select.held_out import HELD_OUT_TOLERANCE, MAX_PROJECTION_SIGMA_PX, PROJECTION_SIGMA_FACTOR, describe_choice

        scored = "held_out_rms_px" in next(e for e in result.distortion_selection if e.get("chosen"))
        result.model_selection["distortion"] = {
            "chosen": distortion, "why": describe_choice(result.distortion_selection),
            "criterion": (f"smallest {options.held_out_folds}-fold held-out error (fewest terms within "
                          f"{100 * HELD_OUT_TOLERANCE:g} % or one standard error over the views)" if scored else "smallest BIC (fewer than 3 views)")
            + ", radial mapping one-to-one over the image, a rational model's projection uncertain by at most "
            f"{MAX_PROJECTION_SIGMA_PX:g} px or {PROJECTION_SIGMA_FACTOR:g}× opencv5's" + (", the board refitted in each fold" if result.board is not None
                                                 and result.board.model != "flat" else "")}
    if blur_ok and "U_mm" not in undetermined and "theta_F_deg" not in undetermined:
        pts = obs.points_mm.numpy()
        extent = (pts[:, 0].min(), pts[:, 1].min(), pts[:, 0].max(), pts[:, 1].max())
        with torch.no_grad():
            lens = result.camera.lens
            R, T = result.camera.R.numpy(), result.camera.T_mm.numpy()
        for v, view in enumerate(result.views):
            view["sharp_line_board_mm"] = sharp_line(lens, R[v], T[v], extent)
    result.skipped = skipped
    result.notes = notes
    result.warnings = warnings
    result.runtime_s = time.perf_counter() - t0
    if say:
        v, s = result.values, result.sigma
        focus = ", ".join(f"{k} {v[k]:.4g} ± {s[k]:.2g} mm" for k in ("U_mm", "d_mm") if k not in undetermined)
        say(f"done in {result.runtime_s:.2f} s: w {v['w_mm']:.4f} ± {s['w_mm']:.2g} mm"
            + (f", {focus}" if focus else "")
            + (f", θF {v['theta_F_deg']:.3f} ± {s['theta_F_deg']:.2g}°, θL {v['theta_L_deg']:.3f} ± "
               f"{s['theta_L_deg']:.2g}° (paper's (1): {v['theta_L_paper_deg']:.3f}°)"
               if blur_ok and not misfit else "")
            + f", distortion {distortion}")
    return result


def _add_choice_variance(result: FitResult, choice: dict, free_pp: bool) -> None:
    """The automatic choices' model-selection variance (`tiltfit.select.held_out.choice_variance`, of the distortion terms
    and of the board's model) added to the reported σ of the focal length (w) and principal point, and to the
    intrinsics covariance's diagonal, so that σ holds what the choice between models the views cannot tell apart
    leaves open; recorded under `sigma_model["model_choice"]` (one-σ, px)."""
    parts = [v for v in (choice or {}).values() if v]
    if not parts or not result.sigma or not result.sigma.get("w_mm"):
        return
    pitch = float(result.camera.pixel_pitch_mm)
    var_w = sum(p["w_mm"] for p in parts)
    var_pp = [sum(p["principal_point_px"][i] for p in parts) if free_pp else 0.0 for i in (0, 1)]
    s = result.sigma
    s["w_mm"] = math.sqrt(s["w_mm"] ** 2 + var_w)
    if s.get("principal_point_px") is not None:
        s["principal_point_px"] = [math.sqrt(a ** 2 + b) for a, b in zip(s["principal_point_px"], var_pp)]
    ic = result.intrinsics_covariance
    if ic:
        names, matrix = list(ic["names"]), [list(map(float, row)) for row in ic["matrix"]]
        for name, var in (("focal_px", var_w / pitch ** 2), ("cx_px", var_pp[0]), ("cy_px", var_pp[1])):
            if name in names:
                matrix[names.index(name)][names.index(name)] += var
        result.intrinsics_covariance = dict(ic, matrix=matrix)
    result.sigma_model = dict(result.sigma_model or {}, model_choice={
        "focal_px": math.sqrt(var_w) / pitch, "principal_point_px": [math.sqrt(v) for v in var_pp],
        "weights": {k: p["weights"] for k, p in choice.items() if p},
        "description": "spread of the estimates over the models the held-out views cannot tell apart, added to "
                       "sigma: weights exp((z|z| - z_rule^2)/2) against the chosen model, z a richer model's held-out "
                       "gain in standard errors over the views, z_rule what the choice asks of it (1 for the "
                       "distortion terms, 2 for the board's shape)"})


def _blur_record(used: bool, noise_px: float, misfit: str | None, trend: dict | None) -> dict:
    """CALIB.json's `model_selection.blur`: whether the thin-lens blur model gave U (`used`), why it was refused
    (`blur_misfit`; null where it was not, or where the notes say why U is undetermined), the widths' noise and
    the residuals' trend with depth (`blur_trend`)."""
    finite = lambda v: v if v is not None and math.isfinite(v) else None  # noqa: E731
    out = {"used": bool(used), "why_not": misfit, "noise_px": finite(noise_px)}
    if trend is not None:
        out["trend_with_depth"] = {k: trend[k] for k in ("significant", "p_value", "amplitude_px", "depth_mm")}
    return out


def _fit_board(geometry: FitResult, obs: Observations, mode: str, options: FitOptions, distortion: str, say=None):
    """The target's shape as `options.board` says (`tiltfit.target.shape`): a named model fitted, or "auto" chosen by
    the held-out error against the flat board's fit `geometry`. Returns (geometric fit with `board` set, the
    selection's entries, the chosen model's held-out error or None)."""
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
        fit, held = _redistort(fit, obs, mode, opts, held, say)
        fit.held_out = held
    if board_var:
        fit.choice_variance = dict(fit.choice_variance, board=board_var)
    return fit, entries, held


def _redistort(fit: FitResult, obs: Observations, mode: str, options: FitOptions, held, say=None):
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
                                known=known, models=models)
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


def _board_line(board) -> str:
    """', sag ... ± ...' of a fitted board for the notes (values rounded to their σ)."""
    from tiltfit.report.plots import with_sigma

    s = board.summary()
    if board.model == "warp" and "sigma" in s:
        return ": " + ", ".join(f"{k} {with_sigma(s['parameters'][k], s['sigma'][k])}" for k in s["parameters"])
    spread = (f" (median σ of a point's coordinates {float(board.sigma.median()):.2g} mm)"
              if board.sigma is not None and len(board.sigma) else "")
    return (f": points moved up to {s['max_offset_in_plane_mm']:.2g} mm in the board's plane and "
            f"{s['max_offset_out_of_plane_mm']:.2g} mm out of it{spread}")


def sharp_line(lens, R, T, extent_mm) -> list | None:
    """Where a view is sharp: the plane of focus met with the board (z = 0 in board coordinates), as the two
    end points [[X, Y], [X, Y]] (mm) of that line within the board's extent (x0, y0, x1, y1); None when the
    plane of focus misses the board there (or holds it whole: the board parallel to it)."""
    m, U = lens.focus_plane()
    R, T = np.asarray(R, dtype=np.float64), np.asarray(T, dtype=np.float64)
    a, b = R.T @ m, U - m @ T  # m · (R X + T) = U on the board: a_x X + a_y Y = b
    x0, y0, x1, y1 = extent_mm
    ends = []
    if abs(a[1]) > 1e-12:
        ends += [(x, (b - a[0] * x) / a[1]) for x in (x0, x1)]
    if abs(a[0]) > 1e-12:
        ends += [((b - a[1] * y) / a[0], y) for y in (y0, y1)]
    inside = sorted({(round(x, 9), round(y, 9)) for x, y in ends
                     if x0 - 1e-9 <= x <= x1 + 1e-9 and y0 - 1e-9 <= y <= y1 + 1e-9})
    if len(inside) < 2:
        return None
    return [list(inside[0]), list(inside[-1])]


def _say_test(say, label: str, entry: dict, outcome: str) -> None:
    """The progress line of a likelihood-ratio test (`likelihood_ratio`'s entry) and what it decided."""
    if say:
        say(f"model selection: freeing {label} is {'justified' if entry['justified'] else 'not justified'} "
            f"(Λ = {entry['lr_statistic']:.3g}, p = {entry['p_value']:.3g}, ΔBIC = {entry['delta_bic']:.3g}): "
            + outcome)


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
    _say_test(say, "the tilt axis's direction", entry,
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
    instead (made here if needed); raises where the widths vary with depth and still did not fit."""
    if geometry is not None:
        start_blur(cam, obs, mode, init)
    if say:
        s = cam.summary()
        say(f"start: w {s['w_mm']:.3f} mm, U {s['U_mm']:.1f} mm, d {s['d_mm']:.2f} mm, θF {s['theta_F_deg']:.2f}°")
    _set_free(cam, mode, bool(options.free_principal_point))
    cam.free(*distortion_parameter_names(distortion))
    start = cam.copy()
    sigma_init = init_sigma if mode == "tilt" else None
    result = None
    try:
        if options.blur_offset and mode != "tilt":
            cam.free("blur_offset")
            try:
                result = _fit_camera(cam, obs, options, sigma_init, say, mode=mode, board=_board_copy(board))
                if _offset_correlation(result) > MAX_OFFSET_CORRELATION:
                    raise FitError("the blur offset is not separable from U and d: the depths do not "
                                   "straddle the plane of focus")
            except FitError as e:
                if say:
                    say(f"blur offset held at 0 ({e})")
                # warm start: the fit with the offset, the offset held at 0 (the same minimum, fewer iterations)
                cam, board = (start.copy(), board) if result is None else _offset_held(result, start)
                result = None
        if result is None:
            result = _fit_camera(cam, obs, options, sigma_init, say, mode=mode, board=_board_copy(board))
        return result, _undetermined_focus(result), None
    except FitError as e:
        if geometry is None:
            # No geometric fit to fall back on: make one where the widths say nothing about focus (the same
            # blur at every depth: a soft lens, detector blur); widths that vary with depth should have
            # fitted, and the tilt stage fits the blur alone.
            if mode == "tilt" or blur_depends_on_depth(start, obs):
                raise
        return None, ["U_mm", "d_mm"], f"U and d undetermined: the blur fit failed ({e}); the calibration is geometric"


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


def _check_rms(result: FitResult, options: FitOptions, distortion: str):
    """A view reprojecting worse than `options.max_rms_px` means mismatched data: FitError."""
    worst = max((v["rms_reprojection_px"] for v in result.views if math.isfinite(v["rms_reprojection_px"])),
                default=0.0)
    if options.max_rms_px is not None and worst > options.max_rms_px:
        bad = max(result.views, key=lambda v: v["rms_reprojection_px"] if math.isfinite(v["rms_reprojection_px"])
                  else 0.0)
        hint = "" if distortion != "none" else "; a lens with distortion needs the distortion model auto"
        raise FitError(f"the fit found no consistent solution: {bad['image']} reprojects with an RMS of "
                       f"{worst:.3g} px (the target file or the detections do not match{hint})")


# Physical ranges of the lens values (`_out_of_range`): a value outside is not a measurement of this lens.
PHYSICAL_RANGES = {"w_mm": (0.0, math.inf), "U_mm": (0.0, math.inf), "d_mm": (0.0, math.inf),
                   "f_mm": (0.0, math.inf)}


def _out_of_range(result: FitResult) -> list:
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
    (`_undetermined_focus`: 1/U within 2σ of 0) or fails, U came from the sub-floor widths alone. On the
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
    if "U_mm" not in _undetermined_focus(alt):
        return None
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
