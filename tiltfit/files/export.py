"""A calibration in other libraries' terms: OpenCV's camera, the note of what it cannot hold, and kornia's
PinholeCamera; what the camera-file readers share (focus nodes, focal-length checks).

    opencv_camera(calib)                 CALIB.json dict -> K, distortion coefficients, lens_from_camera
    kornia_camera(calib)                 CALIB.json dict -> kornia.geometry.camera.PinholeCamera (all views)
    tiltfit.files.opencv_file            write_opencv / read_opencv: camera.yml (cv2.FileStorage)
    tiltfit.files.mrcal_file             write_mrcal / read_mrcal: mrcal's .cameramodel

OpenCV's camera: K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx = fy = w / p (pixels), the distortion
coefficients (k1, k2, p1, p2, k3 [, k4, k5, k6]) in the same order and normalisation as ours, and per-view
rvec (Rodrigues of R) and tvec (mm) with X_cam = R X_target + t — the same conventions as CALIB.json, so an
untilted calibration projects identically through `cv2.projectPoints`. What OpenCV cannot represent is said
in the file (`tiltfit_note`): the blur (U, d) and the tilted plane of focus. A distortion model that the
coefficients alone do not name (rational5: the rational model with k3, k5, k6 held at 0) is written as `flags`
(`cv2.calibrateCamera`'s, e.g. CALIB_RATIONAL_MODEL | CALIB_FIX_K3 | CALIB_FIX_K5 | CALIB_FIX_K6) and
`tiltfit_distortion_model` (a line saying it).

A tilted lens whose distortion is about its own axis (CALIB.json `distortion_centre` "lens_axis") is OpenCV's
tilted model (CALIB_TILTED_MODEL), exactly: OpenCV's camera frame is the lens frame (its z the lens axis n),
its tilt R(τx, τy) = R_y(τy) R_x(τx) has n as third column (`renderer.cameras.lens.opencv_tilt`), and with
the sensor w from the lens centre along our optical axis

    fx = fy = w / (p cos θL)   (n_z = cos θL: the lens centre to the sensor along the lens axis),
    (cx, cy) = our principal point + fx (R₀₂, R₁₂)   (where the lens axis meets the sensor),
    rvec, tvec = Rᵀ R_view, Rᵀ T_view          (the pose in the lens frame),

with the 14 coefficients (k1, k2, p1, p2, k3, k4, k5, k6, s1..s4 = 0, τx, τy). (OpenCV's map after the
distortion is u = fx (R₂₂ s_x / s_z − R₀₂) + cx with s = R (x'', y'', 1): our uv = c + (w / p) s_xy / s_z.)
`read_opencv` inverts it. A tilted lens with the distortion about the principal point is OpenCV's plain model
(τ = 0). kornia's PinholeCamera has no distortion: `kornia_camera` refuses a calibration with distortion unless
`allow_distortion`.
"""
from __future__ import annotations

import math

import numpy as np


class ExportError(ValueError):
    """A calibration that cannot be exported, or an OpenCV file that cannot be read; one line."""


def camera_matrix(calib: dict) -> np.ndarray:
    """OpenCV's camera matrix of a CALIB.json dict: its lens's (`tiltfit.files.calib_lens.lens_from_calib`, `Lens.K`)."""
    from tiltfit.files.calib_lens import lens_from_calib

    return lens_from_calib(calib)[0].K


def _theta_L_deg(calib: dict) -> float | None:
    """The lens tilt θL, degrees: the file's `theta_L_deg`, or where a hand-made file leaves it out, that of θF, w
    and U (tan θL = w tan θF / (U + w), as `tiltfit.files.calib.camera_from_calib` builds the lens); None unknown."""
    theta_L = calib.get("theta_L_deg")
    if theta_L is not None:
        return theta_L
    th, w, U = calib.get("theta_F_deg"), calib.get("w_mm"), calib.get("U_mm")
    if th == 0:  # an untilted plane of focus: an untilted lens, whatever U is
        return 0.0
    if th is None or w is None or U is None:
        return None
    from renderer.cameras.optics import theta_L_from_theta_F

    return math.degrees(float(theta_L_from_theta_F(math.radians(th), w, U)))


