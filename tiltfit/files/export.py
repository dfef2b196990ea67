"""A calibration in other libraries' terms: OpenCV FileStorage files and kornia's PinholeCamera.

    write_opencv(calib, path)            CALIB.json dict -> camera.yml (cv2.FileStorage)
    read_opencv(path, pixel_pitch_mm)    camera.yml -> CALIB.json-like dict (to start a fit with --init)
    kornia_camera(calib)                 CALIB.json dict -> kornia.geometry.camera.PinholeCamera (all views)

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
import os

import numpy as np
from camio.checks import is_finite_number


class ExportError(ValueError):
    """A calibration that cannot be exported, or an OpenCV file that cannot be read; one line."""


def _K(calib: dict) -> np.ndarray:
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

    K, dist = _K(calib), _dist(calib)
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


# The OpenCV calibration flags that fit the same distortion terms as a tiltfit model (CALIB.json
# `distortion_model`), where the coefficients alone do not say it: rational5 is OpenCV's rational model (8
# coefficients) with k3, k5 and k6 held at 0.
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


def _dist(calib: dict) -> np.ndarray:
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


#: The largest rotation-vector angle (rad) read from a camera file: OpenCV writes angles within π; far larger
#: ones lose the rotation to rounding (1e308 became NaN).
MAX_ROTATION_VECTOR_RAD = 1e3
# FileStorage formats by file name ending; `.gz` after any of them compresses the file.
OPENCV_EXTENSIONS = (".yml", ".yaml", ".xml", ".json")
# The largest image side an OpenCV camera file may state (as tiltfit.files.det.MAX_IMAGE_SIDE).
MAX_IMAGE_SIDE = 1 << 17


def _format_name(path: str) -> str:
    """`path`'s FileStorage format as a dummy file name (".yml", ".xml" or ".json"); YAML by default."""
    name = path.lower().removesuffix(".gz")
    ext = os.path.splitext(name)[1]
    return {".yaml": ".yml", ".xml": ".xml", ".json": ".json"}.get(ext, ".yml")


