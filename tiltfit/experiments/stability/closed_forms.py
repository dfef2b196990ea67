"""The closed forms beside the stability measurements: coverage of the accumulation buffer (c), the
inverted perspective's singular depth and magnification (d), the paper's two-stage θL (b), and the bias of blur
read off sRGB values (e). Each is checked against the camera or fit it describes in tests/tiltfit/test_stability.py."""
from __future__ import annotations

import math

import numpy as np
import torch
from renderer.cameras import optics

from .common import D_MM, U0_MM, W_MM

def first_row_lost_theta_F(w: float, sensor_height: float, principal_offset: float = 0.0) -> float:
    """θF (radians, > 0) at which the accumulation-buffer camera loses its first pixel row.

    A pixel has a focus point in front of the lens where D = w − y_s tan θF > 0 (y_s its screen height at
    distance w, y down). The largest y_s on the image is at its bottom edge, y_s = h/2 − offset, so the first
    row goes at tan θF = w / (h/2 − offset). Negative θF lose the top row at the mirrored angle.

    Args:
        w: lens centre to sensor; sensor_height: h, the image height at distance w (same unit).
        principal_offset: principal point below the image centre, same unit [0].
    """
    return math.atan2(w, sensor_height / 2.0 - principal_offset)


def coverage_closed_form(theta_F: float, w: float, sensor_height: float) -> float:
    """Fraction of the image the accumulation buffer can render: the part of y_s ∈ [−h/2, h/2] with
    y_s tan θF < w (principal point at the centre; θF radians, |θF| < π/2)."""
    t = abs(math.tan(theta_F))
    if t == 0.0:
        return 1.0
    return float(min(1.0, max(0.0, 0.5 + w / (t * sensor_height))))


def singular_depth(alpha: float, p3: float) -> float:
    """a3* = α p3 / (α − 1): the depth where eq. (4)'s denominator α (p3 − a3) + a3 vanishes (α ≠ 1)."""
    if alpha == 1.0:
        raise ValueError("alpha: the parallel projection (α = 1) has no singular depth")
    return alpha * p3 / (alpha - 1.0)


def inverted_magnification(alpha: float, p3: float, q3: float, a3) -> np.ndarray:
    """Screen size per unit object size, q3 / (α (p3 − a3) + a3) (eq. (4)); ±inf at the singular depth.

    Near it, a3 = a3* − ε, this is q3 / ((α − 1) ε): it blows up as 1/ε and changes sign across it
    (points beyond a3* are imaged point-reflected).
    """
    den = alpha * (p3 - np.asarray(a3, dtype=np.float64)) + np.asarray(a3, dtype=np.float64)
    with np.errstate(divide="ignore"):
        return np.where(den != 0, q3 / np.where(den != 0, den, 1.0), np.inf)


def two_stage_prediction(p_cam, theta_L: float, w_mm: float = W_MM, U_mm: float = U0_MM,
                         d_mm: float = D_MM) -> dict:
    """What the paper's stage 2 returns for a thin lens tilted about its centre, predicted from the physics.

    The truth: the lens (f = U w / (U + w) from the untilted state) tilted by θL about its centre has
    U' = f w / (w cos θL − f) (hinge rule) and tan θF = (U' + w) tan θL / w (Scheimpflug), and the blur of a
    point is the exact spot (`renderer.cameras.optics.blur_diameter_exact`). Stage 2 holds w, U, d at the untilted
    values and fits θF with the paper's eq. (4); with the poses known from the corners this is the 1-D least
    squares problem min over θF of Σ (b_eq4(p; w, U, d, θF) − b_exact(p))², solved here on a 0.1° grid
    refined by golden section. θL then follows from eq. (1) with f = U w cos θL / (U + w) at the fitted
    state (as `LensCamera.theta_L_paper`).

    Args:
        p_cam: (N, 3) camera-frame points where blur is observed, mm.
        theta_L: the true lens tilt, radians.
        w_mm, U_mm, d_mm: the untilted lens (what stage 1 measures).
    Returns:
        dict (degrees, mm): theta_L_true, U_true, theta_F_true, theta_F_stage2, theta_L_stage2 (eq. (1), the
        prediction), theta_L_formula_only (eq. (1) applied to the true θF and U: the bias of the formula
        alone), and error = theta_L_stage2 − theta_L_true.
    """
    p = torch.as_tensor(np.asarray(p_cam, dtype=np.float64))
    f = float(optics.focal_length(w_mm, U_mm))
    U1 = float(optics.focus_distance_tilted(w_mm, f, theta_L))
    tF1 = float(optics.theta_F_from_theta_L(theta_L, w_mm, U1))
    b_true = optics.blur_diameter_exact(p, w_mm, U1, d_mm, tF1)
    y, z = p[:, 1], p[:, 2]

    def rss(tf):
        tf = torch.as_tensor(tf, dtype=torch.float64)
        b = optics.blur_diameter_paper(y, z, w_mm, U_mm, d_mm, tf[..., None])
        return ((b - b_true) ** 2).sum(-1)

    grid = torch.deg2rad(torch.arange(-89.0, 89.05, 0.1, dtype=torch.float64))
    i = int(torch.argmin(rss(grid)))
    lo, hi = float(grid[max(i - 1, 0)]), float(grid[min(i + 1, grid.numel() - 1)])
    g = (math.sqrt(5) - 1) / 2
    for _ in range(60):
        a, b = hi - g * (hi - lo), lo + g * (hi - lo)
        if float(rss(a)) < float(rss(b)):
            hi = b
        else:
            lo = a
    tF2 = 0.5 * (lo + hi)
    tL2_exact = float(optics.theta_L_from_theta_F(tF2, w_mm, U_mm))
    f2 = float(optics.focal_length(w_mm, U_mm, tL2_exact))
    tL2 = float(optics.theta_L_paper(tF2, f2, U_mm))
    f1 = float(optics.focal_length(w_mm, U1, theta_L))
    return {"theta_L_true": math.degrees(theta_L), "U_true": U1, "theta_F_true": math.degrees(tF1),
            "theta_F_stage2": math.degrees(tF2), "theta_L_stage2": math.degrees(tL2),
            "theta_L_formula_only": math.degrees(float(optics.theta_L_paper(tF1, f1, U1))),
            "error": math.degrees(tL2 - theta_L)}


