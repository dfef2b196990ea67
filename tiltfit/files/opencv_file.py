"""OpenCV FileStorage camera files (YAML, XML or JSON, optionally .gz): `write_opencv` and `read_opencv` (for `--init`),
in OpenCV's camera (`tiltfit.files.export.opencv_camera`, whose docstring gives the conventions).

    write_opencv(calib, path)            CALIB.json dict -> camera.yml (cv2.FileStorage)
    read_opencv(path, pixel_pitch_mm)    camera.yml -> CALIB.json-like dict (to start a fit with --init)
"""
from __future__ import annotations

import math
import os

import numpy as np
from camio.checks import is_finite_number

from .export import (FOCUS_NODES, MAX_IMAGE_SIDE, ExportError, add_focus, board_points_mm, check_exportable, check_focal,
                     check_focal_length_mm, focus_value, opencv_camera, opencv_model, opencv_note)


#: The largest rotation-vector angle (rad) read from a camera file: OpenCV writes angles within π; far larger
#: ones lose the rotation to rounding (1e308 became NaN).
MAX_ROTATION_VECTOR_RAD = 1e3
# FileStorage formats by file name ending; `.gz` after any of them compresses the file.


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
        for key, node in FOCUS_NODES:  # for tiltfit and the renderer's calibrated camera; OpenCV ignores them
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
    if not os.path.isfile(path):
        raise ExportError(f"{path}: {'is a folder' if os.path.isdir(path) else 'no such file'}")
    fs = _open_storage(path)
    try:
        _refuse_fisheye(path, fs)
        K = _matrix(path, fs, "camera_matrix", ((3, 3),), required=True)
        size = [_integer(path, fs, "image_width"), _integer(path, fs, "image_height")]
        d, tau = _distortion_and_tilt(path, fs)
        p_node = fs.getNode("pixel_pitch_mm")
        pitch = pixel_pitch_mm
        if not p_node.empty() and not p_node.isNone():
            if not (p_node.isReal() or p_node.isInt()):
                raise ExportError(f"{path}: pixel_pitch_mm: expected a number")
            pitch = p_node.real()
        rv = _matrix(path, fs, "rvecs", ((None, 3), (3,)), required=False)
        tv = _matrix(path, fs, "tvecs", ((None, 3), (3,)), required=False)
        focus = {}
        for key, node_name in FOCUS_NODES:
            node = fs.getNode(node_name)
            if not node.empty() and not node.isNone():
                focus[key] = focus_value(path, node_name, node.real() if (node.isReal() or node.isInt()) else
                                         node.string() if node.isString() else "a sequence or a map")
    finally:
        fs.release()
    if pitch is None or not (np.isfinite(pitch) and pitch > 0):
        raise ExportError(f"{path}: pixel_pitch_mm: not in the file (or not a positive number); give it as "
                          "the pixel_pitch_mm argument")
    out, camera_from_lens = _lens(path, K, size, d, tau, pitch)
    add_focus(path, out, focus, dict(FOCUS_NODES))
    if rv is not None and tv is not None:
        out["views"] = _views(path, rv, tv, camera_from_lens)
    return out


def _refuse_fisheye(path: str, fs) -> None:
    """Refuse a fisheye camera file (its `fisheye_model` / `fisheye` node, or a fisheye `distortion_model`)."""
    for key in ("fisheye_model", "fisheye"):
        node = fs.getNode(key)
        if not node.empty() and not node.isNone() and (not (node.isInt() or node.isReal()) or node.real() != 0):
            raise ExportError(f"{path}: {key}: a fisheye camera file; tiltfit models Brown–Conrady lenses "
                              "(convert with cv2.fisheye, or calibrate without this file as the start)")
    model = fs.getNode("distortion_model")
    if model.isString() and "fisheye" in model.string().lower():
        raise ExportError(f"{path}: distortion_model: a fisheye camera file; tiltfit models Brown–Conrady "
                          "lenses")


def _distortion_and_tilt(path: str, fs) -> tuple[list, tuple[float, float]]:
    """(the Brown–Conrady coefficients, at most 8, and (τx, τy) in radians, (0, 0) without them) of the file's
    distortion_coefficients; thin-prism terms are refused."""
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
    return d, tau


def _lens(path: str, K: np.ndarray, size: list, d: list, tau: tuple, pitch: float):
    """(the CALIB.json-like dict of the lens: w, principal point, distortion and, with τ, the lens tilt and its
    axis; camera_from_lens (3, 3), the identity without τ), the inverse of `opencv_camera`."""
    fx, fy = float(K[0, 0]), float(K[1, 1])
    check_focal(path, "camera_matrix", fx, fy)
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
    check_focal_length_mm(path, "camera_matrix", out["w_mm"])
    if any(tau):
        # θF needs U, which an OpenCV file does not hold: the lens tilt θL and its axis are what it says.
        out.update(theta_F_deg=None, theta_L_deg=math.degrees(theta_L), tilt_axis_deg=math.degrees(phi),
                   distortion_centre="lens_axis")
    return out, R


def _views(path: str, rv: np.ndarray, tv: np.ndarray, camera_from_lens) -> list:
    """CALIB.json views {R, T_mm} in our camera frame of the file's rvecs and tvecs (OpenCV's, the lens frame)."""
    import torch

    from renderer import axis_angle_to_matrix

    R = camera_from_lens
    rv, tv = rv.reshape(-1, 3), tv.reshape(-1, 3)
    if rv.shape[0] != tv.shape[0]:
        raise ExportError(f"{path}: rvecs, tvecs: {rv.shape[0]} and {tv.shape[0]} rows; expected one per view")
    with np.errstate(over="ignore"):
        angle = np.linalg.norm(rv, axis=1)
    if (angle > MAX_ROTATION_VECTOR_RAD).any():
        i = int(np.argmax(angle > MAX_ROTATION_VECTOR_RAD))
        raise ExportError(f"{path}: rvecs: row {i} turns by {angle[i]:g} rad; expected a rotation vector (angle "
                          f"at most {MAX_ROTATION_VECTOR_RAD:g} rad)")
    return [{"R": (R @ axis_angle_to_matrix(torch.tensor(r, dtype=torch.float64)).numpy()).tolist(),
             "T_mm": [float(x) for x in R @ t]} for r, t in zip(rv, tv)]


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
