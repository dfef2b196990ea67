"""tiltfit's scene-file components for the renderer: the `calibrated` camera and the `target` shape.

The renderer finds them through the `renderer.scene.plugins` entry point (`renderer.scene.plugins`), so a scene file can
render what a calibrated camera saw:

    {"image": {"spp": 16},
     "camera": {"type": "calibrated", "file": "calib.json", "view": 3},
     "lights": [{"type": "point", "position": [0, 0, -800], "intensity": [6e5, 6e5, 6e5]}],
     "objects": [{"name": "board", "shape": {"type": "target", "file": "target.json"}}]}

`calibrated` camera keys:

| key | kind | default | meaning |
|---|---|---|---|
| `file` | str | required | CALIB.json, an OpenCV FileStorage file or an mrcal `.cameramodel` (beside the scene file) |
| `view` | int or str | 0 | the view whose pose is used: its index, or its image's name |
| `R`, `T_mm` | 3×3, vec3 | the view's | a pose of your own, X_cam = R · X_target + T (mm) |
| `pixel_pitch_mm` | float | from the file | for OpenCV and mrcal files that do not state it |

The image size defaults to the calibration's; a scene `image.width` (or `height`) of the same aspect ratio renders
the same view with coarser or finer pixels. Lengths are in mm and the world is the target's frame (X along the
board's columns, Y along its rows, Z = 0 on the board), as in the calibration.

`target` shape keys: `file` (a target file, or a CALIB.json whose `target` is used), `reflectance` [dark, light]
([0.04, 0.8]: toner on paper). It is the board with its margin, in the target frame: its squares (the target
file's edges), ChArUco markers and white margin, as exact edges at any distance (`renderer.scene.materials.GridTexture`);
an `inverted` print swaps the two reflectances. Unless the object's material gives a `color` or a `texture`, its
albedo is the print.
"""
from __future__ import annotations

import functools
import os

import numpy as np

from renderer import GridTexture
from renderer.cameras import register_camera
from renderer.core.params import Param, SceneError
from renderer.shapes import Rectangle, register_shape

#: Printed reflectances (dark toner, white paper) of a target shape without `reflectance`.
DEFAULT_REFLECTANCE = (0.04, 0.8)

CALIBRATED_PARAMS = [
    Param("file", "str", doc="calibration file: CALIB.json, OpenCV FileStorage or mrcal .cameramodel"),
    Param("view", "any", 0, "view index or image name whose pose is used"),
    Param("R", "any", None, "3x3 rotation camera_from_target (with T_mm: a pose of your own)"),
    Param("T_mm", "vec3", None, "translation, mm (with R)"),
    Param("pixel_pitch_mm", "float", None, "pixel pitch for files that do not state it, mm"),
]


@functools.lru_cache(maxsize=16)
def _calibration(path: str, mtime: float, pixel_pitch_mm):
    from tiltfit.files.calibrated import Calibration

    return Calibration.read(path, pixel_pitch_mm)


def _read(key: str, cfg: dict):
    from camio.checks import is_finite_number

    from tiltfit.files.calibrated import CalibrationError

    path, pitch = cfg.get("file"), cfg.get("pixel_pitch_mm")
    if not isinstance(path, str) or not path.strip():
        raise SceneError(f"{key}.file: expected the calibration file's name, got {path!r}")
    if pitch is not None and not (is_finite_number(pitch) and not isinstance(pitch, bool) and 0 < pitch <= 1e3):
        raise SceneError(f"{key}.pixel_pitch_mm: expected a positive number of mm (at most 1000), got {pitch!r}")
    try:
        mtime = os.path.getmtime(path) if os.path.exists(path) else 0.0
        return _calibration(os.path.abspath(path), mtime, None if pitch is None else float(pitch))
    except (CalibrationError, ValueError) as e:
        text = str(e)
        raise SceneError(f"{key}.file: {text if path in text or os.path.abspath(path) in text else f'{path}: {text}'}") \
            from None


#: The camera keys every camera has (`renderer.cameras.registry.POSE_PARAMS`) and their defaults: a calibrated
#: camera's pose is the view's (or R and T_mm), so any other value would be ignored, and is refused.
_UNUSED_POSE_KEYS = {"position": (0.0, 0.0, 0.0), "look_at": (0.0, 0.0, 1.0), "up": (0.0, -1.0, 0.0)}


