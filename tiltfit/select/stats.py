"""The one nested-model test every model choice in tiltfit uses (distortion terms, θF and the principal
point, a blur fit against constant widths, the photometric blur kernel).

Λ = Σ_g n_g ln(RSS_g,restricted / RSS_g,full) ~ χ²(k) under the restricted model (Gaussian residuals, each
group's variance profiled out); ΔAIC = Λ − 2k and ΔBIC = Λ − k ln n are the fuller model's improvements
(positive: preferred). A fuller model is justified where p < α and ΔBIC > 0.
"""
from __future__ import annotations

import math

import torch


def chi2_sf(x: float, k: int) -> float:
    """Survival function of χ²(k) (regularised upper incomplete gamma)."""
    if x <= 0:
        return 1.0
    return float(torch.special.gammaincc(torch.tensor(k / 2.0, dtype=torch.float64),
                                         torch.tensor(x / 2.0, dtype=torch.float64)))


def nested_test(groups, k: int, alpha: float = 0.01) -> dict:
    """Test a restricted model against one with k more parameters.

    Args:
        groups: (n_g, RSS_g restricted, RSS_g full) per residual group with its own variance.
        k: extra parameters of the fuller model.
    Returns:
        lr_statistic, dof, p_value, delta_aic, delta_bic, justified, alpha.
    """
    lam, n = 0.0, 0
    for n_g, rss_r, rss_f in groups:
        if n_g > 0:
            lam += n_g * math.log(max(rss_r, 1e-300) / max(rss_f, 1e-300))
            n += n_g
    lam = max(lam, 0.0)
    p = chi2_sf(lam, k)
    d_aic, d_bic = lam - 2 * k, lam - k * math.log(max(n, 1))
    return {"lr_statistic": lam, "dof": k, "p_value": p, "delta_aic": d_aic, "delta_bic": d_bic,
            "justified": bool(p < alpha and d_bic > 0), "alpha": alpha}