def opencv_text(calib: dict, format_name: str = ".yml") -> str:
    """The OpenCV FileStorage text (YAML, XML or JSON by `format_name`'s extension) of a CALIB.json dict.

    Nodes: camera_matrix (3×3), distortion_coefficients (1×5 or 1×8; 1×14 with τx, τy for a tilted lens's
    distortion about its axis: `opencv_camera`), image_width, image_height, rvecs and tvecs (V×3, one row per
    view, tvec in mm, OpenCV's frame), images (a sequence of the views' file names), object_points (N×3, mm: the
    target's fitted points where the calibration fitted its shape, `board_points_mm`; the poses hold with these,
    as with cv2.calibrateCameraRO's newObjPoints), rms_reprojection_px (per corner, OpenCV's definition),
    pixel_pitch_mm, tiltfit_note.
    """
    import cv2

    from renderer import matrix_to_axis_angle  # torch: imported by the commands that convert rotations

    check_exportable(calib)
    fs = cv2.FileStorage(format_name, cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
    try:
        W, H = calib["image_size_px"]
        fs.write("image_width", int(W))
        fs.write("image_height", int(H))
        K, dist, lens_from_camera = opencv_camera(calib)
        lens_from_camera = lens_from_camera.T
        fs.write("camera_matrix", K)
        fs.write("distortion_coefficients", dist.reshape(1, -1))
        views = calib.get("views") or []
        if views:
            rv = matrix_to_axis_angle(lens_from_camera @ np.array([v["R"] for v in views], dtype=np.float64)).numpy()
            tv = np.array([v["T_mm"] for v in views], dtype=np.float64) @ lens_from_camera.T
            fs.write("rvecs", rv)
            fs.write("tvecs", tv)
            fs.startWriteStruct("images", cv2.FileNode_SEQ)  # one string per view: no length limit
            for v in views:
                fs.write("", os.path.basename(str(v.get("image", ""))))
            fs.endWriteStruct()
            points = board_points_mm(calib)
            if points is not None:
                fs.write("object_points", points)
        if calib.get("rms_reprojection_px") is not None:
            fs.write("rms_reprojection_px", float(calib["rms_reprojection_px"]))
        fs.write("pixel_pitch_mm", float(calib["pixel_pitch_mm"]))
        for key, node in _FOCUS_NODES:  # for tiltfit and the renderer's calibrated camera; OpenCV ignores them
            if is_finite_number(calib.get(key)):
                fs.write(node, float(calib[key]))
        fs.write("tiltfit_note", opencv_note(calib) or "the calibration is fully represented")
        model = opencv_model(calib)
        if model is not None:
            fs.write("flags", int(model[1]))
            fs.write("tiltfit_distortion_model", model[0])
        text = fs.releaseAndGetString()
        # OpenCV's JSON writer escapes an apostrophe (in a note, an image's name) as \', which JSON does not allow;
        # its reader takes the plain apostrophe back, and a backslash is written as \\ so no other \' occurs.
        return text.replace("\\'", "'") if format_name.endswith(".json") else text
    except cv2.error as e:
        fs.release()
        raise ExportError(f"cannot write in OpenCV's format ({' '.join(str(e).split())[-160:]})") from None


def write_opencv(calib: dict, path: str) -> None:
    """Write an OpenCV FileStorage of a CALIB.json dict (`opencv_text`; YAML/XML/JSON by extension, gzip
    compressed when the name ends in .gz) atomically (`camio.files.atomic_output`)."""
    import gzip

    from camio.files import atomic_output

    text = opencv_text(calib, _format_name(path))
    data = text.encode("utf-8")
    if path.lower().endswith(".gz"):
        data = gzip.compress(data, mtime=0)
    with atomic_output(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)


def _matrix(path: str, fs, key: str, shapes: tuple, required: bool):
    """A FileStorage node as a finite float64 array of one of `shapes` (None when absent and optional)."""
    import cv2

    node = fs.getNode(key)
    if node.empty() or node.isNone():
        if required:
            raise ExportError(f"{path}: {key}: missing")
        return None
    try:
        m = node.mat() if node.isMap() else None
    except (cv2.error, SystemError):
        m = None
    if m is None and node.isSeq():
        try:
            m = np.array([node.at(i).real() for i in range(node.size())], dtype=np.float64)
        except (cv2.error, SystemError):
            m = None
    if m is None:
        raise ExportError(f"{path}: {key}: expected a matrix (!!opencv-matrix with rows, cols, dt, data)")
    m = np.asarray(m, dtype=np.float64)
    if not any(m.shape == s or (s[0] is None and m.ndim == 2 and m.shape[1:] == s[1:]) for s in shapes):
        want = " or ".join("×".join("N" if d is None else str(d) for d in s) for s in shapes)
        raise ExportError(f"{path}: {key}: expected {want}, got shape {'×'.join(map(str, m.shape)) or 'scalar'}")
    if not np.isfinite(m).all():
        raise ExportError(f"{path}: {key}: expected finite numbers")
    return m


def _check_focal(path: str, key: str, fx: float, fy: float) -> None:
    """Refuse a camera file's focal lengths (pixels) that tiltfit cannot hold: not positive (a mirrored or
    flipped camera) or not square within 1 %."""
    for name, v in (("fx", fx), ("fy", fy)):
        if not v > 0:
            raise ExportError(f"{path}: {key}: the focal length {name} = {v:g} is not positive (a negative one "
                              "mirrors the image); expected fx, fy > 0")
    if abs(fx / fy - 1) > 0.01:
        raise ExportError(f"{path}: {key}: fx = {fx:g} and fy = {fy:g} differ by more than 1 % "
                          "(tiltfit models square pixels)")


def _check_focal_length_mm(path: str, key: str, w_mm: float) -> None:
    """Refuse a focal length in mm (focal length in pixels × pixel pitch) beyond CALIB.json's lengths (1e9 mm),
    naming both of its sources."""
    if not (math.isfinite(w_mm) and w_mm <= 1e9):
        raise ExportError(f"{path}: {key}, pixel_pitch_mm: the focal length in pixels times the pixel pitch is "
                          f"{w_mm:g} mm; expected at most 1e9 mm")


def _integer(path: str, fs, key: str) -> int:
    node = fs.getNode(key)
    if node.empty() or node.isNone():
        raise ExportError(f"{path}: {key}: missing")
    if not node.isInt() and not node.isReal():
        raise ExportError(f"{path}: {key}: expected an integer number of pixels")
    v = node.real()
    if not (np.isfinite(v) and v == int(v) and 1 <= v <= MAX_IMAGE_SIDE):
        raise ExportError(f"{path}: {key}: expected an integer in 1..{MAX_IMAGE_SIDE}, got {v:g}")
    return int(v)


def _open_storage(path: str):
    """A cv2.FileStorage open for reading (a .gz file is decompressed by OpenCV itself)."""
    import cv2

    from camio.files import quiet_c_stderr

    try:
        with quiet_c_stderr():  # OpenCV's parser prints its complaints before raising
            fs = cv2.FileStorage(path, cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError):  # a parse error surfaces as either
        raise ExportError(f"{path}: not an OpenCV FileStorage file") from None
    if not fs.isOpened():
        raise ExportError(f"{path}: not an OpenCV FileStorage file")
    return fs


def read_opencv(path: str, pixel_pitch_mm: float | None = None) -> dict:
    """Read an OpenCV FileStorage camera file (YAML, XML or JSON, optionally .gz) into a CALIB.json-like dict
    (for `--init`).

    Needs camera_matrix (3×3) and image_width/image_height (integers); distortion_coefficients optional
    (Brown–Conrady with 4, 5, 8, 12 or 14 coefficients; thin-prism terms s1..s4 must be 0; τx, τy are read as
    a tilted lens with its distortion about its axis, the inverse of `opencv_camera`: θL, the tilt axis,
    w = fx p cos θL, the principal point and the poses in our frame; a fisheye file is refused). fx and fy
    must agree within 1 % (our pixels are square; their mean is used). The pixel pitch comes from the file (`pixel_pitch_mm`, written by `write_opencv`)
    or the argument.

    Raises:
        ExportError: naming the file and the missing or malformed node.
    """
    import torch

    from renderer import axis_angle_to_matrix

    if not os.path.isfile(path):
        raise ExportError(f"{path}: {'is a folder' if os.path.isdir(path) else 'no such file'}")
    fs = _open_storage(path)
    try:
        for key in ("fisheye_model", "fisheye"):
            node = fs.getNode(key)
            if not node.empty() and not node.isNone() and (not (node.isInt() or node.isReal()) or node.real() != 0):
                raise ExportError(f"{path}: {key}: a fisheye camera file; tiltfit models Brown–Conrady lenses "
                                  "(convert with cv2.fisheye, or calibrate without this file as the start)")
        model = fs.getNode("distortion_model")
        if model.isString() and "fisheye" in model.string().lower():
            raise ExportError(f"{path}: distortion_model: a fisheye camera file; tiltfit models Brown–Conrady "
                              "lenses")
        K = _matrix(path, fs, "camera_matrix", ((3, 3),), required=True)
        size = [_integer(path, fs, "image_width"), _integer(path, fs, "image_height")]
        d = _matrix(path, fs, "distortion_coefficients",
                    tuple((1, n) for n in (4, 5, 8, 12, 14)) + tuple((n, 1) for n in (4, 5, 8, 12, 14))
                    + tuple((n,) for n in (4, 5, 8, 12, 14)), required=False)
        d = [] if d is None else [float(v) for v in d.ravel()]
        tau = (0.0, 0.0)
        if len(d) > 8:
            if any(d[8:12]):
                raise ExportError(f"{path}: distortion_coefficients: thin-prism terms (s1..s4) are not supported")
            if len(d) == 14:
                tau = (d[12], d[13])
                if not all(abs(t) < math.pi / 2 for t in tau):
                    raise ExportError(f"{path}: distortion_coefficients: tau_x, tau_y: expected tilts within "
                                      f"±90° (radians), got {tau[0]:g}, {tau[1]:g}")
            d = d[:8]
        p_node = fs.getNode("pixel_pitch_mm")
        pitch = pixel_pitch_mm
        if not p_node.empty() and not p_node.isNone():
            if not (p_node.isReal() or p_node.isInt()):
                raise ExportError(f"{path}: pixel_pitch_mm: expected a number")
            pitch = p_node.real()
        rv = _matrix(path, fs, "rvecs", ((None, 3), (3,)), required=False)
        tv = _matrix(path, fs, "tvecs", ((None, 3), (3,)), required=False)
        focus = {}
        for key, node_name in _FOCUS_NODES:
            node = fs.getNode(node_name)
            if not node.empty() and not node.isNone():
                focus[key] = _focus_value(path, node_name, node.real() if (node.isReal() or node.isInt()) else
                                          node.string() if node.isString() else "a sequence or a map")
    finally:
        fs.release()
    if pitch is None or not (np.isfinite(pitch) and pitch > 0):
        raise ExportError(f"{path}: pixel_pitch_mm: not in the file (or not a positive number); give it as "
                          "the pixel_pitch_mm argument")
    fx, fy = float(K[0, 0]), float(K[1, 1])
    _check_focal(path, "camera_matrix", fx, fy)
    from renderer.cameras import lens_tilt_from_opencv, tilt_rotation

    f = 0.5 * (fx + fy)
    R = tilt_rotation(*tau)  # camera_from_lens (the identity without τ)
    theta_L, phi = lens_tilt_from_opencv(*tau)
    pp = [float(K[0, 2]) - f * R[0, 2], float(K[1, 2]) - f * R[1, 2]]
    if any(tau) and not all(-s <= c <= 2 * s for c, s in zip(pp, size)):
        # CALIB.json's own bound on the principal point (tiltfit.files.calib): name the tilt that moved it there.
        raise ExportError(f"{path}: distortion_coefficients: tau_x, tau_y = {tau[0]:g}, {tau[1]:g} rad tilt the "
                          f"lens by theta_L = {math.degrees(theta_L):.4g} deg, which puts the optical axis at "
                          f"({pp[0]:.6g}, {pp[1]:.6g}) px, more than one image size outside the {size[0]}x{size[1]} "
                          "image; expected a smaller tilt")
    out = {"pixel_pitch_mm": float(pitch), "image_size_px": size,
           "principal_point_px": pp,
           "w_mm": float(f * R[2, 2]) * float(pitch), "U_mm": None, "d_mm": None, "theta_F_deg": 0.0,
           "distortion": {"model": "brown_conrady", "coefficients": d or [0.0]},
           "undetermined": ["U_mm", "d_mm"], "source": os.path.abspath(path)}
    _check_focal_length_mm(path, "camera_matrix", out["w_mm"])
    _add_focus(path, out, focus, dict(_FOCUS_NODES))
    if any(tau):
        # θF needs U, which an OpenCV file does not hold: the lens tilt θL and its axis are what it says.
        out.update(theta_F_deg=None, theta_L_deg=math.degrees(theta_L), tilt_axis_deg=math.degrees(phi),
                   distortion_centre="lens_axis")
    if rv is not None and tv is not None:
        rv, tv = rv.reshape(-1, 3), tv.reshape(-1, 3)
        if rv.shape[0] != tv.shape[0]:
            raise ExportError(f"{path}: rvecs, tvecs: {rv.shape[0]} and {tv.shape[0]} rows; expected one per view")
        with np.errstate(over="ignore"):
            angle = np.linalg.norm(rv, axis=1)
        if (angle > MAX_ROTATION_VECTOR_RAD).any():
            i = int(np.argmax(angle > MAX_ROTATION_VECTOR_RAD))
            raise ExportError(f"{path}: rvecs: row {i} turns by {angle[i]:g} rad; expected a rotation vector (angle "
                              f"at most {MAX_ROTATION_VECTOR_RAD:g} rad)")
        out["views"] = [{"R": (R @ axis_angle_to_matrix(torch.tensor(r, dtype=torch.float64)).numpy()).tolist(),
                         "T_mm": [float(x) for x in R @ t]} for r, t in zip(rv, tv)]
    return out


# mrcal (https://mrcal.secretsauce.net): a camera model file is a Python dict literal, `#` comments allowed.
MRCAL_EXTENSION = ".cameramodel"
_MRCAL_PITCH = "# tiltfit pixel_pitch_mm = "
#: U and d in camera files (tiltfit's own nodes: OpenCV FileStorage node names; mrcal comment lines by the key).
_FOCUS_NODES = (("U_mm", "tiltfit_U_mm"), ("d_mm", "tiltfit_d_mm"))
_MRCAL_MODELS = {"LENSMODEL_PINHOLE": 0, "LENSMODEL_OPENCV4": 4, "LENSMODEL_OPENCV5": 5, "LENSMODEL_OPENCV8": 8}


def mrcal_text(calib: dict) -> str:
    """An mrcal `.cameramodel` of a CALIB.json dict: LENSMODEL_OPENCV8 (fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5,
    k6: OpenCV's order and pixel convention, which are mrcal's), the camera at the reference frame. A tilted
    lens projects its corners exactly as this model (the chief ray meets a sensor perpendicular to the axis);
    what mrcal cannot hold (focus, aperture, the tilted plane of focus) is said in a comment line."""
    K, d = _K(calib), np.zeros(8)
    coeffs = _dist(calib)
    d[:coeffs.size] = coeffs
    W, H = (int(v) for v in calib["image_size_px"])
    intrinsics = [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), *(float(v) for v in d)]
    note = opencv_note(calib, "mrcal") or "the calibration is fully represented"
    name = calib.get("distortion_model")
    model = (f"# distortion {name}: LENSMODEL_OPENCV8 with {', '.join(k for k in ('k3', 'k5', 'k6'))} = 0\n"
             if name == "rational5" else "")
    return ("# tiltfit calibration as an mrcal camera model\n"
            f"# what this file does not hold: {note}\n" + model +
            f"{_MRCAL_PITCH}{float(calib['pixel_pitch_mm'])!r}\n" +
            "".join(f"# tiltfit {key} = {float(calib[key])!r}\n" for key, _ in _FOCUS_NODES
                    if is_finite_number(calib.get(key))) +
            "{\n"
            "    'lensmodel': 'LENSMODEL_OPENCV8',\n"
            f"    'intrinsics': [{', '.join(repr(v) for v in intrinsics)}],\n"
            "    'extrinsics': [0.0, 0.0, 0.0, 0.0, 0.0, 0.0],\n"
            f"    'imagersize': [{W}, {H}],\n"
            "}\n")