def srgb_blur_bias(b_px: float, dark: float = 0.05, white: float = 0.8, angle_deg: float = 0.0) -> float:
    """Predicted relative bias b_fit / b − 1 of a blur diameter measured on sRGB-encoded values.

    One straight edge between linear levels `dark` and `white`, blurred by a disc of diameter b and
    integrated over pixels (`tiltfit.detect.blur.pixel_esf`, edge at `angle_deg` to the pixel grid), is encoded
    to sRGB and then fitted, as `tiltfit.detect.blur` fits linear data, with the same pixel-integrated disc model
    (free dark level, contrast, edge offset and diameter). The encoding is concave, so it steepens the dark
    side of the edge and flattens the bright one: at pixel-sized blur the bent ramp reads wider (b is
    overestimated); at large blur the bend is symmetric enough that b is slightly underestimated.

    Args:
        b_px: true blur diameter, pixels (> 0).
        dark, white: linear levels on either side of the edge.
    Returns:
        b_fit / b − 1 (dimensionless).
    """
    from camio.files import linear_to_srgb

    from tiltfit.detect.blur import pixel_esf
    from ...solve import LMOptions, least_squares

    if not b_px > 0:
        raise ValueError(f"b_px: expected a positive blur diameter, got {b_px}")
    r = b_px / 2.0
    a = math.radians(angle_deg)
    wa, wb = (torch.tensor(v, dtype=torch.float64) for v in sorted((abs(math.cos(a)), abs(math.sin(a))),
                                                                   reverse=True))
    half = 2.0 * r + 2.0
    d = torch.linspace(-half, half, 801, dtype=torch.float64)
    E = pixel_esf(d, torch.tensor(r, dtype=torch.float64), wa, wb)
    y = torch.as_tensor(linear_to_srgb((dark + (white - dark) * E).numpy()))
    # Levenberg–Marquardt on (level, contrast, edge offset, radius), started at the undistorted edge.
    lo, hi = float(y.min()), float(y.max())
    theta = torch.tensor([lo, hi - lo, 0.0, r], dtype=torch.float64)

    def residuals(th):
        return th[0] + th[1] * pixel_esf(d - th[2], th[3].clamp_min(1e-3), wa, wb) - y

    def jacobian(th):
        e, de_dd, de_dr = pixel_esf(d - th[2], th[3].clamp_min(1e-3), wa, wb, with_derivatives=True)
        return torch.stack([torch.ones_like(e), e, -th[1] * de_dd, th[1] * de_dr], -1)

    # noise-free residuals: converge on the step (xtol), not on a decrement scaled for residuals in units of σ
    fit = least_squares(residuals, theta, LMOptions(decrement_tol=0.0, ftol=1e-15, xtol=1e-12), jacobian)
    theta = fit.x
    return float(theta[3]) / r - 1.0