def _tilt(calib: dict) -> tuple[float, float] | None:
    """OpenCV's (τx, τy) of a calibration whose distortion is about a tilted lens's axis, else None."""
    theta_L = _theta_L_deg(calib)
    if calib.get("distortion_centre") != "lens_axis" or not theta_L:
        return None
    from renderer.cameras import opencv_tilt

    return opencv_tilt(math.radians(theta_L), math.radians(calib.get("tilt_axis_deg") or 0.0))


def check_exportable(calib: dict) -> None:
    """Refuse a calibration that no OpenCV camera file projects as it does: distortion about the lens axis
    (`distortion_centre` "lens_axis") of a lens whose tilt θL is undetermined. OpenCV's tilted model needs θL for
    τx, τy, and τ = 0 would put the distortion about the principal point, another camera. Raises ExportError
    naming the field."""
    if calib.get("distortion_centre") == "lens_axis" and _theta_L_deg(calib) is None:
        raise ExportError("theta_L_deg: undetermined (null) in a calibration whose distortion is about the lens "
                          "axis (distortion_centre lens_axis): OpenCV's tilted model needs the lens tilt for tau_x, "
                          "tau_y, and no other OpenCV camera projects as this one; calibrate again with the "
                          "distortion centre at the sensor (principal point), or with views that determine the tilt")


