"""The stored lens vector of `LensCamera` (`renderer.cameras.lens_model`): log w (w in mm), 1/U in dioptres, d in cm,
θF in radians, and their lengths.

This module is the one place a lens vector is read (by name or by position) and turned into lengths, or lengths and
their σ into stored values: every other module calls `lens_values`, `stored_from_lens` or `stored_lens_sigma`
(tests/test_one_lens.py scans for hand-written copies).
"""
from __future__ import annotations

import math

import torch

APERTURE_SCALE_MM = 10.0  # d_scaled is the aperture diameter in cm

#: The stored lens parameters in the order of a lens vector: log w (w in mm), 1/U in dioptres, d in cm, θF in radians.
LENS_PARAMETERS = ("log_w_mm", "inv_U_per_m", "d_scaled", "theta_F")


def w_from_stored(log_w_mm):
    """w in mm of the stored log w (a tensor keeps its graph; a number gives a float)."""
    return torch.exp(log_w_mm) if isinstance(log_w_mm, torch.Tensor) else math.exp(log_w_mm)


def U_from_stored(inv_U_per_m):
    """U in mm of the stored 1/U in dioptres (inf at 0, focus at infinity)."""
    if isinstance(inv_U_per_m, torch.Tensor):
        return 1000.0 / inv_U_per_m
    return math.inf if inv_U_per_m == 0 else 1000.0 / inv_U_per_m


def d_from_stored(d_scaled):
    """The aperture d in mm of the stored d_scaled (cm, sign free: d = |d_scaled| · 10 mm)."""
    return (d_scaled.abs() if isinstance(d_scaled, torch.Tensor) else abs(d_scaled)) * APERTURE_SCALE_MM


def lens_values(stored) -> tuple:
    """(w_mm, U_mm, d_mm, θF in radians) of stored lens parameters.

    Args:
        stored: a mapping by stored name (`LENS_PARAMETERS`: a module's parameters, a state dict), or a (4,) tensor
            or sequence in that order (a solver's lens block). Tensors keep their graph; numbers give floats.
    """
    if hasattr(stored, "keys"):
        log_w, inv_U, d_scaled, theta_F = (stored[n] for n in LENS_PARAMETERS)
    else:
        log_w, inv_U, d_scaled, theta_F = (stored[i] for i in range(len(LENS_PARAMETERS)))
    return w_from_stored(log_w), U_from_stored(inv_U), d_from_stored(d_scaled), theta_F


def stored_from_lens(w_mm=None, U_mm=None, d_mm=None, theta_F=None) -> dict:
    """The stored values (floats) of the lens values given (mm, radians; U = inf: focus at infinity), by stored name:
    the inverse of `lens_values`."""
    out = {}
    if w_mm is not None:
        out["log_w_mm"] = math.log(float(w_mm))
    if U_mm is not None:
        out["inv_U_per_m"] = 1000.0 / float(U_mm)
    if d_mm is not None:
        out["d_scaled"] = float(d_mm) / APERTURE_SCALE_MM
    if theta_F is not None:
        out["theta_F"] = float(theta_F)
    return out


def stored_lens_sigma(w_mm: float, U_mm: float, sigma: dict) -> dict:
    """One-σ of the stored lens parameters from physical ones, to first order: σ(log w) = σ_w / w,
    σ(1/U) = 1000 σ_U / U² (dioptres), σ(d_scaled) = σ_d / 10 mm, σ(θF) = σ_θF.

    Args:
        w_mm, U_mm: the lens's w and U (floats, mm).
        sigma: physical σ by CALIB.json name (w_mm, U_mm, d_mm, theta_F_deg); missing, None, 0 or non-finite ones are
            left out (and σ_U where U is infinite).
    Returns:
        {stored name: σ} for the σ given.
    """
    def get(key):
        v = sigma.get(key)
        return float(v) if isinstance(v, (int, float)) and math.isfinite(float(v)) and float(v) > 0 else None

    out = {}
    if get("w_mm") is not None:
        out["log_w_mm"] = get("w_mm") / w_mm
    if get("U_mm") is not None and math.isfinite(U_mm):
        out["inv_U_per_m"] = get("U_mm") * 1000.0 / (U_mm * U_mm)
    if get("d_mm") is not None:
        out["d_scaled"] = get("d_mm") / APERTURE_SCALE_MM
    if get("theta_F_deg") is not None:
        out["theta_F"] = math.radians(get("theta_F_deg"))
    return out


def lens_from_stored_jacobian(w_mm: torch.Tensor, U_mm: torch.Tensor, d_scaled: torch.Tensor) -> torch.Tensor:
    """(4,) diagonal of ∂(w, U, d, θF)/∂(log w, 1/U, d_scaled, θF) at the lens (w, U in mm; d_scaled the stored
    value): w, −U²/1000, 10 sign(d_scaled) mm, 1 (w = exp(log w), U = 1000 / (1/U), d = 10 |d_scaled|)."""
    return torch.stack([w_mm, -U_mm * U_mm / 1000.0, APERTURE_SCALE_MM * torch.sign(d_scaled), torch.ones_like(w_mm)])
