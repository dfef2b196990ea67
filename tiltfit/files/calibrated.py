"""A calibration read once: the lens, the views' poses and the target, from any calibration file.

`Calibration.read(path)` takes a CALIB.json (`tiltfit calibrate`), an OpenCV FileStorage camera file (the
14-coefficient tilted model included: τx, τy become the lens tilt with its distortion about the lens axis) or an
mrcal `.cameramodel`, validates it once and gives:

- `lens`: the one `renderer.Lens` (w, U, d, θF, tilt axis φ, sensor, principal point, distortion and its
  centre), plain numbers, for rendering and projecting;
- `pose(view)`: (R, T) of a view, X_cam = R · X_target + T (mm), the view named by index or image name;
- `camera(view)`: the renderer's `ThinLensCamera` of that view (the calibrated distortion and defocus), at the
  file's image size or scaled to another of the same aspect;
- `target` (the target file stored in CALIB.json, or None) and `board_points_mm` (a fitted board's points).

Where the file cannot say how the lens blurs (U or d undetermined, or not in a camera file from another tool), the
lens renders sharp: a pinhole aperture (d = 0; `tiltfit.files.calib_lens`). The blur of a real photo is then not
reproduced, and `blur_known` says so.

Scene files use it through the `calibrated` camera (`tiltfit.files.scene_plugins`):
    {"type": "calibrated", "file": "calib.json", "view": 0}
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np

from renderer import Lens


class CalibrationError(ValueError):
    """A calibration file that cannot be used; the message is one line naming the file and the field."""


class PoseError(CalibrationError):
    """A pose of one's own that is not one (`checked_pose`): `field` is "R" or "T_mm", `reason` what is wrong."""

    def __init__(self, path: str, field: str, reason: str):
        super().__init__(f"{path}: {field}: {reason}")
        self.field, self.reason = field, reason


#: A pose of one's own (`Calibration.camera`'s R): R · Rᵀ within this of the identity (as CALIB.json's views).
ROTATION_TOLERANCE = 1e-6
#: The largest |T| coordinate (mm) of a pose of one's own (as CALIB.json's views: `tiltfit.files.calib`).
MAX_TRANSLATION_MM = 1e9


def checked_pose(R, T_mm, path: str = "<calibration>") -> tuple[np.ndarray, np.ndarray]:
    """(R (3, 3), T (3,)) as float64 after checking them: R a rotation (rows; orthonormal within
    `ROTATION_TOLERANCE`, determinant +1), T three finite numbers within ±`MAX_TRANSLATION_MM`.

    Raises:
        PoseError: one line naming `path` and R or T_mm.
    """
    def numbers(value) -> np.ndarray | None:
        flat = np.asarray(value, dtype=object).ravel() if isinstance(value, (list, tuple, np.ndarray)) else ()
        if not len(flat) or any(isinstance(v, (bool, np.bool_, str, bytes, dict, list)) for v in flat):
            return None
        try:
            a = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError, OverflowError):
            return None
        return a if np.isfinite(a).all() else None

    Rm = numbers(R)
    with np.errstate(all="ignore"):
        rotation = Rm is not None and Rm.shape == (3, 3) and bool(
            np.abs(Rm @ Rm.T - np.eye(3)).max() < ROTATION_TOLERANCE and np.linalg.det(Rm) > 0)
    if not rotation:
        raise PoseError(path, "R", f"expected a 3x3 rotation matrix (rows; orthonormal, determinant +1), got "
                                   f"{str(R)[:80]}")
    T = numbers(T_mm)
    if T is None or T.shape != (3,) or np.abs(T).max() > MAX_TRANSLATION_MM:
        raise PoseError(path, "T_mm", f"expected 3 finite numbers within ±{MAX_TRANSLATION_MM:g} mm, got "
                                      f"{str(T_mm)[:80]}")
    return Rm, T


