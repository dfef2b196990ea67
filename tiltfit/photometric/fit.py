"""The photometric solve: Levenberg–Marquardt with Huber weights, resumed while the robust scale moves (`_solve`);
the kernel choice (`_select_kernel`); the camera of a solver state."""
from __future__ import annotations


import torch

from renderer.cameras import LENS_PARAMETERS, Lens, lens_values

from tiltfit.calibrate.model import LensCamera, robust_rho, robust_weight
from ..solve import Block, LMOptions, SolverError, levenberg_marquardt, solve_rescaling
from tiltfit.select.stats import nested_test
from .options import PSF_EVIDENCE_PX, PSF_START_PX, PhotometricError, PhotometricOptions
from .problem import _Problem
from .sigma import _robust_sigma


#: Relative cost decrease at which a solve has converged: thousands of pixels put the cost in the thousands, and a
#: step that lowers it by less moves the lens by a few hundredths of its σ (the solver's default, 1e-7, spent
#: half of a real photo's iterations there).
SOLVE_FTOL = 1e-5


#: A fit whose robust residual σ moved by more than this fraction resumes with the new σ (the Huber weights).
SCALE_TOLERANCE = 0.05


def _solve(problem: _Problem, x0: dict, blocks: list, view_rows: torch.Tensor, opts: PhotometricOptions,
           history: list):
    """Huber IRLS by `tiltfit.solve.levenberg_marquardt`, the residuals' robust σ re-estimated after each solve
    until it holds (at most three solves). Returns (LMResult, iterations)."""
    k = opts.huber_scale
    lm = LMOptions(max_iterations=opts.iterations, rho=lambda s2: robust_rho(s2, "huber", k),
                   weight=lambda s2: robust_weight(s2, "huber", k), ftol=SOLVE_FTOL)
    problem.scale = _robust_sigma(problem.residuals(x0))

    def solve(x):
        try:
            return levenberg_marquardt(problem.evaluate, x, blocks, view_rows, lm)
        except SolverError as e:
            raise PhotometricError(str(e)) from None

    def rescale(res, k: int, last: bool):
        history.append(res.cost)
        new = _robust_sigma(res.r * problem.scale)
        if abs(new / problem.scale - 1) <= SCALE_TOLERANCE:
            return res, False
        if problem.say:
            problem.say(f"photometric: the residuals' robust σ re-estimated ({problem.scale:.4g} → {new:.4g}); the "
                        "fit resumes with the new Huber weights, and its cost is not comparable with the lines above")
        problem.scale = new
        return res, True

    return solve_rescaling(solve, rescale, x0, 3)


def _select_kernel(problem: _Problem, res, iterations: int, blocks: list, view_rows, opts: PhotometricOptions,
                   history: list, say):
    """Kernel `auto`: the Gaussian part freed from the disc's solution on the same pixels and weights, kept where
    the likelihood-ratio test and its width justify it. Returns (LMResult, iterations, scale, selection)."""
    scale = problem.scale
    w0, r0 = res.weights, res.r * scale
    rss0 = float((w0 * r0 * r0).sum())
    x1 = {**res.x, "psf": torch.tensor([PSF_START_PX], dtype=torch.float64)}
    res1, it1 = _solve(problem, x1, blocks + [Block("psf", (1,))], view_rows, opts, history)
    r1 = res1.r * problem.scale
    rss1 = float((w0 * r1 * r1).sum())
    test = nested_test([(int(r0.numel()), rss0, rss1)], 1, opts.alpha)
    psf = abs(float(res1.x["psf"][0]))
    justified = test["justified"] and psf >= PSF_EVIDENCE_PX
    selection = {"kernel": "disc_gaussian" if justified else "disc", "lr_statistic": test["lr_statistic"],
                 "disc_fit": _lens_values(problem.full_lens(res.x["lens"])), "p_value": test["p_value"],
                 "delta_bic": test["delta_bic"], "rss_disc": rss0, "rss_disc_gaussian": rss1,
                 "psf_sigma_px": psf}
    if say:
        say(f"photometric: kernel {selection['kernel']} (Gaussian σ {psf:.3f} px, Λ = {test['lr_statistic']:.3g}, "
            f"p = {test['p_value']:.2g}, ΔBIC = {test['delta_bic']:.3g})")
    if justified:
        res, iterations, scale = res1, iterations + it1, problem.scale
    else:
        problem.scale = scale
    return res, iterations, scale, selection


def _camera_of(camera: LensCamera, x: dict, problem: "_Problem") -> LensCamera:
    """`camera` (modified in place) holding the lens and poses of the solver's state `x`."""
    lens = problem.full_lens(x["lens"].detach())
    with torch.no_grad():
        for i, n in enumerate(LENS_PARAMETERS):
            getattr(camera, n).copy_(lens[i].to(getattr(camera, n)))
        camera.rvec.copy_(x["pose"][:, :3].to(camera.rvec))
        camera.T_scaled.copy_(x["pose"][:, 3:6].to(camera.T_scaled))
    return camera


def _lens_values(lens: torch.Tensor) -> dict:
    """w, U, d, θF, θL of a stored lens block (mm, degrees)."""
    record = Lens(*lens_values([float(v) for v in lens])).record()
    return {k: v for k, v in record.items() if k != "tilt_axis_deg"}   # the block has no tilt axis
