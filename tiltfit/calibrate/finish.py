"""What the calibration adds to its fit once the models are chosen: the model choices' variance in σ, the check of
the worst view's RMS, outlier views, where each view is sharp, and CALIB.json's `model_selection` record.

    add_choice_variance(result, choice, free_pp)    (σ of w and the principal point widened in place)
    check_rms(result, options, distortion)          (FitError: mismatched data)
    flag_outliers(result, factor)                   -> names of the outlier views (each view's `outlier` set)
    sharp_line(lens, R, T, extent_mm)               -> where a view is sharp on the board, or None
    add_sharp_lines(result, obs)                    (each view's `sharp_line_board_mm`)
    model_selection_record(...)                     -> CALIB.json's `model_selection`
"""
from __future__ import annotations

import math

import numpy as np
import torch

from tiltfit.calibrate.fit import FitError, FitOptions, FitResult
from tiltfit.calibrate.model import Observations


def model_selection_record(tests: dict, choices, options: FitOptions, result: FitResult, blur: dict | None) -> dict:
    """CALIB.json's `model_selection`: the nested-model tests (`tests`), the principal point's, tilt axis's and
    distortion centre's tests from `choices` (a `ModelChoices`), the blur model's record (`blur`, or None) and, under
    distortion "auto", what chose the terms."""
    from tiltfit.select.held_out import (HELD_OUT_TOLERANCE, MAX_PROJECTION_SIGMA_PX, PROJECTION_SIGMA_FACTOR,
                                         describe_choice)

    out = dict(tests)
    for key, entry in (("principal_point", choices.principal_point_test), ("tilt_axis", choices.tilt_axis_test),
                       ("distortion_centre", choices.distortion_centre_test)):
        if entry is not None:
            out[key] = entry
    if blur is not None:
        out["blur"] = blur
    selection = result.distortion_selection
    if options.distortion == "auto" and selection:
        scored = "held_out_rms_px" in next(e for e in selection if e.get("chosen"))
        shaped = result.board is not None and result.board.model != "flat"
        out["distortion"] = {
            "chosen": choices.distortion, "why": describe_choice(selection),
            "criterion": (f"smallest {options.held_out_folds}-fold held-out error (fewest terms within "
                          f"{100 * HELD_OUT_TOLERANCE:g} % or one standard error over the views)" if scored
                          else "smallest BIC (fewer than 3 views)")
            + ", radial mapping one-to-one over the image, a rational model's projection uncertain by at most "
            f"{MAX_PROJECTION_SIGMA_PX:g} px or {PROJECTION_SIGMA_FACTOR:g}× opencv5's"
            + (", the board refitted in each fold" if shaped else "")}
    return out


def add_sharp_lines(result: FitResult, obs: Observations) -> None:
    """Each view's `sharp_line_board_mm`: where its plane of focus meets the board (`sharp_line`)."""
    pts = obs.points_mm.numpy()
    extent = (pts[:, 0].min(), pts[:, 1].min(), pts[:, 0].max(), pts[:, 1].max())
    with torch.no_grad():
        lens = result.camera.lens
        R, T = result.camera.R.numpy(), result.camera.T_mm.numpy()
    for v, view in enumerate(result.views):
        view["sharp_line_board_mm"] = sharp_line(lens, R[v], T[v], extent)


def add_choice_variance(result: FitResult, choice: dict, free_pp: bool) -> None:
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


def check_rms(result: FitResult, options: FitOptions, distortion: str):
    """A view reprojecting worse than `options.max_rms_px` means mismatched data: FitError."""
    worst = max((v["rms_reprojection_px"] for v in result.views if math.isfinite(v["rms_reprojection_px"])),
                default=0.0)
    if options.max_rms_px is not None and worst > options.max_rms_px:
        bad = max(result.views, key=lambda v: v["rms_reprojection_px"] if math.isfinite(v["rms_reprojection_px"])
                  else 0.0)
        hint = "" if distortion != "none" else "; a lens with distortion needs the distortion model auto"
        raise FitError(f"the fit found no consistent solution: {bad['image']} reprojects with an RMS of "
                       f"{worst:.3g} px (the target file or the detections do not match{hint})")


def flag_outliers(result: FitResult, factor: float) -> list:
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
