"""CALIB.json, the calibration file of `tiltfit calibrate` (keys as in docs/file_formats.md, plus extras).

Contract keys: pixel_pitch_mm, image_size_px [W, H], principal_point_px [cx, cy], w_mm, U_mm, d_mm, f_mm,
theta_F_deg, theta_L_deg (exact thin-lens relation), theta_L_paper_deg (the paper's eq (1)),
views [{image, R (3×3, camera_from_target), T_mm, rms_reprojection_px, rms_blur_px, n_points}],
sigma {w_mm, U_mm, d_mm, theta_F_deg, theta_L_deg} (one standard deviation), runtime_s.

Extras (readers must ignore keys they do not know): tilt_axis_deg (φ, the tilt axis's direction from the camera x
axis, 0 unless the data justify turning it), distortion_centre ("sensor": the distortion about the principal
point; "lens_axis": about the tilted lens's own axis, in its frame, as OpenCV's tilted model; `renderer.Lens`),
fit (mode), blur_model, noise {sigma_corner_px,
sigma_blur_px, variance_factor}, sigma.{f_mm, theta_L_paper_deg, principal_point_px}, views[].{sigma_rvec_deg,
sigma_T_mm}, model_selection {theta_F: {...,justified}, principal_point: {...}}, iterations, n_residuals,
n_parameters, software.

Since the real-photos work (format_version 2): `format_version`, `created` (UTC, ISO 8601), `target` (the
target file's content), `distortion` ({model: "brown_conrady", coefficients: [k1, k2, p1, p2, k3, k4, k5,
k6]}, OpenCV's order), `distortion_model` (the terms fitted) and `distortion_selection` (the `auto` tests),
`sigma.distortion`, `undetermined` (keys the data cannot determine; their values are null), `skipped`
([{image, reason}]), `notes`, `warnings`, `principal_point_fitted`, `rms_reprojection_px` (all views, per
corner as OpenCV's calibrateCamera: sqrt(mean(dx² + dy²)), like every reprojection RMS here), `held_out` (see
`tiltfit.select.held_out`), and per view `corners_px` (detected, null where missing), `residuals_px` (model −
detected), `blur_px`, `blur_residuals_px`, `depth_mm` (camera-frame z of each feature point) and `outlier`
— what `tiltfit report` draws.

Since the board-shape work: `board` (the target as fitted, `tiltfit.target.shape.Board.summary`: `model` "flat", "warp"
or "free"; for warp `parameters` {sag_x_mm, sag_y_mm, scale_y_minus_1} and their `sigma`; for free
`points_mm` and `sigma_points_mm`; `max_offset_in_plane_mm`, `max_offset_out_of_plane_mm`), `board_selection`
(per model: fit `rms_px`, `held_out_rms_px`, `chosen`) and, with a fitted shape, per view
`residuals_flat_board_px` (the same lens with the target file's flat points, each view's pose refitted).
Honest uncertainties (`tiltfit.uncertainty.covariance`): `sigma_model` ({name: "views" | "classical", description,
design_effect, ratio_min, ratio_max, n_views, view_error_px, pose_ratio_min, pose_ratio_max}: which error model
`sigma` uses), `sigma_classical` (the same keys as `sigma` under independent noise), `intrinsics_covariance`
({names: focal_px, cx_px, cy_px, k1 … k6, matrix}), `projection_uncertainty` ({median_px, worst_px, grid_x_px,
grid_y_px, sigma_px, method}), and after cross-validation `cross_validation`
(`tiltfit.uncertainty.covariance.projection_difference` per pair of groups).

Numbers that are not finite (e.g. the blur RMS of a view without blur widths) are written as null.
The file is written atomically (temporary file in the same folder, then renamed).
"""
from __future__ import annotations

import json
import math
import os
from typing import TYPE_CHECKING

import numpy as np

from camio.files import write_text
from renderer.core.params import DISTORTION_CENTRES
from camio.checks import describe, is_finite_number, read_json

from tiltfit.files.det import MAX_IMAGE_SIDE