class CalibratedCamera:
    """Builds the renderer's `ThinLensCamera` of a calibration's view (module docstring)."""

    @classmethod
    def image_size(cls, path: str, cfg: dict) -> tuple[int, int]:
        """(W, H) of the calibrated images."""
        return _read(path, cfg).image_size_px

    @classmethod
    def from_config(cls, path, cfg, transform, width, height):
        from tiltfit.files.calibrated import CalibrationError, PoseError, checked_pose

        cal = _read(path, cfg)
        for key, default in _UNUSED_POSE_KEYS.items():
            if tuple(cfg.get(key, default)) != default:
                raise SceneError(f"{path}.{key}: not used by a calibrated camera (its pose is the view's, or R and "
                                 "T_mm in the target's frame)")
        R, T = cfg.get("R"), cfg.get("T_mm")
        if (R is None) != (T is None):
            raise SceneError(f"{path}.{'T_mm' if T is None else 'R'}: missing (give both R and T_mm for a pose of "
                             "your own, or neither)")
        if R is not None:
            try:
                R, T = checked_pose(R, T, cal.path)
            except PoseError as e:
                raise SceneError(f"{path}.{e.field}: {e.reason}") from None
        try:
            cal.lens_for_image((width, height))
        except CalibrationError:
            W0, H0 = cal.image_size_px
            raise SceneError(f"image: {width}x{height} px: expected the aspect ratio of the calibration's {W0}x{H0} "
                             f"images ({cal.path}) within 1 %") from None
        try:
            return cal.camera(cfg.get("view", 0), (width, height), R, T)
        except CalibrationError as e:
            raise SceneError(f"{path}.{'view' if ': view:' in str(e) else 'file'}: {e}") from None
        except ValueError as e:
            raise SceneError(f"{path}: {e}") from None


TARGET_PARAMS = [
    Param("file", "str", doc="target file (or a CALIB.json holding one)"),
    Param("reflectance", "vec2", DEFAULT_REFLECTANCE, "[dark, light] reflectances of the print"),
]


def target_texture(target, reflectance=DEFAULT_REFLECTANCE) -> GridTexture:
    """The print of `target` (squares, ChArUco markers, margin) as a `GridTexture` over its extent, uv = target
    X, Y minus the extent's (x_min, y_min); palette (light, dark), swapped for an inverted print."""
    x0, y0, x1, y1 = target.extent_mm
    rects = np.asarray(target.dark_rectangles(), dtype=np.float64).reshape(-1, 4)
    xb = np.unique(np.concatenate([[x0, x1], target.x_edges, rects[:, 0], rects[:, 2]]))
    yb = np.unique(np.concatenate([[y0, y1], target.y_edges, rects[:, 1], rects[:, 3]]))
    xc, yc = (xb[:-1] + xb[1:]) / 2, (yb[:-1] + yb[1:]) / 2
    col = np.searchsorted(np.asarray(target.x_edges), xc) - 1  # cell column (−1 or n: the margin)
    row = np.searchsorted(np.asarray(target.y_edges), yc) - 1
    dark = target.is_dark(col[None, :], row[:, None])
    for rx0, ry0, rx1, ry1 in rects:
        i0, i1 = np.searchsorted(xb, [rx0, rx1])
        j0, j1 = np.searchsorted(yb, [ry0, ry1])
        dark[j0:j1, i0:i1] = True
    dark_r, light_r = (float(v) for v in reflectance)
    colors = ((light_r,) * 3, (dark_r,) * 3)
    if getattr(target, "inverted", False):
        colors = colors[::-1]
    return GridTexture(xb - x0, yb - y0, dark.astype(np.int64), colors, outside=0)


class TargetBoard(Rectangle):
    """The calibration target's board as a rectangle in the target frame, with its print as `texture`."""

    def __init__(self, target, reflectance=DEFAULT_REFLECTANCE):
        x0, y0, x1, y1 = target.extent_mm
        super().__init__(((x0 + x1) / 2, (y0 + y1) / 2, 0.0), (x1 - x0, y1 - y0))
        self.target = target
        self.texture = target_texture(target, reflectance)


def _load_target(path: str, key: str):
    from camio.checks import read_json

    from tiltfit.target.layout import TargetError, target_from_dict

    if not os.path.exists(path):
        raise SceneError(f"{key}.file: {path}: no such file")
    try:
        data = read_json(path, TargetError, "target file")
        if isinstance(data, dict) and "views" in data and "w_mm" in data:  # a CALIB.json
            if not isinstance(data.get("target"), dict):
                raise SceneError(f"{key}.file: {path}: target: the calibration holds no target; give the target "
                                 "file itself")
            return target_from_dict(data["target"], f"{path}: target")
        return target_from_dict(data, path)
    except ValueError as e:
        raise SceneError(f"{key}.file: {e}") from None


def _build_target(path: str, cfg: dict, base_dir: str):
    file = os.path.join(base_dir, os.path.expanduser(cfg["file"]))
    refl = cfg["reflectance"]
    if not all(0.0 <= float(r) <= 1.0 for r in refl):
        raise SceneError(f"{path}.reflectance: expected [dark, light] in [0, 1], got {list(refl)}")
    return TargetBoard(_load_target(file, path), refl)


def register() -> None:
    """The `renderer.scene.plugins` entry point: register the `calibrated` camera and the `target` shape."""
    register_camera("calibrated", CALIBRATED_PARAMS)(CalibratedCamera)
    register_shape("target", TARGET_PARAMS)(_build_target)