def opencv_camera(calib: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """OpenCV's camera of a CALIB.json dict: (K (3, 3), distortion coefficients (5, 8 or 14: with τx, τy when the
    distortion is about a tilted lens's axis), camera_from_lens (3, 3): the rotation taking a view's pose into
    OpenCV's frame, R_cv = Rᵀ R, t_cv = Rᵀ T; the identity without τ). Module docstring for the relation."""
    from renderer.cameras import tilt_rotation

    K, dist = camera_matrix(calib), distortion_coefficients(calib)
    tau = _tilt(calib)
    if tau is None:
        return K, dist, np.eye(3)
    R = tilt_rotation(*tau)
    f = K[0, 0] / R[2, 2]
    K = np.array([[f, 0.0, K[0, 2] + f * R[0, 2]], [0.0, f, K[1, 2] + f * R[1, 2]], [0.0, 0.0, 1.0]])
    d = np.zeros(14)
    d[:dist.size] = dist
    d[12:] = tau
    return K, d, R


OPENCV_MODEL_FLAGS = {"rational5": ("CALIB_RATIONAL_MODEL", "CALIB_FIX_K3", "CALIB_FIX_K5", "CALIB_FIX_K6"),
                      "rational": ("CALIB_RATIONAL_MODEL",)}


def opencv_model(calib: dict) -> tuple[str, int] | None:
    """(a line naming the distortion model in OpenCV's terms, the `cv2.calibrateCamera` flags that fit the same
    terms) of a calibration whose `distortion_model` is one of `OPENCV_MODEL_FLAGS`, else None."""
    import cv2

    name = calib.get("distortion_model")
    flags = OPENCV_MODEL_FLAGS.get(name)
    if flags is None:
        return None
    from renderer.cameras.distortion import COEFFICIENT_NAMES, MODEL_TERMS

    held = [k for k in COEFFICIENT_NAMES if k not in MODEL_TERMS[name]]
    what = "OpenCV's rational model" + (f" with {', '.join(held)} fixed at 0" if held else "")
    return f"{name}: {what} ({' | '.join(flags)})", sum(int(getattr(cv2, f)) for f in flags)


def distortion_coefficients(calib: dict) -> np.ndarray:
    from renderer.cameras.distortion import BrownConrady

    c = tuple((calib.get("distortion") or {}).get("coefficients") or ())
    return np.array(BrownConrady(c).to_config()["coefficients"], dtype=np.float64)  # OpenCV's 5 or 8


def opencv_note(calib: dict, tool: str = "OpenCV") -> str:
    """What this calibration holds that `tool`'s camera model (OpenCV's, or mrcal's OPENCV8, the same model)
    cannot represent ('' if nothing)."""
    parts = []
    th = calib.get("theta_F_deg")
    theta_L = _theta_L_deg(calib)
    axis = calib.get("distortion_centre") == "lens_axis" and bool(theta_L)
    if axis and tool == "OpenCV":
        parts.append(f"the lens is tilted (theta_L = {theta_L:.6g} deg about the axis at "
                     f"{calib.get('tilt_axis_deg') or 0.0:.6g} deg) with its distortion about its own axis: OpenCV's "
                     "tilted model (tau_x, tau_y) holds that exactly (camera frame = the lens frame, principal point "
                     "= where the lens axis meets the sensor); the tilted plane of focus (theta_F = "
                     f"{'unknown' if th is None else format(th, '.6g')} deg) "
                     "and its depth of field are not represented")
    elif axis:
        parts.append(f"the lens is tilted (theta_L = {theta_L:.6g} deg) and its distortion is "
                     f"about its own axis: {tool} has no tilted model, so this distortion about the principal point "
                     "only approximates the projection; the tilted plane of focus is not represented")
    elif calib.get("distortion_centre") == "lens_axis" and theta_L is None:
        parts.append(f"the lens tilt is undetermined (theta_L null) and the distortion is about the lens axis: "
                     f"{tool}'s distortion about the principal point only approximates the projection")
    elif th is not None and abs(th) > 1e-9:
        parts.append(f"the lens is tilted (plane of focus tilted by theta_F = {th:.4g} deg, lens tilt theta_L = "
                     f"{'unknown' if theta_L is None else format(theta_L, '.4g')} deg): {tool} has no tilted-lens model (OpenCV's tilted-sensor "
                     "tau is a different geometry and is 0 here); the projection of corners is still exact, the "
                     "tilted depth of field is not represented")
    if calib.get("U_mm") is not None or calib.get("d_mm") is not None:
        U, d = calib.get("U_mm"), calib.get("d_mm")
        parts.append(f"the blur model (focus distance U = {'unknown' if U is None else format(U, '.5g')} mm, "
                     f"aperture d = {'unknown' if d is None else format(d, '.4g')} mm) is not in the {tool} camera "
                     f"model: tiltfit keeps U and d beside it (tiltfit_U_mm, tiltfit_d_mm) for rendering")
    board = calib.get("board")
    if isinstance(board, dict) and board.get("model") not in (None, "flat"):
        head = (f"the target's fitted shape (board model {board.get('model')}, CALIB.json `board`): the poses "
                "and the RMS hold with those points, not the target file's flat ones")
        if tool == "OpenCV" and board_points_mm(calib) is not None:
            parts.append(head + "; they are in object_points (N x 3, mm, the target's feature-point order, as "
                         "cv2.calibrateCameraRO's newObjPoints): cv2.projectPoints of object_points with each view's "
                         "rvec, tvec gives the calibration's residuals")
        else:
            parts.append(head + "; the shape is not represented")
    return "; ".join(parts)


def board_points_mm(calib: dict) -> np.ndarray | None:
    """(N, 3) the target's feature points as fitted (CALIB.json `board`, mm, the target frame, feature-point
    order), or None: a flat board (the target file's points are the fitted ones) or a shape this file cannot
    rebuild (a `warp` board without the `target` it bends)."""
    board = calib.get("board")
    if not isinstance(board, dict) or board.get("model") in (None, "flat"):
        return None
    if board.get("model") == "free" and board.get("points_mm") is not None:
        return np.asarray(board["points_mm"], dtype=np.float64).reshape(-1, 3)
    if not isinstance(calib.get("target"), dict):
        return None
    from tiltfit.target.shape import Board
    from tiltfit.target.layout import target_from_dict

    nominal = target_from_dict(calib["target"]).feature_points()
    try:
        return Board.from_summary(nominal, board).points().numpy()
    except (KeyError, TypeError, ValueError) as e:
        raise ExportError(f"board: cannot rebuild the fitted target points ({e})") from None


# The largest image side an OpenCV camera file may state (as tiltfit.files.det.MAX_IMAGE_SIDE).
MAX_IMAGE_SIDE = 1 << 17
#: U and d in camera files (tiltfit's own nodes: OpenCV FileStorage node names; mrcal comment lines by the key).
FOCUS_NODES = (("U_mm", "tiltfit_U_mm"), ("d_mm", "tiltfit_d_mm"))


def check_focal(path: str, key: str, fx: float, fy: float) -> None:
    """Refuse a camera file's focal lengths (pixels) that tiltfit cannot hold: not positive (a mirrored or
    flipped camera) or not square within 1 %."""
    for name, v in (("fx", fx), ("fy", fy)):
        if not v > 0:
            raise ExportError(f"{path}: {key}: the focal length {name} = {v:g} is not positive (a negative one "
                              "mirrors the image); expected fx, fy > 0")
    if abs(fx / fy - 1) > 0.01:
        raise ExportError(f"{path}: {key}: fx = {fx:g} and fy = {fy:g} differ by more than 1 % "
                          "(tiltfit models square pixels)")


def check_focal_length_mm(path: str, key: str, w_mm: float) -> None:
    """Refuse a focal length in mm (focal length in pixels × pixel pitch) beyond CALIB.json's lengths (1e9 mm),
    naming both of its sources."""
    if not (math.isfinite(w_mm) and w_mm <= 1e9):
        raise ExportError(f"{path}: {key}, pixel_pitch_mm: the focal length in pixels times the pixel pitch is "
                          f"{w_mm:g} mm; expected at most 1e9 mm")


def focus_value(path: str, key: str, value) -> float:
    """A focus distance or aperture from a camera file: a positive length (U) or ≥ 0 (d), else ExportError."""
    ok = isinstance(value, float) and math.isfinite(value) and (value >= 0 if "d_mm" in key else value > 0) \
        and value < 1e9
    if not ok:
        raise ExportError(f"{path}: {key}: expected {'an aperture >= 0' if 'd_mm' in key else 'a positive length'} "
                          f"in mm, got {value!r}")
    return float(value)


def add_focus(path: str, out: dict, focus: dict, names: dict) -> None:
    """Put U and d read from a camera file's tiltfit nodes (both or neither; `names`: key -> the file's name of
    it) into a CALIB.json-like dict."""
    if len(focus) == 1:
        given = next(iter(focus))
        missing = next(k for k in names if k != given)
        raise ExportError(f"{path}: {names[missing]}: missing ({names[given]} is given; the blur needs both, or "
                          "neither for a sharp rendering)")
    if len(focus) == 2:
        out.update(U_mm=focus["U_mm"], d_mm=focus["d_mm"], undetermined=[])


def kornia_camera(calib: dict, allow_distortion: bool = False):
    """A kornia PinholeCamera holding every view of a CALIB.json dict (batch = views).

    intrinsics (V, 4, 4) with K in the top-left, extrinsics (V, 4, 4) = [[R, T], [0, 1]] (camera_from_target,
    mm), height and width (V,). kornia's pinhole has no distortion and no tilted lens: a calibration with
    distortion raises ExportError unless `allow_distortion` (then the distortion is dropped).
    """
    import torch
    from kornia.geometry.camera import PinholeCamera

    if not allow_distortion and any(abs(c) > 0 for c in distortion_coefficients(calib)):
        raise ExportError("kornia's PinholeCamera has no lens distortion; undistort the images first or pass "
                          "allow_distortion=True to drop it")
    views = calib.get("views") or [{"R": np.eye(3).tolist(), "T_mm": [0.0, 0.0, 0.0]}]
    V = len(views)
    K = torch.eye(4, dtype=torch.float64).repeat(V, 1, 1)
    K[:, :3, :3] = torch.as_tensor(camera_matrix(calib))
    E = torch.eye(4, dtype=torch.float64).repeat(V, 1, 1)
    E[:, :3, :3] = torch.tensor([v["R"] for v in views], dtype=torch.float64)
    E[:, :3, 3] = torch.tensor([v["T_mm"] for v in views], dtype=torch.float64)
    W, H = calib["image_size_px"]
    return PinholeCamera(K, E, torch.full((V,), float(H), dtype=torch.float64),
                         torch.full((V,), float(W), dtype=torch.float64))