# torch and the camera model (`tiltfit.calibrate.model`) are imported where a camera is built, so that reading and checking
# a CALIB.json (`tiltfit export`, `compare`, `report`, the commands' file errors) does not load them.
if TYPE_CHECKING:
    from tiltfit.calibrate.model import LensCamera

FORMAT_VERSION = 2

REQUIRED_KEYS = ("pixel_pitch_mm", "image_size_px", "principal_point_px", "w_mm", "U_mm", "d_mm", "f_mm",
                 "theta_F_deg", "theta_L_deg", "theta_L_paper_deg", "views", "sigma", "runtime_s")
VIEW_KEYS = ("image", "R", "T_mm", "rms_reprojection_px", "rms_blur_px", "n_points")
SIGMA_KEYS = ("w_mm", "U_mm", "d_mm", "theta_F_deg", "theta_L_deg")


# Lengths in a calibration file beyond this (mm, a thousand kilometres) are unit mistakes, not lenses.
MAX_LENGTH_MM = 1e9


class CalibFileError(ValueError):
    """A CALIB.json that cannot be read or is malformed; the message is one line, naming file and key."""


def _clean(v):
    """JSON-safe copy: tensors and arrays to lists, non-finite floats to None."""
    if hasattr(v, "detach"):  # a torch tensor
        v = v.detach().cpu().tolist()
    if isinstance(v, np.ndarray):
        v = v.tolist()
    if isinstance(v, dict):
        return {str(k): _clean(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_clean(x) for x in v]
    if isinstance(v, (np.floating, np.integer)):
        v = v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def _per_view_data(result, obs) -> list:
    """Per-view corners, residuals, blur and depths for the report (lists aligned with the feature points);
    with a fitted board, residuals of its points and, beside them, of the target file's flat points."""
    import torch

    from tiltfit.target.shape import with_points
    from tiltfit.calibrate.model import residuals

    cam = result.camera
    board = getattr(result, "board", None)
    flat = None
    if board is not None and board.model != "flat":
        # The same lens with the target file's flat points, each view's pose refitted to them: what the fitted
        # shape explains (the points' offsets include a gauge, a similarity that the poses absorb).
        from tiltfit.calibrate.fit import FitError
        from tiltfit.select.held_out import predict_views

        try:
            nominal = with_points(obs, board.nominal_mm)
            flat_cam = predict_views(cam, nominal).camera
            with torch.no_grad():
                flat = residuals(flat_cam, nominal).corners_px
        except FitError:
            flat = None
        obs = with_points(obs, board.points())
    with torch.no_grad():
        r = residuals(cam, obs)
        depth = cam.to_camera(obs.points_mm)[..., 2]
    out = []
    for v in range(obs.n_views):
        cm, bm = obs.corner_mask[v].tolist(), obs.blur_mask[v].tolist()
        out.append({
            "corners_px": [c if ok else None for c, ok in zip(obs.corners_px[v].tolist(), cm)],
            "residuals_px": [e if ok else None for e, ok in zip(r.corners_px[v].tolist(), cm)],
            "blur_px": [b if ok else None for b, ok in zip(obs.blur_px[v].tolist(), bm)],
            "blur_residuals_px": [e if ok else None for e, ok in zip(r.blur_px[v].tolist(), bm)],
            "depth_mm": depth[v].tolist(),
        })
        if flat is not None:
            out[-1]["residuals_flat_board_px"] = [e if ok else None for e, ok in zip(flat[v].tolist(), cm)]
    return out


def calib_dict(result, runtime_s: float | None = None, obs=None, target: dict | None = None,
               held_out: dict | None = None) -> dict:
    """The CALIB.json content of a `tiltfit.calibrate.fit.FitResult`.

    Args:
        obs: the observations the fit used (its views, in order), to store per-view corners and residuals.
        target: the target file's content, stored under `target`.
        held_out: `tiltfit.select.held_out.held_out_rms`'s result, stored under `held_out`.
    """
    import datetime

    from tiltfit.calibrate.fit import per_corner_rms_px

    cam = result.camera
    v, s, undetermined = _determined_values(result)
    n_rows = result.rss.get("n_corners", 0)
    out = {
        "pixel_pitch_mm": cam.pixel_pitch_mm,
        "image_size_px": list(cam.image_size_px),
        "principal_point_px": v["principal_point_px"],
        "w_mm": v["w_mm"], "U_mm": v["U_mm"], "d_mm": v["d_mm"], "f_mm": v["f_mm"],
        "theta_F_deg": v["theta_F_deg"], "theta_L_deg": v["theta_L_deg"],
        "theta_L_paper_deg": v["theta_L_paper_deg"],
        "tilt_axis_deg": v.get("tilt_axis_deg", 0.0),
        "views": [dict(view) for view in result.views],
        "sigma": {k: s[k] for k in SIGMA_KEYS} | {"f_mm": s["f_mm"], "theta_L_paper_deg": s["theta_L_paper_deg"],
                                                   "tilt_axis_deg": s.get("tilt_axis_deg", 0.0),
                                                   "principal_point_px": s["principal_point_px"]},
        "runtime_s": result.runtime_s if runtime_s is None else runtime_s,
        "fit": result.mode,
        "blur_model": cam.blur_model,
        "noise": dict(result.noise),
        "model_selection": result.model_selection,
        "iterations": result.iterations,
        "n_residuals": result.n_residuals,
        "n_parameters": result.n_parameters,
        "software": "tiltfit",
        "format_version": FORMAT_VERSION,
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "distortion": {"model": "brown_conrady", "coefficients": [float(c) for c in cam.distortion.detach()]},
        "distortion_centre": cam.distortion_centre,
        "distortion_model": getattr(result, "distortion_model", "none"),
        "distortion_selection": getattr(result, "distortion_selection", []),
        "undetermined": undetermined,
        "skipped": list(getattr(result, "skipped", []) or []),
        "notes": list(getattr(result, "notes", []) or []),
        "rms_reprojection_px": per_corner_rms_px(result.rss) if n_rows else None,
        "warnings": list(getattr(result, "warnings", []) or []),
        "principal_point_fitted": bool(getattr(result, "free_principal_point", False)),
        "blur_offset_px": v.get("blur_offset_px"),
    }
    out["sigma"]["blur_offset_px"] = s.get("blur_offset_px")
    out["sigma"]["distortion"] = s.get("distortion")
    _add_uncertainty(out, result, undetermined)
    if target is not None:
        out["target"] = target
    if held_out is not None:
        out["held_out"] = held_out
    board = getattr(result, "board", None)
    if board is not None:
        out["board"] = board.summary()
        out["board_selection"] = [{k: e[k] for k in e if k != "held_out"}
                                  for e in getattr(result, "board_selection", []) or []]
    if obs is not None:
        for view, extra in zip(out["views"], _per_view_data(result, obs)):
            view.update(extra)
    return _clean(out)


def _determined_values(result) -> tuple[dict, dict, list]:
    """(values, σ, undetermined keys) of a fit as CALIB.json writes them: undetermined keys null, and never a number
    outside its physical range (w, U, f > 0, d ≥ 0, |θF| < 90°; such a key becomes null and undetermined); f null
    without U, the tilt angles null without θF."""
    v, s = dict(result.values), dict(result.sigma)
    undetermined = list(getattr(result, "undetermined", []) or [])
    for k in undetermined:
        v[k] = None
        s[k] = None
    for k in ("w_mm", "U_mm", "d_mm", "f_mm"):  # never a number outside its physical range (w, U, f > 0, d ≥ 0)
        x = v.get(k)
        if x is not None and not (math.isfinite(x) and (x >= 0 if k == "d_mm" else x > 0)):
            v[k] = s[k] = None
            if k != "f_mm" and k not in undetermined:
                undetermined.append(k)
    if v.get("theta_F_deg") is not None and not abs(v["theta_F_deg"]) < 90:
        v["theta_F_deg"] = s["theta_F_deg"] = None
        undetermined.append("theta_F_deg")
    if "U_mm" in undetermined:  # f = U w / (U + w) needs U
        v["f_mm"] = s["f_mm"] = None
    if "theta_F_deg" in undetermined:
        for k in ("theta_L_deg", "theta_L_paper_deg", "tilt_axis_deg"):
            v[k] = s[k] = None
    return v, s, undetermined


def _add_uncertainty(out: dict, result, undetermined: list) -> None:
    """`sigma_model`, `sigma_classical`, `intrinsics_covariance` and `projection_uncertainty` (tiltfit.uncertainty.covariance)
    where the fit computed its covariance."""
    model = getattr(result, "sigma_model", None)
    if not model:
        return
    out["sigma_model"] = dict(model) | {"description": (
        "per-view cluster-robust covariance (corner and blur errors may be correlated within a view; poses "
        "profiled out, CR2 small-sample correction), never below the classical one; each pose's own part from a "
        "random affine error per view estimated from the residuals" if model["name"] == "views"
        else "classical: independent residuals, s² (JᵀWJ)⁻¹")}
    sc = dict(result.sigma_classical)
    blank = set(undetermined) | {k for k in out["sigma"] if out["sigma"][k] is None}
    out["sigma_classical"] = {k: (None if k in blank else sc.get(k)) for k in out["sigma"]}
    ic = getattr(result, "intrinsics_covariance", None)
    if ic:
        from tiltfit.uncertainty.covariance import covariance_from_calib, projection_summary

        out["intrinsics_covariance"] = ic
        cov = covariance_from_calib(out, check=False)
        out["projection_uncertainty"] = projection_summary(result.camera.lens, cov, nx=24)


def write_calib(path: str, data) -> None:
    """Write CALIB.json atomically. `data` is a FitResult or a dict from `calib_dict`."""
    if not isinstance(data, dict):
        data = calib_dict(data)
    write_text(path, json.dumps(_clean(data), indent=1, allow_nan=False) + "\n")


def _number(path, key, value, positive=False):
    if not is_finite_number(value):
        raise CalibFileError(f"{path}: {key}: expected a finite number, got {describe(value)}")
    if positive and not value > 0:
        raise CalibFileError(f"{path}: {key}: expected a positive number, got {value!r}")
    return float(value)


def _vector(path, key, value, n):
    if not isinstance(value, list) or len(value) != n:
        raise CalibFileError(f"{path}: {key}: expected a list of {n} numbers, got {describe(value)}")
    return [_number(path, f"{key}[{i}]", x) for i, x in enumerate(value)]


def read_calib(path: str) -> dict:
    """Read and validate CALIB.json; returns the parsed dict (extras kept as they are).

    Raises:
        CalibFileError: missing file, invalid JSON, a missing key or a malformed value (one line).
    """
    if not os.path.exists(path):
        raise CalibFileError(f"{path}: no such file")
    return validate_calib(path, read_json(path, CalibFileError, "calibration file"))


def validate_calib(path: str, data) -> dict:
    """The checks of `read_calib` on an already parsed CALIB dict (also an OpenCV file's, from
    `tiltfit.files.opencv_file.read_opencv`); `path` names the file in messages."""
    if not isinstance(data, dict):
        raise CalibFileError(f"{path}: expected a JSON object")
    # Only the lens state is needed to start another fit; views and sigma may be absent in hand-made files.
    for key in ("pixel_pitch_mm", "image_size_px", "w_mm", "U_mm", "d_mm"):
        if key not in data:
            raise CalibFileError(f"{path}: {key}: missing key")
    for key in ("pixel_pitch_mm", "w_mm"):
        _number(path, key, data[key], positive=True)
    for key in ("U_mm", "d_mm"):
        if data[key] is not None:
            _number(path, key, data[key], positive=True)
    dist = data.get("distortion")
    if dist is not None:
        from renderer.cameras.distortion import distortion_from_config
        from renderer.core.params import SceneError

        try:
            distortion_from_config("distortion", dist)
        except SceneError as e:
            raise CalibFileError(f"{path}: {e}") from None
    for key in ("pixel_pitch_mm", "w_mm", "U_mm", "d_mm"):
        if data[key] is not None and is_finite_number(data[key]) and abs(data[key]) > MAX_LENGTH_MM:
            raise CalibFileError(f"{path}: {key}: expected at most {MAX_LENGTH_MM:g} mm, got {describe(data[key])}")
    size = _vector(path, "image_size_px", data["image_size_px"], 2)
    if not all(1 <= s <= MAX_IMAGE_SIDE and s == int(s) for s in size):
        raise CalibFileError(f"{path}: image_size_px: expected two positive integers, got {data['image_size_px']!r}")
    if data.get("principal_point_px") is not None:
        pp = _vector(path, "principal_point_px", data["principal_point_px"], 2)
        if not all(-s <= c <= 2 * s for c, s in zip(pp, size)):
            raise CalibFileError(f"{path}: principal_point_px: expected a point within one image size of the "
                                 f"{int(size[0])}x{int(size[1])} image, got {pp}")
    if data.get("theta_F_deg") is not None:
        if abs(_number(path, "theta_F_deg", data["theta_F_deg"])) >= 90:
            raise CalibFileError(f"{path}: theta_F_deg: expected |θF| < 90, got {data['theta_F_deg']!r}")
    if data.get("tilt_axis_deg") is not None and abs(_number(path, "tilt_axis_deg", data["tilt_axis_deg"])) > 360:
        raise CalibFileError(f"{path}: tilt_axis_deg: expected an angle within ±360°, got {data['tilt_axis_deg']!r}")
    if data.get("theta_L_deg") is not None and abs(_number(path, "theta_L_deg", data["theta_L_deg"])) >= 90:
        raise CalibFileError(f"{path}: theta_L_deg: expected |θL| < 90, got {data['theta_L_deg']!r}")
    centre = data.get("distortion_centre", "sensor")
    if centre not in DISTORTION_CENTRES:
        raise CalibFileError(f"{path}: distortion_centre: expected one of {', '.join(DISTORTION_CENTRES)}, got "
                             f"{describe(centre)}")
    views = data.get("views", [])
    if not isinstance(views, list):
        raise CalibFileError(f"{path}: views: expected a list, got {views!r}")
    for i, view in enumerate(views):
        if not isinstance(view, dict):
            raise CalibFileError(f"{path}: views[{i}]: expected an object")
        for key in ("R", "T_mm"):
            if key not in view:
                raise CalibFileError(f"{path}: views[{i}].{key}: missing key")
        R = view["R"]
        if not (isinstance(R, list) and len(R) == 3 and all(isinstance(r, list) and len(r) == 3 for r in R)):
            raise CalibFileError(f"{path}: views[{i}].R: expected a 3×3 matrix")
        for j, row in enumerate(R):
            _vector(path, f"views[{i}].R[{j}]", row, 3)
        Rm = np.array(R, dtype=np.float64)
        if not (np.abs(Rm @ Rm.T - np.eye(3)).max() < 1e-6 and np.linalg.det(Rm) > 0):
            raise CalibFileError(f"{path}: views[{i}].R: expected a rotation (orthonormal, determinant +1)")
        T = _vector(path, f"views[{i}].T_mm", view["T_mm"], 3)
        if max(abs(t) for t in T) > MAX_LENGTH_MM:
            raise CalibFileError(f"{path}: views[{i}].T_mm: expected coordinates within ±{MAX_LENGTH_MM:g} mm, got {T}")
    sigma = data.get("sigma", {})
    if not isinstance(sigma, dict):
        raise CalibFileError(f"{path}: sigma: expected an object, got {describe(sigma)}")
    _check_extras(path, data)
    return data


# A calibration with more views than this is not one `tiltfit calibrate` writes (docs/file_formats.md).
MAX_VIEWS = 100_000


def _optional_number(path, key, value, nonnegative=False):
    if value is None:
        return None
    x = _number(path, key, value)
    if nonnegative and x < 0:
        raise CalibFileError(f"{path}: {key}: expected a non-negative number or null, got {describe(value)}")
    return x


def _list_of(path, key, value, kind, what):
    if not isinstance(value, list) or not all(isinstance(x, kind) for x in value):
        raise CalibFileError(f"{path}: {key}: expected a list of {what}, got {describe(value)}")
    return value


def _point_list(path, key, value, width, first=None):
    """A per-feature-point list ([x, y] | null when width 2, number | null when width 1) as long as the
    `first` such list (its (key, length)); returns (key, length)."""
    if not isinstance(value, list):
        raise CalibFileError(f"{path}: {key}: expected a list, got {describe(value)}")
    if first is not None and len(value) != first[1]:
        raise CalibFileError(f"{path}: {key}: {len(value)} entries, but {first[0]} has {first[1]} (expected one "
                             "per feature point in every list)")
    for j, x in enumerate(value):
        if x is None:
            continue
        if width == 1:
            _number(path, f"{key}[{j}]", x)
        else:
            _vector(path, f"{key}[{j}]", x, width)
    return first or (key, len(value))


def _check_extras(path: str, data: dict) -> None:
    """The optional keys `tiltfit report` and `tiltfit export` read (each checked where present): types, the
    per-view lists' common length, and every number finite."""
    views = data.get("views", [])
    if len(views) > MAX_VIEWS:
        raise CalibFileError(f"{path}: views: expected at most {MAX_VIEWS} views, got {len(views)}")
    _optional_number(path, "rms_reprojection_px", data.get("rms_reprojection_px"), nonnegative=True)
    for key in ("undetermined", "notes", "warnings"):
        if data.get(key) is not None:
            _list_of(path, key, data[key], str, "strings")
    if data.get("skipped") is not None:
        skipped = _list_of(path, "skipped", data["skipped"], dict, "objects ({image, reason})")
        for i, s in enumerate(skipped):
            if not isinstance(s.get("image", ""), str):
                raise CalibFileError(f"{path}: skipped[{i}].image: expected a file name, got {describe(s['image'])}")
    held = data.get("held_out")
    if held is not None:
        if not isinstance(held, dict):
            raise CalibFileError(f"{path}: held_out: expected an object or null, got {describe(held)}")
        _optional_number(path, "held_out.rms_px", held.get("rms_px"), nonnegative=True)
        folds = held.get("folds")
        if folds is not None and not (is_finite_number(folds) and folds == int(folds) and folds >= 0):
            raise CalibFileError(f"{path}: held_out.folds: expected a count, got {describe(folds)}")
    ic = data.get("intrinsics_covariance")
    if ic is not None:
        from tiltfit.uncertainty.covariance import covariance_problem

        if not isinstance(ic, dict):
            raise CalibFileError(f"{path}: intrinsics_covariance: expected an object {{names, matrix}}, got "
                                 f"{describe(ic)}")
        problem = covariance_problem(ic.get("names"), ic.get("matrix"))
        if problem:
            raise CalibFileError(f"{path}: {problem}")
    pu = data.get("projection_uncertainty")
    if pu is not None:
        if not isinstance(pu, dict):
            raise CalibFileError(f"{path}: projection_uncertainty: expected an object, got {describe(pu)}")
        for key in ("median_px", "worst_px"):
            _optional_number(path, f"projection_uncertainty.{key}", pu.get(key), nonnegative=True)
    for key in ("distortion_model", "fit", "blur_model"):
        if data.get(key) is not None and not isinstance(data[key], str):
            raise CalibFileError(f"{path}: {key}: expected a name, got {describe(data[key])}")
    _check_uncertainty_extras(path, data)
    first = None
    for i, view in enumerate(views):
        if not isinstance(view.get("image", ""), str):
            raise CalibFileError(f"{path}: views[{i}].image: expected a file name, got {describe(view['image'])}")
        for key in ("rms_reprojection_px", "rms_blur_px"):
            _optional_number(path, f"views[{i}].{key}", view.get(key), nonnegative=True)
        npts = view.get("n_points")
        if npts is not None and not (is_finite_number(npts) and npts == int(npts) and npts >= 0):
            raise CalibFileError(f"{path}: views[{i}].n_points: expected a count, got {describe(npts)}")
        if not isinstance(view.get("outlier", False), bool):
            raise CalibFileError(f"{path}: views[{i}].outlier: expected true or false, got {describe(view['outlier'])}")
        for key, width in (("corners_px", 2), ("residuals_px", 2), ("blur_px", 1), ("blur_residuals_px", 1),
                           ("depth_mm", 1), ("residuals_flat_board_px", 2)):
            if view.get(key) is not None:
                first = _point_list(path, f"views[{i}].{key}", view[key], width, first)
    _check_board(path, data.get("board"), first)


def _check_board(path: str, board, first=None) -> None:
    """The `board` entry (`tiltfit.target.shape.Board.summary`), where present: a known model, finite parameters and
    σ, and for the free model one [X, Y, Z] per point: as many as the views' per-point lists hold (`first`, as
    `_point_list` returns it), where the file has such lists."""
    from tiltfit.target.shape import BOARD_MODELS, WARP_PARAMETERS

    if board is None:
        return
    if not isinstance(board, dict):
        raise CalibFileError(f"{path}: board: expected an object or null, got {describe(board)}")
    model = board.get("model")
    if model not in BOARD_MODELS:
        raise CalibFileError(f"{path}: board.model: expected one of {', '.join(BOARD_MODELS)}, got {describe(model)}")
    for key in ("max_offset_in_plane_mm", "max_offset_out_of_plane_mm"):
        _optional_number(path, f"board.{key}", board.get(key), nonnegative=True)
    if model == "warp":
        for group in ("parameters", "sigma"):
            entry = board.get(group)
            if entry is None and group == "sigma":
                continue
            if not isinstance(entry, dict):
                raise CalibFileError(f"{path}: board.{group}: expected an object, got {describe(entry)}")
            for k in WARP_PARAMETERS:
                if k not in entry and group == "parameters":
                    raise CalibFileError(f"{path}: board.{group}.{k}: missing key")
                _optional_number(path, f"board.{group}.{k}", entry.get(k), nonnegative=group == "sigma")
    if model == "free":
        if not isinstance(board.get("points_mm"), list):
            raise CalibFileError(f"{path}: board.points_mm: expected a list of [X, Y, Z], got "
                                 f"{describe(board.get('points_mm'))}")
        for key in ("points_mm", "sigma_points_mm"):
            if board.get(key) is not None:
                if first is not None and isinstance(board[key], list) and len(board[key]) != first[1]:
                    raise CalibFileError(f"{path}: board.{key}: {len(board[key])} points, but {first[0]} has "
                                         f"{first[1]} (expected one [X, Y, Z] per feature point of the target)")
                first = _point_list(path, f"board.{key}", board[key], 3, first)


def _check_uncertainty_extras(path: str, data: dict) -> None:
    """`sigma_model`, `cross_validation` and the map of `projection_uncertainty` where present (what
    `tiltfit.report.plots` reads of them): objects, a name, numbers where numbers are written (null where not finite),
    per pair its two groups and verdict, and a σ map of one row per grid_y_px and one column per grid_x_px."""
    pu = data.get("projection_uncertainty")
    if isinstance(pu, dict) and pu.get("sigma_px") is not None:
        shape = []
        for key in ("grid_y_px", "grid_x_px"):
            grid = pu.get(key)
            if not (isinstance(grid, list) and grid and all(is_finite_number(v) for v in grid)):
                raise CalibFileError(f"{path}: projection_uncertainty.{key}: expected a list of pixel positions, "
                                     f"got {describe(grid)}")
            shape.append(len(grid))
        sigma = pu["sigma_px"]
        if not (isinstance(sigma, list) and len(sigma) == shape[0]
                and all(isinstance(row, list) and len(row) == shape[1]
                        and all(v is None or (is_finite_number(v) and v >= 0) for v in row) for row in sigma)):
            raise CalibFileError(f"{path}: projection_uncertainty.sigma_px: expected {shape[0]} rows of {shape[1]} "
                                 "non-negative numbers or null (grid_y_px by grid_x_px)")
    model = data.get("sigma_model")
    if model is not None:
        if not isinstance(model, dict):
            raise CalibFileError(f"{path}: sigma_model: expected an object, got {describe(model)}")
        if model.get("name") is not None and not isinstance(model["name"], str):
            raise CalibFileError(f"{path}: sigma_model.name: expected a name, got {describe(model['name'])}")
        for key in ("design_effect", "ratio_min", "ratio_max", "n_views"):
            _optional_number(path, f"sigma_model.{key}", model.get(key), nonnegative=True)
    cv = data.get("cross_validation")
    if cv is None:
        return
    if not isinstance(cv, dict):
        raise CalibFileError(f"{path}: cross_validation: expected an object, got {describe(cv)}")
    pairs = cv.get("pairs", [])
    if not isinstance(pairs, list):
        raise CalibFileError(f"{path}: cross_validation.pairs: expected a list, got {describe(pairs)}")
    for i, pair in enumerate(pairs):
        key = f"cross_validation.pairs[{i}]"
        if not isinstance(pair, dict):
            raise CalibFileError(f"{path}: {key}: expected an object, got {describe(pair)}")
        groups = pair.get("groups")
        if not (isinstance(groups, list) and len(groups) == 2):
            raise CalibFileError(f"{path}: {key}.groups: expected the two groups' numbers, got {describe(groups)}")
        for name in ("median_px", "worst_px", "predicted_median_px", "predicted_worst_px", "rms_ratio"):
            _optional_number(path, f"{key}.{name}", pair.get(name), nonnegative=True)
        if not isinstance(pair.get("verdict"), str):
            raise CalibFileError(f"{path}: {key}.verdict: expected a sentence, got {describe(pair.get('verdict'))}")


#: Where `camera_from_calib` starts U and d that the file leaves undetermined (mm).
START_U_MM, START_D_MM = 600.0, 10.0


def camera_from_calib(data: dict, blur_model: str | None = None) -> LensCamera:
    """A LensCamera with the file's lens state and views (one identity view if it has none).

    U and d the file leaves undetermined start at 600 and 10 mm; a file that gives the lens tilt θL but not θF
    (an OpenCV tilted-model file: `tiltfit.files.opencv_file.read_opencv`) gets the θF of that θL at this U."""
    import torch

    from tiltfit.calibrate.model import LensCamera
    from tiltfit.files.calib_lens import lens_from_calib

    views = data.get("views") or []
    n = max(len(views), 1)
    R = [v["R"] for v in views] if views else None
    T = [v["T_mm"] for v in views] if views else None
    start = {"U_mm": START_U_MM if data["U_mm"] is None else data["U_mm"],
             "d_mm": START_D_MM if data["d_mm"] is None else data["d_mm"]}
    lens, _ = lens_from_calib({**data, **start})
    cam = LensCamera.from_lens(lens, n, R=R, T_mm=T,
                                   blur_model=blur_model or data.get("blur_model") or "ellipse")
    if isinstance(data.get("blur_offset_px"), (int, float)) and math.isfinite(data["blur_offset_px"]):
        with torch.no_grad():
            cam.blur_offset_px.fill_(float(data["blur_offset_px"]))
    return cam


def sigma_from_calib(data: dict) -> dict:
    """The file's one-σ values of w_mm, U_mm, d_mm (those present and finite)."""
    sig = data.get("sigma") or {}
    return {k: float(sig[k]) for k in ("w_mm", "U_mm", "d_mm")
            if is_finite_number(sig.get(k)) and 0 < sig[k] < MAX_LENGTH_MM}