def write_mrcal(calib: dict, path: str) -> None:
    """Write `mrcal_text` atomically (`camio.files.write_text`)."""
    from camio.files import write_text

    write_text(path, mrcal_text(calib))


def read_mrcal(path: str, pixel_pitch_mm: float | None = None) -> dict:
    """Read an mrcal `.cameramodel` (LENSMODEL_PINHOLE or OPENCV4/5/8) into a CALIB.json-like dict (for
    `--init`). The pixel pitch comes from tiltfit's comment line or the argument.

    Raises:
        ExportError: naming the file and the missing or malformed key.
    """
    import ast

    if not os.path.isfile(path):
        raise ExportError(f"{path}: {'is a folder' if os.path.isdir(path) else 'no such file'}")
    try:
        with open(path, encoding="utf-8") as f:
            text = f.read(1 << 20)
        model = ast.literal_eval(text)
    except (OSError, UnicodeDecodeError, ValueError, SyntaxError, MemoryError, RecursionError):
        raise ExportError(f"{path}: not an mrcal camera model (a Python dict literal)") from None
    if not isinstance(model, dict):
        raise ExportError(f"{path}: not an mrcal camera model (a Python dict literal)")
    lensmodel = model.get("lensmodel")
    if lensmodel not in _MRCAL_MODELS:
        raise ExportError(f"{path}: lensmodel: expected one of {', '.join(_MRCAL_MODELS)}, got {lensmodel!r}")
    n = 4 + _MRCAL_MODELS[lensmodel]
    intr = model.get("intrinsics")
    if not (isinstance(intr, (list, tuple)) and len(intr) == n and all(is_finite_number(v) for v in intr)):
        raise ExportError(f"{path}: intrinsics: expected {n} finite numbers for {lensmodel}")
    size = model.get("imagersize")
    if not (isinstance(size, (list, tuple)) and len(size) == 2 and all(
            isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= MAX_IMAGE_SIDE for v in size)):
        raise ExportError(f"{path}: imagersize: expected two integers in 1..{MAX_IMAGE_SIDE}, got {size!r}")
    pitch = pixel_pitch_mm
    for line in text.splitlines():
        if line.startswith(_MRCAL_PITCH):
            try:
                pitch = float(line[len(_MRCAL_PITCH):])
            except ValueError:
                raise ExportError(f"{path}: pixel_pitch_mm: expected a number in tiltfit's comment line") from None
    if pitch is None or not (math.isfinite(pitch) and pitch > 0):
        raise ExportError(f"{path}: pixel_pitch_mm: not in the file (or not a positive number); give it as "
                          "the pixel_pitch_mm argument")
    focus = {}
    for line in text.splitlines():
        for key, _ in _FOCUS_NODES:
            head = f"# tiltfit {key} = "
            if line.startswith(head):
                try:
                    value = float(line[len(head):])
                except ValueError:
                    value = line[len(head):].strip()
                focus[key] = _focus_value(path, key, value)
    fx, fy, cx, cy = (float(v) for v in intr[:4])
    _check_focal(path, "intrinsics", fx, fy)
    out = {"pixel_pitch_mm": float(pitch), "image_size_px": [int(size[0]), int(size[1])],
           "principal_point_px": [cx, cy], "w_mm": 0.5 * (fx + fy) * float(pitch),
           "U_mm": None, "d_mm": None, "theta_F_deg": 0.0,
           "distortion": {"model": "brown_conrady", "coefficients": [float(v) for v in intr[4:]] or [0.0]},
           "undetermined": ["U_mm", "d_mm"], "source": os.path.abspath(path)}
    _check_focal_length_mm(path, "intrinsics", out["w_mm"])
    _add_focus(path, out, focus, {key: f"# tiltfit {key}" for key, _ in _FOCUS_NODES})
    return out


