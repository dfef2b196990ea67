"""The pinhole projection, written once: camera-frame points to pixels and back (forward and inverse side by side).

A point p = (x, y, z) in the camera frame (x right, y down, z forward) lands on the pixel

    uv = c + f ⊙ D(x / z, y / z)

where (x/z, y/z) are its ideal normalised image coordinates, D the lens distortion (Brown–Conrady in OpenCV's
order, `distortion.distort`; the identity without coefficients), f = (f_x, f_y) the focal length in pixels
(distance of the screen or sensor divided by the pixel pitch along each axis) and c = (c_x, c_y) the principal
point in pixels ((0, 0) is the centre of the top-left pixel). It is the chief-ray projection of every camera
with a centre of projection: the pinhole (screen at q3), the thin lens (sensor at w, tilted or not), the
calibration model `LensCamera` and tiltfit's synthetic observations all call `project_pinhole`.
"""
from __future__ import annotations

import numpy as np
import torch

from .distortion import distort_about_axis


def image_centre_px(width_px, height_px) -> tuple[float, float]:
    """The centre of a W × H image, ((W − 1)/2, (H − 1)/2) px (pixel (0, 0) is the centre of the top-left pixel):
    the default principal point. Written once here (tests/test_one_lens.py scans for copies)."""
    return (width_px - 1) / 2.0, (height_px - 1) / 2.0


def camera_matrix(focal_px, principal_point_px) -> np.ndarray:
    """(3, 3) OpenCV's camera matrix K = [[f, 0, cx], [0, f, cy], [0, 0, 1]] (pixels from normalised coordinates)
    of a focal length f (px, square pixels) and principal point (cx, cy) (px), float64."""
    cx, cy = principal_point_px
    return np.array([[focal_px, 0.0, cx], [0.0, focal_px, cy], [0.0, 0.0, 1.0]], dtype=np.float64)


def _as_pair(v, like):
    """A focal length or principal point as something that broadcasts against (..., 2) coordinates `like`:
    a scalar (number or 0-dim tensor) as it is, a pair (tuple, list) as a (2,) array of `like`'s kind (tensors
    in it keep their graph), an array (..., 2) as it is."""
    if isinstance(v, (tuple, list)):
        if isinstance(like, np.ndarray):
            return np.asarray(v, dtype=np.float64)
        if any(isinstance(a, torch.Tensor) for a in v):
            return torch.stack([torch.as_tensor(a, dtype=like.dtype, device=like.device) for a in v])
        return torch.tensor(v, dtype=like.dtype, device=like.device)
    return v


def pixels_from_normalised(xy: torch.Tensor, focal_px, principal_point_px) -> torch.Tensor:
    """(..., 2) normalised image coordinates (x/z, y/z), already distorted -> (..., 2) pixels, uv = c + f ⊙ xy.

    Args:
        xy: (..., 2) normalised coordinates, dimensionless.
        focal_px: f (a number or 0-dim tensor) or (f_x, f_y) (a pair, or a tensor (..., 2)), pixels.
        principal_point_px: (c_x, c_y) (a pair or a tensor (..., 2)), pixels.
    Returns:
        (..., 2) pixels; gradients reach tensor focal lengths and principal points. A numpy `xy` gives numpy
        (the beam tracer's and tiltfit's numpy callers).
    """
    return xy * _as_pair(focal_px, xy) + _as_pair(principal_point_px, xy)


def normalised_from_pixels(uv_px: torch.Tensor, focal_px, principal_point_px) -> torch.Tensor:
    """Inverse of `pixels_from_normalised`: (..., 2) pixels -> (..., 2) normalised (distorted) coordinates."""
    return (uv_px - _as_pair(principal_point_px, uv_px)) / _as_pair(focal_px, uv_px)


def project_pinhole(p_cam: torch.Tensor, focal_px, principal_point_px, distortion=None,
                    camera_from_lens=None) -> torch.Tensor:
    """(..., 3) camera-frame points -> (..., 2) pixels: uv = c + f ⊙ D(x / z, y / z).

    Args:
        p_cam: (..., 3) points in the camera frame (x right, y down, z forward), any length unit; a tensor, or
            a numpy array when there is no distortion (the result is then numpy too).
        focal_px, principal_point_px: as in `pixels_from_normalised`.
        distortion: None (no distortion) or up to 8 Brown–Conrady coefficients (k1, k2, p1, p2, k3, k4, k5, k6)
            as a sequence or a tensor (differentiable).
        camera_from_lens: None (the distortion about the principal point) or the (3, 3) rotation of a tilted
            lens's frame: D applied about the lens axis (`distortion.distort_about_axis`).
    Returns:
        (..., 2) pixels. Points with z = 0 give inf/NaN; points behind the camera (z < 0) project through
        the centre like any other (callers mask them).
    """
    xy = p_cam[..., :2] / p_cam[..., 2:3]
    if distortion is not None:
        xy = distort_about_axis(xy, distortion, camera_from_lens)
    return pixels_from_normalised(xy, focal_px, principal_point_px)
