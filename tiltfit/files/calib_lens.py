"""The lens of a calibration file's content: the one place a CALIB.json-like dict becomes a `renderer.Lens`.

`lens_from_calib(data)` is used by `tiltfit.files.calibrated.Calibration` (rendering, projecting a calibration) and by
`tiltfit.uncertainty.covariance` (projection σ, `tiltfit compare`); it imports nothing else of tiltfit, so both can use it.
"""
from __future__ import annotations

import math

from renderer import Lens, Sensor

#: U for the geometry of a tilted lens whose file has no focus distance (an OpenCV file's τ gives θL only): any
#: finite U with the θF of that θL projects the same; with d = 0 it does not blur either.
GEOMETRY_U_MM = 600.0


def lens_from_calib(data: dict) -> tuple[Lens, bool]:
    """(the calibrated `Lens` with its sensor, whether U and d come from the file).

    Where U or d is undetermined (null) the lens renders sharp: d = 0, and U at infinity, or `GEOMETRY_U_MM`
    for a tilted lens (θL or θF given), whose projection does not depend on U once θL is fixed. A file giving θL
    but not θF (OpenCV's tilted model) gets the θF of that θL at U."""
    from renderer.cameras import optics

    U, d = data.get("U_mm"), data.get("d_mm")
    blur_known = U is not None and d is not None
    w = float(data["w_mm"])
    tilted = bool(data.get("theta_F_deg") or data.get("theta_L_deg"))
    if not blur_known:
        U, d = (GEOMETRY_U_MM if tilted else math.inf), 0.0
    theta_F = data.get("theta_F_deg")
    if theta_F is not None:
        theta_F = math.radians(theta_F)
    elif data.get("theta_L_deg"):
        theta_F = float(optics.theta_F_from_theta_L(math.radians(data["theta_L_deg"]), w, float(U)))
    else:
        theta_F = 0.0
    coefficients = (data.get("distortion") or {}).get("coefficients") or None
    W, H = (int(v) for v in data["image_size_px"])
    pp = data.get("principal_point_px")
    lens = Lens(w, float(U), float(d), float(theta_F), Sensor(W, H, float(data["pixel_pitch_mm"])),
                None if pp is None else (float(pp[0]), float(pp[1])),
                None if coefficients is None else tuple(float(c) for c in coefficients),
                math.radians(data.get("tilt_axis_deg") or 0.0), data.get("distortion_centre") or "sensor")
    return lens, blur_known