def _focus_value(path: str, key: str, value) -> float:
    """A focus distance or aperture from a camera file: a positive length (U) or ≥ 0 (d), else ExportError."""
    ok = isinstance(value, float) and math.isfinite(value) and (value >= 0 if "d_mm" in key else value > 0) \
        and value < 1e9
    if not ok:
        raise ExportError(f"{path}: {key}: expected {'an aperture >= 0' if 'd_mm' in key else 'a positive length'} "
                          f"in mm, got {value!r}")
    return float(value)


def _add_focus(path: str, out: dict, focus: dict, names: dict) -> None:
    """Put U and d read from a camera file's tiltfit nodes (both or neither; `names`: key -> the file's name of
    it) into a CALIB.json-like dict."""
    if len(focus) == 1:
        given = next(iter(focus))
        missing = next(k for k in names if k != given)
        raise ExportError(f"{path}: {names[missing]}: missing ({names[given]} is given; the blur needs both, or "
                          "neither for a sharp rendering)")
    if len(focus) == 2:
        out.update(U_mm=focus["U_mm"], d_mm=focus["d_mm"], undetermined=[])


def is_mrcal_file(path: str) -> bool:
    return path.lower().endswith(MRCAL_EXTENSION)


def is_opencv_file(path: str) -> bool:
    """True for .yml/.yaml/.xml files (optionally .gz), .json files in OpenCV's JSON FileStorage layout (an
    `opencv-matrix` camera_matrix, as `write_opencv` writes), or a file that starts like a FileStorage."""
    low = path.lower()
    ext = os.path.splitext(low.removesuffix(".gz"))[1]
    if ext in (".yml", ".yaml", ".xml"):
        return True
    if low.endswith(".gz") and ext == ".json":
        return True
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError:
        return False
    if head.startswith(b"%YAML") or head.startswith(b"<?xml"):
        return True
    return ext == ".json" and b'"camera_matrix"' in head and b'"opencv-matrix"' in head


