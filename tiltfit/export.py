"""A calibration in other libraries' terms: OpenCV FileStorage files and kornia's PinholeCamera.

    write_opencv(calib, path)            CALIB.json dict -> camera.yml (cv2.FileStorage)
    read_opencv(path, pixel_pitch_mm)    camera.yml -> CALIB.json-like dict (the start of a fit)
    kornia_camera(calib)                 CALIB.json dict -> kornia.geometry.camera.PinholeCamera (all views)

OpenCV's camera: K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx = fy = w / p (pixels), the distortion
coefficients (k1, k2, p1, p2, k3 [, k4, k5, k6]) in the same order and normalisation as ours, and per-view
rvec (Rodrigues of R) and tvec (mm) with X_cam = R X_target + t — the same conventions as CALIB.json, so an
untilted calibration projects identically through `cv2.projectPoints`. What OpenCV cannot represent is said
in the file (`tiltfit_note`): the blur (U, d) and a tilted plane of focus (θF ≠ 0) — OpenCV's tilted-sensor
model (τx, τy) describes a tilted sensor, not a tilted lens, and is left at 0. kornia's PinholeCamera has no
distortion: `kornia_camera` refuses a calibration with distortion unless `allow_distortion`.
"""
from __future__ import annotations

import os

import numpy as np
import torch
from renderer import axis_angle_to_matrix, matrix_to_axis_angle


class ExportError(ValueError):
    """A calibration that cannot be exported, or an OpenCV file that cannot be read; one line."""


def _K(calib: dict) -> np.ndarray:
    F = float(calib["w_mm"]) / float(calib["pixel_pitch_mm"])
    W, H = calib["image_size_px"]
    cx, cy = calib.get("principal_point_px") or ((W - 1) / 2.0, (H - 1) / 2.0)
    return np.array([[F, 0.0, cx], [0.0, F, cy], [0.0, 0.0, 1.0]])


def _dist(calib: dict) -> np.ndarray:
    from renderer.cameras.distortion import BrownConrady

    c = tuple((calib.get("distortion") or {}).get("coefficients") or ())
    return np.array(BrownConrady(c).to_config()["coefficients"], dtype=np.float64)  # OpenCV's 5 or 8


def opencv_note(calib: dict) -> str:
    """What this calibration holds that OpenCV's camera model cannot represent ('' if nothing)."""
    parts = []
    th = calib.get("theta_F_deg")
    if th is not None and abs(th) > 1e-9:
        parts.append(f"the lens is tilted (plane of focus tilted by theta_F = {th:.4g} deg, lens tilt theta_L = "
                     f"{calib.get('theta_L_deg')} deg): OpenCV has no tilted-lens model (its tilted-sensor tau is "
                     "a different geometry and is 0 here); the projection of corners is still exact, the "
                     "tilted depth of field is not represented")
    if calib.get("U_mm") is not None or calib.get("d_mm") is not None:
        parts.append(f"the blur model (focus distance U = {calib.get('U_mm')} mm, aperture d = "
                     f"{calib.get('d_mm')} mm) is not represented")
    return "; ".join(parts)


def write_opencv(calib: dict, path: str) -> None:
    """Write an OpenCV FileStorage (YAML/XML/JSON by extension) of a CALIB.json dict.

    Nodes: camera_matrix (3×3), distortion_coefficients (1×5 or 1×8), image_width, image_height, rvecs and
    tvecs (V×3, one row per view, tvec in mm), image names, rms_reprojection_px (per corner, OpenCV's
    definition), tiltfit_note.
    """
    import cv2

    fs = cv2.FileStorage(path, cv2.FILE_STORAGE_WRITE)
    if not fs.isOpened():
        raise ExportError(f"{path}: cannot write")
    try:
        W, H = calib["image_size_px"]
        fs.write("image_width", int(W))
        fs.write("image_height", int(H))
        fs.write("camera_matrix", _K(calib))
        fs.write("distortion_coefficients", _dist(calib).reshape(1, -1))
        views = calib.get("views") or []
        if views:
            rv = matrix_to_axis_angle(np.array([v["R"] for v in views], dtype=np.float64)).numpy()
            tv = np.array([v["T_mm"] for v in views], dtype=np.float64)
            fs.write("rvecs", rv)
            fs.write("tvecs", tv)
            fs.write("images", "; ".join(os.path.basename(str(v.get("image", ""))) for v in views))
        if calib.get("rms_reprojection_px") is not None:
            fs.write("rms_reprojection_px", float(calib["rms_reprojection_px"]))
        fs.write("pixel_pitch_mm", float(calib["pixel_pitch_mm"]))
        fs.write("tiltfit_note", opencv_note(calib) or "the calibration is fully represented")
    finally:
        fs.release()


