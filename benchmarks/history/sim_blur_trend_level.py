"""The blur-trend test's level under errors a view's widths share (the review of session 10).

Simulated residuals with no trend with depth: G views at depths spread over 500–900 mm (±30 mm within a view),
40 widths a view, independent noise 0.2 px, and an offset shared by each view's widths (σ 0, 0.1 or 0.3 px).
The share of captures called significant at p < 1e-3 by (a) the cluster-robust Wald χ²(2) on the quadratic's
(b, c) that `tiltfit.calibrate.flow.blur_trend` used before, and (b) the F(2, G − 3) test on the views' means it
uses now; and the share at α = 1e-2 (its level now) with a real trend of 0.4 px over the depths (power).
Plain least squares here (the code fits Huber weights first; with no outliers they are all 1).
`python benchmarks/history/sim_blur_trend_level.py` → benchmarks/results/blur_trend_level.md.
"""
from __future__ import annotations

import os

import numpy as np

HERE = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "benchmarks", "results")


def trial(rng, G, off_sd, trend=0.0, n=40, noise=0.2):
    zc = np.sort(rng.uniform(500, 900, G))
    z = np.concatenate([c + rng.uniform(-30, 30, n) for c in zc])
    view = np.repeat(np.arange(G), n)
    z5, z50, z95 = np.percentile(z, [5, 50, 95])
    t = (z - z50) / (z95 - z5)
    r = np.repeat(rng.normal(0, off_sd, G), n) + rng.normal(0, noise, G * n) + trend * t
    X = np.stack([np.ones_like(t), t, t * t], 1)
    coef = np.linalg.lstsq(X, r, rcond=None)[0]
    e = r - X @ coef
    bread = np.linalg.pinv(X.T @ X)
    sc = np.zeros((G, 3))
    np.add.at(sc, view, X * e[:, None])
    cov = bread @ (sc.T @ sc) @ bread * G / (G - 1)
    wald = float(coef[1:] @ np.linalg.solve(cov[1:, 1:], coef[1:]))
    p_wald = float(np.exp(-wald / 2))
    Xm = np.stack([X[view == g].mean(0) for g in range(G)])
    rm = np.array([r[view == g].mean() for g in range(G)])
    c1 = np.linalg.lstsq(Xm, rm, rcond=None)[0]
    rss1, rss0 = float(((rm - Xm @ c1) ** 2).sum()), float(((rm - rm.mean()) ** 2).sum())
    d = G - 3
    f = max(rss0 - rss1, 0.0) / 2 / max(rss1 / d, 1e-300)
    return p_wald, (1 + 2 * f / d) ** (-d / 2)


def main() -> int:
    rng = np.random.default_rng(0)
    lines = ["# The blur-trend test's level with errors a view's widths share", "",
             "`python benchmarks/history/sim_blur_trend_level.py` (module docstring: what is simulated). Share of captures "
             "called significant; 2,000 null captures a row, 500 with the trend.", "",
             "| views | offset σ px | Wald χ²(2), p < 1e-3 (before) | F on view means, p < 1e-3 | F, p < 1e-2 (now) "
             "| power, trend 0.4 px, F p < 1e-2 |", "|---|---|---|---|---|---|"]
    for G in (4, 6, 10, 20):
        for sd in (0.0, 0.1, 0.3):
            null = np.array([trial(rng, G, sd) for _ in range(2000)])
            alt = np.array([trial(rng, G, sd, trend=0.4) for _ in range(500)])
            lines.append(f"| {G} | {sd:g} | {np.mean(null[:, 0] < 1e-3):.3f} | {np.mean(null[:, 1] < 1e-3):.4f} | "
                         f"{np.mean(null[:, 1] < 1e-2):.3f} | {np.mean(alt[:, 1] < 1e-2):.3f} |")
    os.makedirs(HERE, exist_ok=True)
    with open(os.path.join(HERE, "blur_trend_level.md"), "w", encoding="utf-8") as fh:
        fh.write("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