def kornia_camera(calib: dict, allow_distortion: bool = False):
    """A kornia PinholeCamera holding every view of a CALIB.json dict (batch = views).

    intrinsics (V, 4, 4) with K in the top-left, extrinsics (V, 4, 4) = [[R, T], [0, 1]] (camera_from_target,
    mm), height and width (V,). kornia's pinhole has no distortion and no tilted lens: a calibration with
    distortion raises ExportError unless `allow_distortion` (then the distortion is dropped).
    """
    import torch
    from kornia.geometry.camera import PinholeCamera

    if not allow_distortion and any(abs(c) > 0 for c in _dist(calib)):
        raise ExportError("kornia's PinholeCamera has no lens distortion; undistort the images first or pass "
                          "allow_distortion=True to drop it")
    views = calib.get("views") or [{"R": np.eye(3).tolist(), "T_mm": [0.0, 0.0, 0.0]}]
    V = len(views)
    K = torch.eye(4, dtype=torch.float64).repeat(V, 1, 1)
    K[:, :3, :3] = torch.as_tensor(_K(calib))
    E = torch.eye(4, dtype=torch.float64).repeat(V, 1, 1)
    E[:, :3, :3] = torch.tensor([v["R"] for v in views], dtype=torch.float64)
    E[:, :3, 3] = torch.tensor([v["T_mm"] for v in views], dtype=torch.float64)
    W, H = calib["image_size_px"]
    return PinholeCamera(K, E, torch.full((V,), float(H), dtype=torch.float64),
                         torch.full((V,), float(W), dtype=torch.float64))