def read_opencv(path: str, pixel_pitch_mm: float | None = None) -> dict:
    """Read an OpenCV FileStorage camera file into a CALIB.json-like dict (the start of a calibration).

    Needs camera_matrix and image_width/image_height; distortion_coefficients optional. fx and fy must agree
    within 1 % (our pixels are square; their mean is used). The pixel pitch comes from the file
    (`pixel_pitch_mm`, written by `write_opencv`) or the argument.

    Raises:
        ExportError: naming the file and the missing or malformed node.
    """
    import cv2

    if not os.path.isfile(path):
        raise ExportError(f"{path}: no such file")
    try:
        fs = cv2.FileStorage(path, cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError):  # a parse error surfaces as either
        raise ExportError(f"{path}: not an OpenCV FileStorage file") from None
    if not fs.isOpened():
        raise ExportError(f"{path}: not an OpenCV FileStorage file")
    try:
        K = fs.getNode("camera_matrix").mat()
        if K is None or K.shape != (3, 3):
            raise ExportError(f"{path}: camera_matrix: missing or not 3×3")
        size = [fs.getNode("image_width").real(), fs.getNode("image_height").real()]
        if not all(s > 0 for s in size):
            raise ExportError(f"{path}: image_width, image_height: missing")
        d = fs.getNode("distortion_coefficients").mat()
        d = [] if d is None else [float(v) for v in d.ravel()]
        if len(d) > 8:
            if any(d[8:]):
                raise ExportError(f"{path}: distortion_coefficients: thin-prism or tilted-sensor terms (s1..s4, "
                                  "tau) are not supported")
            d = d[:8]
        p_node = fs.getNode("pixel_pitch_mm")
        pitch = p_node.real() if not p_node.empty() else pixel_pitch_mm
        rv, tv = fs.getNode("rvecs").mat(), fs.getNode("tvecs").mat()
    finally:
        fs.release()
    if not pitch or not pitch > 0:
        raise ExportError(f"{path}: pixel_pitch_mm: not in the file; give it as the pixel_pitch_mm argument")
    fx, fy = float(K[0, 0]), float(K[1, 1])
    if not (fx > 0 and fy > 0) or abs(fx / fy - 1) > 0.01:
        raise ExportError(f"{path}: camera_matrix: fx = {fx:g} and fy = {fy:g} differ by more than 1 % "
                          "(tiltfit models square pixels)")
    out = {"pixel_pitch_mm": float(pitch), "image_size_px": [int(size[0]), int(size[1])],
           "principal_point_px": [float(K[0, 2]), float(K[1, 2])], "w_mm": 0.5 * (fx + fy) * float(pitch),
           "U_mm": None, "d_mm": None, "theta_F_deg": 0.0,
           "distortion": {"model": "brown_conrady", "coefficients": d or [0.0]},
           "undetermined": ["U_mm", "d_mm"], "source": os.path.abspath(path)}
    if rv is not None and tv is not None and rv.shape[0] == tv.shape[0] and rv.size and rv.shape[-1] == 3:
        out["views"] = [{"R": axis_angle_to_matrix(torch.tensor(r, dtype=torch.float64)).tolist(),
                         "T_mm": [float(x) for x in t.ravel()]} for r, t in zip(rv.reshape(-1, 3), tv.reshape(-1, 3))]
    return out


def is_opencv_file(path: str) -> bool:
    """True for .yml/.yaml/.xml files, or a file that starts like an OpenCV FileStorage."""
    ext = os.path.splitext(path)[1].lower()
    if ext in (".yml", ".yaml", ".xml"):
        return True
    try:
        with open(path, "rb") as f:
            head = f.read(64)
    except OSError:
        return False
    return head.startswith(b"%YAML") or head.startswith(b"<?xml")


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