def read_calibration_dict(path: str, pixel_pitch_mm: float | None = None) -> dict:
    """The validated CALIB.json-like dict of any calibration file (CALIB.json, OpenCV FileStorage, mrcal),
    chosen by its content. `pixel_pitch_mm` is needed for OpenCV and mrcal files that do not state it.

    Raises:
        ValueError (CalibFileError, ExportError): one line naming the file and the field.
    """
    from tiltfit.files.calib import read_calib, validate_calib
    from tiltfit.files.mrcal_file import is_mrcal_file, read_mrcal
    from tiltfit.files.opencv_file import is_opencv_file, read_opencv

    path = os.fspath(path)
    if not os.path.exists(path):
        raise CalibrationError(f"{path}: no such file")
    if os.path.isdir(path):
        raise CalibrationError(f"{path}: is a folder, not a calibration file")
    if is_mrcal_file(path):
        return validate_calib(path, read_mrcal(path, pixel_pitch_mm))
    if is_opencv_file(path):
        return validate_calib(path, read_opencv(path, pixel_pitch_mm))
    return read_calib(path)


@dataclass(frozen=True)
class Calibration:
    """A calibration file's content as one object (see the module docstring).

    Attributes:
        path: the file it was read from.
        data: the validated CALIB.json-like dict.
        lens: the calibrated `renderer.Lens` with its sensor (mm).
        blur_known: whether U and d come from the calibration (else the lens renders sharp).
        result: the fit (`tiltfit.calibrate.fit.FitResult`) where the calibration was just made, else None.
        held_out: {"rms_px", "folds", ...} of the k-fold held-out error where computed, else None.
    """

    path: str
    data: dict = field(repr=False)
    lens: Lens
    blur_known: bool
    result: object = field(default=None, repr=False, compare=False)
    held_out: dict | None = field(default=None, repr=False, compare=False)

    @classmethod
    def read(cls, path, pixel_pitch_mm: float | None = None) -> "Calibration":
        """Read and validate `path` (CALIB.json, OpenCV FileStorage or mrcal; see the module docstring)."""
        path = os.fspath(path)
        return cls.from_dict(read_calibration_dict(path, pixel_pitch_mm), path)

    @classmethod
    def from_dict(cls, data: dict, path: str = "<calibration>", result=None,
                  held_out: dict | None = None) -> "Calibration":
        """The Calibration of an already validated CALIB.json dict (`tiltfit.files.calib.validate_calib`), or of a
        fit just made (`tiltfit.calibrate_photos`: its `tiltfit.calibrate.fit.FitResult` as `result`, the k-fold held-out
        error as `held_out`)."""
        from tiltfit.files.calib_lens import lens_from_calib

        lens, blur_known = lens_from_calib(data)
        return cls(path, data, lens, blur_known, result, held_out)

    # --- what people read first --------------------------------------------------------------------------
    @property
    def focal_px(self) -> float:
        """Focal length w / pixel pitch (px)."""
        return float(self.lens.focal_px)

    @property
    def sigma_focal_px(self) -> float | None:
        """One-σ of the focal length (px): the file's σ of w over the pixel pitch, or None where it has none."""
        s = (self.data.get("sigma") or {}).get("w_mm")
        return None if s is None else float(s) / self.lens.sensor.pixel_pitch

    @property
    def principal_point_px(self) -> tuple[float, float]:
        """(cx, cy) in pixels (pixel centres at integers)."""
        cx, cy = self.lens.center_px
        return float(cx), float(cy)

    @property
    def rms_px(self) -> float | None:
        """Reprojection RMS per corner over all views (px; OpenCV's `calibrateCamera` definition), or None."""
        rms = self.data.get("rms_reprojection_px")
        return None if rms is None else float(rms)

    def save(self, path: str) -> None:
        """Write CALIB.json atomically (read by `tiltfit report`, `tiltfit export`, `--init` and the `calibrated`
        scene camera)."""
        from tiltfit.files.calib import write_calib

        write_calib(path, self.data)

    # --- views -------------------------------------------------------------------------------------------
    @property
    def views(self) -> list[dict]:
        """The file's views (CALIB.json `views`: image, R, T_mm, ...), in order."""
        return list(self.data.get("views") or [])

    @property
    def image_size_px(self) -> tuple[int, int]:
        """(W, H) of the calibrated images."""
        return self.lens.sensor.size_px

    def view_index(self, view) -> int:
        """The index of `view`: an index (negative counts from the end) or an image name (the file name is
        enough); CalibrationError naming `view` otherwise."""
        views = self.views
        if not views:
            raise CalibrationError(f"{self.path}: views: the file has no views; give the camera's pose (R, T_mm)")
        if isinstance(view, (int, np.integer)) and not isinstance(view, bool):
            if not -len(views) <= int(view) < len(views):
                raise CalibrationError(f"{self.path}: view: expected 0 to {len(views) - 1}, got {int(view)}")
            return int(view) % len(views)
        if isinstance(view, str):
            names = [str(v.get("image", "")) for v in views]
            for i, name in enumerate(names):
                if view in (name, os.path.basename(name)):
                    return i
            shown = ", ".join(os.path.basename(n) for n in names[:4]) + (", ..." if len(names) > 4 else "")
            raise CalibrationError(f"{self.path}: view: no view of image {view!r} (views: {shown})")
        raise CalibrationError(f"{self.path}: view: expected a view index or an image name, got {view!r}")

    def pose(self, view=0) -> tuple[np.ndarray, np.ndarray]:
        """(R (3, 3), T (3,) mm) of a view: X_cam = R · X_target + T."""
        v = self.views[self.view_index(view)]
        return np.asarray(v["R"], dtype=np.float64), np.asarray(v["T_mm"], dtype=np.float64)

    # --- rendering ---------------------------------------------------------------------------------------
    def lens_for_image(self, image_size_px=None) -> Lens:
        """The lens with its sensor resampled to `image_size_px` (W, H) (same aspect ratio: the same field of
        view and principal point, coarser or finer pixels), or the calibrated one for None."""
        if image_size_px is None:
            return self.lens
        size = tuple(image_size_px) if isinstance(image_size_px, (tuple, list)) else ()
        if len(size) != 2 or not all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in size):
            raise CalibrationError(f"{self.path}: image size: expected two integers (W, H), got {image_size_px!r}")
        W, H = (int(v) for v in size)
        W0, H0 = self.image_size_px
        if (W, H) == (W0, H0):
            return self.lens
        if W < 1 or H < 1 or abs(W / H - W0 / H0) > 0.01 * W0 / H0:
            raise CalibrationError(f"{self.path}: image size {W}x{H}: expected the calibration's aspect ratio "
                                   f"({W0}x{H0}, or a scaled copy of it)")
        return self.lens.resampled(W, H)

    def camera(self, view=0, image_size_px=None, R=None, T_mm=None):
        """The renderer's camera of a view (`renderer.cameras.ThinLensCamera`, lengths in mm): the calibrated
        lens, distortion (about its centre) and defocus, the view's pose or the given (R, T_mm)."""
        from renderer.cameras import ThinLensCamera

        if (R is None) != (T_mm is None):
            raise CalibrationError(f"{self.path}: give both R and T_mm for a pose, or neither")
        if R is None:
            R, T_mm = self.pose(view)
        else:
            R, T_mm = checked_pose(R, T_mm, self.path)
        import torch

        return ThinLensCamera.from_calibration(self.lens_for_image(image_size_px),
                                               torch.as_tensor(np.asarray(R, dtype=np.float64)),
                                               torch.as_tensor(np.asarray(T_mm, dtype=np.float64)))

    # --- the target --------------------------------------------------------------------------------------
    @property
    def target(self):
        """The `tiltfit.target.layout.Target` stored in the calibration (CALIB.json `target`), or None."""
        from tiltfit.target.layout import target_from_dict

        t = self.data.get("target")
        return None if not isinstance(t, dict) else target_from_dict(t, f"{self.path}: target")

    @property
    def board_points_mm(self) -> np.ndarray | None:
        """(N, 3) the fitted board's feature points (mm, target frame), or None for a flat board."""
        from tiltfit.files.export import board_points_mm

        return board_points_mm(self.data)

    def project(self, points_mm, view=0) -> np.ndarray:
        """(N, 2) pixel positions of target-frame points (N, 3) in a view, through the full lens (tilt,
        distortion about its centre)."""
        R, T = self.pose(view)
        points = np.asarray(points_mm, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3:
            raise CalibrationError(f"{self.path}: project: expected (N, 3) target points (mm), got shape "
                                   f"{points.shape}")
        p_cam = points @ R.T + T
        return np.asarray(self.lens.project(p_cam), dtype=np.float64)
