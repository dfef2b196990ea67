"""mrcal camera models (https://mrcal.secretsauce.net): a `.cameramodel` is a Python dict literal, `#` comments
allowed. `write_mrcal` writes LENSMODEL_OPENCV8; `read_mrcal` reads LENSMODEL_PINHOLE or OPENCV4/5/8 (for `--init`)."""
from __future__ import annotations

import math
import os

import numpy as np
from camio.checks import is_finite_number

from .export import (FOCUS_NODES, MAX_IMAGE_SIDE, ExportError, add_focus, camera_matrix, check_focal,
                     check_focal_length_mm, distortion_coefficients, focus_value, opencv_note)


MRCAL_EXTENSION = ".cameramodel"
_MRCAL_PITCH = "# tiltfit pixel_pitch_mm = "
_MRCAL_MODELS = {"LENSMODEL_PINHOLE": 0, "LENSMODEL_OPENCV4": 4, "LENSMODEL_OPENCV5": 5, "LENSMODEL_OPENCV8": 8}


def mrcal_text(calib: dict) -> str:
    """An mrcal `.cameramodel` of a CALIB.json dict: LENSMODEL_OPENCV8 (fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5,
    k6: OpenCV's order and pixel convention, which are mrcal's), the camera at the reference frame. A tilted
    lens projects its corners exactly as this model (the chief ray meets a sensor perpendicular to the axis);
    what mrcal cannot hold (focus, aperture, the tilted plane of focus) is said in a comment line."""
    K, d = camera_matrix(calib), np.zeros(8)
    coeffs = distortion_coefficients(calib)
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
            "".join(f"# tiltfit {key} = {float(calib[key])!r}\n" for key, _ in FOCUS_NODES
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
        for key, _ in FOCUS_NODES:
            head = f"# tiltfit {key} = "
            if line.startswith(head):
                try:
                    value = float(line[len(head):])
                except ValueError:
                    value = line[len(head):].strip()
                focus[key] = focus_value(path, key, value)
    fx, fy, cx, cy = (float(v) for v in intr[:4])
    check_focal(path, "intrinsics", fx, fy)
    out = {"pixel_pitch_mm": float(pitch), "image_size_px": [int(size[0]), int(size[1])],
           "principal_point_px": [cx, cy], "w_mm": 0.5 * (fx + fy) * float(pitch),
           "U_mm": None, "d_mm": None, "theta_F_deg": 0.0,
           "distortion": {"model": "brown_conrady", "coefficients": [float(v) for v in intr[4:]] or [0.0]},
           "undetermined": ["U_mm", "d_mm"], "source": os.path.abspath(path)}
    check_focal_length_mm(path, "intrinsics", out["w_mm"])
    add_focus(path, out, focus, {key: f"# tiltfit {key}" for key, _ in FOCUS_NODES})
    return out


def is_mrcal_file(path: str) -> bool:
    return path.lower().endswith(MRCAL_EXTENSION)
