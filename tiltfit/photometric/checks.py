"""What the photometric refinement is judged by: the held-out pixels' cost (`_held_out_costs`) and the held-out
corners (`_corner_check`)."""
from __future__ import annotations

import math

import torch


from tiltfit.calibrate.model import LensCamera, robust_rho, robust_weight
from ..solve import LMOptions, SolverError, least_squares
from .options import PhotometricOptions
from .problem import _Problem


#: The refinement is kept only where its RMS on the (held-out) corners is at most 1 + this times the corner
#: fit's held-out RMS.
CORNER_TOLERANCE = 0.02


#: Without the corner fit's held-out RMS the corners are compared in sample (the corner fit minimised their cost, so
#: any other lens costs more): kept while the cost rises by at most the χ² quantile of this level for the free lens
#: parameters, in units of the corners' own noise: the refined lens inside the corner fit's confidence region.
#: (A tolerance of 2 % on the RMS rejected refinements one corner-fit σ from the start, where the corners were
#: few: on 2 heavy-blur views, 0.0210 against 0.0207 px, the refinement nearer the truth in w, U and d;
#: benchmarks/results/photometric_refine.md.)
CORNER_CONFIDENCE = 0.99


def _held_out_costs(problem: _Problem, held_data: list, x: dict, x0: dict, opts: PhotometricOptions,
                    scale: float) -> dict:
    """Mean Huber cost (residuals in units of `scale`) of the held-out pixels for the refined state `x` and for
    the start `x0`'s lens and poses with the exposure fitted to the fit's pixels (geometry held: per view the
    levels by robust linear least squares, the vignetting the refinement's)."""
    k = opts.huber_scale
    vig = x["vignetting"] if "vignetting" in x else torch.zeros(1, dtype=torch.float64)
    psf = x0["psf"][0] if "psf" in x0 else torch.tensor(problem.psf_fixed, dtype=torch.float64)
    levels = []
    for v, dv in enumerate(problem.data):
        D = problem._dark(v, torch.cat([problem.full_lens(x0["lens"]), x0["pose"][v]]), psf, False)[0]
        f = 1.0 - vig[0] * dv.rho2
        if "gain" in x:   # the refinement's illumination gradient, as its vignetting
            f = f * (1.0 + dv.xy @ x["gain"][v])
        A = torch.stack([f * (1 - D), f * D], 1)
        sol0 = x0["levels"][v].detach().to(torch.float64)  # the start's levels
        huber = LMOptions(max_iterations=50, rho=lambda s2: robust_rho(s2, "huber", k),
                          weight=lambda s2: robust_weight(s2, "huber", k))
        try:
            sol = least_squares(lambda lv: (A @ lv - dv.observed) / scale, sol0, huber,
                                jacobian_fn=lambda lv: A / scale).x
        except SolverError:  # creeping on (nearly) noise-free pixels: the start's levels
            sol = sol0
        levels.append(sol)
    start = {**x0, "levels": torch.stack(levels), "vignetting": vig, **({"gain": x["gain"]} if "gain" in x else {})}
    check = _Problem(problem.camera, problem.target, held_data, problem.lens_uv)
    check.near, check.scale, check.psf_fixed = problem.near, scale, problem.psf_fixed
    check.free, check.bound, check.lens_start = problem.free, problem.bound, problem.lens_start

    def cost(state):
        with torch.no_grad():
            r = check.evaluate(state, False)[0]
        return robust_rho(r * r, "huber", k)

    c_ref, c_start = cost(x), cost(start)
    diff = c_ref - c_start
    n = int(diff.numel())
    se = float(diff.std() / math.sqrt(n)) if n > 1 else math.inf
    return {"pixels": n, "refined": float(c_ref.mean()), "start": float(c_start.mean()), "difference_se": se}


def _chi2_quantile(p: float, k: int) -> float:
    """x with P(χ²(k) ≤ x) = p (bisection on `stats.chi2_sf`)."""
    from tiltfit.select.stats import chi2_sf

    lo, hi = 0.0, 10.0 * k + 100.0
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if chi2_sf(mid, k) > 1 - p else (lo, mid)
    return 0.5 * (lo + hi)


def _corner_check(refined: LensCamera, start: LensCamera, corners, start_held_out_px,
                  n_free: int = 4) -> dict:
    """The refinement judged by the corners (held out of the photometric fit): each view's pose refitted to them
    with the refined lens held (`validate.predict_views`), RMS per corner, against the corner fit's held-out
    RMS times 1 + CORNER_TOLERANCE; or, without it, against the start's own RMS with its poses refitted the same way
    (in sample): there the limit lets the corners' cost rise by the χ² quantile (CORNER_CONFIDENCE, `n_free`
    degrees of freedom) times their noise variance (their RSS over its residual degrees of freedom)."""
    from tiltfit.select.held_out import predict_views

    def rss(camera):
        fit = predict_views(camera.copy().double(), corners)
        return float(fit.rss["corners"]), max(int(fit.rss["n_corners"]), 1)

    got_rss, n_res = rss(refined)
    got = math.sqrt(got_rss / max(n_res // 2, 1))
    if start_held_out_px is not None:
        ref = float(start_held_out_px)
        return {"start_px": ref, "refined_px": got, "limit_px": ref * (1 + CORNER_TOLERANCE),
                "start_is_held_out": True, "views": corners.n_views}
    start_rss, _ = rss(start)
    dof = max(n_res - 6 * corners.n_views - n_free, 1)
    limit_rss = start_rss * (1.0 + _chi2_quantile(CORNER_CONFIDENCE, max(n_free, 1)) / dof)
    return {"start_px": math.sqrt(start_rss / max(n_res // 2, 1)), "refined_px": got,
            "limit_px": math.sqrt(limit_rss / max(n_res // 2, 1)), "start_is_held_out": False,
            "views": corners.n_views}
