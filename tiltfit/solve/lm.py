"""Levenberg–Marquardt over named parameter blocks, with Gauss–Newton covariances.

    levenberg_marquardt(evaluate, x0, blocks, view_rows=None, options=LMOptions()) -> LMResult
    least_squares(residual_fn, x0, options=LMOptions(), jacobian_fn=None) -> LMResult   (one dense vector)
    covariance(result) -> the (P, P) covariance, by blocks

`evaluate(x, with_jacobian)` gets the state as {block name: tensor} and returns (r, jac): r the (M,) residuals,
already divided by their standard deviations, and jac {block name: (M, size)} (None when not asked for): for a
per-view block (`Block.per_view`), row i holds the derivatives with respect to the block of row i's view
(`blocks.Layout`). Every residual row belongs to one view (`view_rows`) when there are per-view blocks; their
normal equations are then solved by the Schur complement (`blocks.SchurNormal`). A point block (`Block.points`:
each row depends on its own point's 3 coordinates, `row_points`) is eliminated point by point before that
(`points.PointSchurNormal`).

Minimises ½ Σ ρ(r_i²) (ρ(s) = s unless `LMOptions.rho`), robust losses by iteratively reweighted least
squares (weights ρ'(r_i²), `LMOptions.weight`), each step solving (JᵀWJ + λ D) δ = −JᵀW r:
- scaling D: the running maximum of diag(JᵀWJ) over the iterations (Marquardt's scaling, kept monotone as in
  Moré, "The Levenberg–Marquardt algorithm: implementation and theory", 1978, eq. 6.3), so the damping is
  invariant to the units of each parameter;
- damping update: the gain ratio ρ_g = (actual cost decrease) / (decrease predicted by the quadratic model);
  a step is accepted when ρ_g > 0, then λ ← λ · max(`DAMPING_DECREASE_FLOOR`, 1 − (2ρ_g − 1)³) and ν ← 2;
  a rejected step gives λ ← λ ν, ν ← 2ν (Nielsen, "Damping parameter in Marquardt's method", IMM-REP-1999-05;
  Madsen, Nielsen & Tingleff, "Methods for non-linear least squares problems", 2004, eq. 3.16; Nielsen's
  floor is 1/3, this one lets λ fall faster on the well-conditioned problems of calibration).
Converged when, at the current point:
- the Gauss–Newton decrement ½ gᵀ (JᵀWJ)⁻¹ g (the cost a full Gauss–Newton step would still gain) is below
  `decrement_tol` or below `ftol` times the cost: with residuals in units of their σ the first means the
  parameters are within about sqrt(2 · decrement_tol) of their standard deviations of the minimum; so does the
  second, relative to the cost (≈ n/2 for n residuals): 1e-7 of it puts them within about sqrt(1e-7 n) σ
  (0.02 σ for 3,000 corners). An ill-conditioned fit (the rational distortion with a free principal point) can
  creep on by 3e-8 of its cost per iteration for hundreds of iterations, which the absolute test alone calls
  no convergence (`REL_COST_TOL`); or
- an accepted step decreased the cost by less than `ftol` relative to it, in fact and as predicted
  (MINPACK's test, Moré, Garbow & Hillstrom, "User guide for MINPACK-1", 1980, §2.3); or
- the step was below `xtol` relative to the largest parameter.
No decreasing step for any damping up to `MAX_DAMPING` means a stationary point to working precision.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Callable

import torch

from .blocks import Block, BlockJacobian, Layout
from .points import normal_equations

#: Smallest factor λ is multiplied by after a successful step (Nielsen's rule has 1/3).
DAMPING_DECREASE_FLOOR = 0.1
#: λ at the start, relative to the scaling D.
INITIAL_DAMPING = 1e-6
#: λ above which no step can decrease the cost (steps of relative size below 1e-16).
MAX_DAMPING = 1e16
#: Default `ftol`: a fit still creeping by 3e-8 of its cost per iteration (the GoPro set's held-out folds with a
#: free principal point and the rational model) is at its minimum to far better than the parameters' σ; 1e-7
#: leaves a margin above that.
REL_COST_TOL = 1e-7
#: Tikhonov damping of the Gauss–Newton solve that measures the decrement (keeps it finite on flat directions).
DECREMENT_DAMPING = 1e-12


class SolverError(RuntimeError):
    """The solve cannot start (non-finite residuals) or did not converge; the message is one line."""


@dataclass(frozen=True)
class LMOptions:
    """Settings of `levenberg_marquardt` (defaults in brackets).

    Attributes:
        max_iterations: accepted steps at most [200].
        decrement_tol: Gauss–Newton decrement below which the solve has converged [1e-9].
        ftol: relative cost decrease (actual and predicted) of a step, and Gauss–Newton decrement relative to
            the cost, below which it has converged [`REL_COST_TOL`, 1e-7].
        xtol: step size, relative to the largest parameter, below which it has converged [1e-12].
        rho: robust cost ρ(s²) of squared residuals (None: ρ(s²) = s²) [None].
        weight: its derivative ρ'(s²), the IRLS weights (None: 1) [None].
    """

    max_iterations: int = 200
    decrement_tol: float = 1e-9
    ftol: float = REL_COST_TOL
    xtol: float = 1e-12
    rho: Callable | None = None
    weight: Callable | None = None


@dataclass
class LMResult:
    """A solve's outcome.

    Attributes:
        x: {block name: tensor} the solution; x_flat: (P,) the same as one vector (`layout`'s order).
        cost: ½ Σ ρ(r²) at x; iterations: accepted steps.
        r: (M,) residuals at x; weights: (M,) IRLS weights at x.
        jacobian: the Jacobian at x (`blocks.BlockJacobian` or a dense (M, P) tensor); normal: its normal
            equations (`blocks.SchurNormal` or `blocks.DenseNormal`) with the weights.
        stop: why the solve ended: "decrement", "ftol", "xtol" or "stationary".
        layout: the `blocks.Layout` of the parameters.
    """

    x: dict
    x_flat: torch.Tensor
    cost: float
    iterations: int
    r: torch.Tensor
    weights: torch.Tensor
    jacobian: object
    normal: object
    stop: str
    layout: Layout

    def scaled(self, factor: float) -> "LMResult":
        """The result for the residuals multiplied by a constant `factor` (a new σ for all of them): the
        minimiser of ½ Σ r² does not move, so no re-solve is needed. Without a robust loss only (its
        weights depend on the scale)."""
        J = self.jacobian
        J = J.scaled(factor) if isinstance(J, BlockJacobian) else J * factor
        return replace(self, cost=self.cost * factor**2, r=self.r * factor, jacobian=J,
                       normal=normal_equations(J, self.weights))


@dataclass(frozen=True)
class _Problem:
    """The residual function of `levenberg_marquardt` on the flat parameter vector (`layout`'s order), and the
    robust cost of its residuals."""
    evaluate: Callable
    layout: Layout
    rho: Callable

    def cost(self, r: torch.Tensor) -> float:
        """½ Σ ρ(r²)."""
        return 0.5 * float(self.rho(r * r).sum())

    def linearise(self, v: torch.Tensor):
        """Residuals (M,) and their `blocks.BlockJacobian` at the flat parameters v."""
        r_v, jac = self.evaluate(self.layout.unflatten(v), True)
        return r_v.detach(), self.layout.jacobian(jac)

    def residuals(self, v: torch.Tensor) -> torch.Tensor:
        """Residuals (M,) at the flat parameters v, without the Jacobian."""
        return self.evaluate(self.layout.unflatten(v), False)[0].detach()


@dataclass(frozen=True)
class _Trial:
    """An accepted damped step: the step (P,), the residuals there (M,), their Jacobian (None where only the
    residuals were evaluated), the cost there, the decrease the quadratic model predicted, and the gain ratio."""
    step: torch.Tensor
    r: torch.Tensor
    J: object
    cost: float
    predicted: float
    gain: float


def _decrement(ne, g: torch.Tensor, scaling: torch.Tensor, lam: float = math.inf):
    """(The Gauss–Newton decrement ½ gᵀ (JᵀWJ + εD)⁻¹ g, inf where the solve fails; the solve (JᵀWJ + λD)⁻¹ g where
    it is that one, else None) with ε = `DECREMENT_DAMPING`, or the iteration's λ where that is smaller: then the
    solve is also the iteration's first trial's (`_damped_step`'s `solved`)."""
    damping = min(lam, DECREMENT_DAMPING)
    try:
        solution = ne.solve(damping * scaling, g)
    except RuntimeError:
        return math.inf, None
    decrement = 0.5 * float(g @ solution)
    return (decrement if math.isfinite(decrement) else math.inf), (solution if damping == lam else None)


def _damped_step(problem: _Problem, x, cost: float, ne, g, scaling, lam: float, nu: float, solved=None):
    """One iteration's trials: solve (JᵀWJ + λD) δ = −g and raise λ (λ ← λν, ν ← 2ν) until the gain ratio is
    positive. Returns (the accepted `_Trial`, or None where λ passed `MAX_DAMPING`; λ; ν). `solved`: the first
    trial's solve (JᵀWJ + λD)⁻¹ g where `_decrement` made it (λ ≤ `DECREMENT_DAMPING`), not solved again."""
    first_trial = True
    while True:
        if first_trial and solved is not None:
            step = -solved
        else:
            try:
                step = -ne.solve(lam * scaling, g)
            except RuntimeError:
                step = torch.full_like(g, math.nan)
        ok = bool(torch.isfinite(step).all())
        # The first trial of an iteration gets its Jacobian with its residuals (one call costs less than
        # residuals now and the Jacobian after, and most first trials are accepted); later ones, after a
        # rejection, residuals only.
        if not ok:
            r_new, J_new = None, None
        elif first_trial:
            r_new, J_new = problem.linearise(x + step)
        else:
            r_new, J_new = problem.residuals(x + step), None
        first_trial = False
        cost_new = problem.cost(r_new) if ok and torch.isfinite(r_new).all() else math.inf
        predicted = float(-(g @ step) - 0.5 * step @ ne.matvec(step)) if ok else 0.0
        gain = (cost - cost_new) / predicted if predicted > 0 else -1.0
        if gain > 0:
            return _Trial(step, r_new, J_new, cost_new, predicted, gain), lam, nu
        lam *= nu
        nu *= 2.0
        if lam > MAX_DAMPING:
            return None, lam, nu


def levenberg_marquardt(evaluate, x0: dict, blocks, view_rows: torch.Tensor | None = None,
                        options: LMOptions = LMOptions(), row_points: torch.Tensor | None = None) -> LMResult:
    """Minimise ½ Σ ρ(r_i(x)²) over the named blocks (module docstring).

    Args:
        evaluate: (x: {name: tensor}, with_jacobian: bool) -> (r (M,), {name: (M, size)} or None). Its tensors
            must be new each call: the solver and `LMResult.jacobian` keep views of them, not copies.
        x0: {name: tensor} the start, each of its block's shape (float64).
        blocks: the `Block`s in flat order.
        view_rows: (V, R) long, each view's residual rows (when a block is per view).
        options: `LMOptions`.
        row_points: (M,) long, each residual row's point (when a block is a point block, `Block.points`).
    Returns:
        LMResult.
    Raises:
        SolverError: non-finite residuals at the start, or no convergence within `options.max_iterations`.
    """
    layout = Layout(blocks, view_rows, row_points)
    problem = _Problem(evaluate, layout, options.rho or (lambda s2: s2))
    weight = options.weight or torch.ones_like
    x = layout.flatten(x0).detach().clone()
    r, J = problem.linearise(x)
    if not torch.isfinite(r).all():
        raise SolverError("the model is undefined at the starting point (a point behind the camera?)")
    cost = problem.cost(r)
    wts = weight(r * r)
    lam, nu, scaling = INITIAL_DAMPING, 2.0, None

    def done(it: int, stop: str, ne) -> LMResult:
        return LMResult(layout.unflatten(x), x, cost, it, r, wts, J, ne, stop, layout)

    decrement = math.inf
    for it in range(options.max_iterations + 1):
        ne = normal_equations(J, wts)
        g = ne.gradient(r)
        d = ne.diag().clamp(min=1e-300)
        scaling = d if scaling is None else torch.maximum(scaling, d)
        decrement, solved = _decrement(ne, g, scaling, lam)
        if decrement < max(options.decrement_tol, options.ftol * cost):
            return done(it, "decrement", ne)
        if it == options.max_iterations:
            break
        trial, lam, nu = _damped_step(problem, x, cost, ne, g, scaling, lam, nu, solved)
        if trial is None:
            return done(it, "stationary", ne)
        small_decrease = cost - trial.cost <= options.ftol * cost and trial.predicted <= options.ftol * cost
        x = x + trial.step
        lam *= max(DAMPING_DECREASE_FLOOR, 1.0 - (2.0 * trial.gain - 1.0) ** 3)
        nu = 2.0
        r, J, cost = (trial.r, trial.J, trial.cost) if trial.J is not None else (*problem.linearise(x), trial.cost)
        wts = weight(r * r)
        if small_decrease:
            return done(it + 1, "ftol", normal_equations(J, wts))
        if float(trial.step.abs().max()) <= options.xtol * (float(x.abs().max()) + options.xtol):
            return done(it + 1, "xtol", normal_equations(J, wts))
    raise SolverError(f"the fit did not converge in {options.max_iterations} iterations (cost {cost:.6g}, "
                      f"still decreasing by about {decrement:.3g})")


def solve_rescaling(solve, rescale, x0, max_solves: int):
    """Solve; re-estimate the residuals' scale from the solution; solve again from there while it moved: the outer
    loop of a fit whose residual weights follow a scale estimated from its own residuals (the corner and blur
    groups' σ of the calibration, the photometric fit's robust σ). Written once here.

    Args:
        solve: x -> `LMResult`, a solve from x at the current scale.
        rescale: (result, k, last) -> (result, again): after solve k (0-based; `last` for the final one allowed),
            re-estimate and keep the scale; `again` whether to solve once more (ignored after the last), the result
            possibly rescaled to the new scale.
        x0: the first solve's start.
        max_solves: the most solves.
    Returns:
        (the last result, the iterations of all solves).
    """
    x, iterations, result = x0, 0, None
    for k in range(max_solves):
        result = solve(x)
        x, iterations = result.x, iterations + result.iterations
        result, again = rescale(result, k, k == max_solves - 1)
        if not again:
            break
    return result, iterations


def covariance(result: LMResult, variance_factor: float = 1.0):
    """Gauss–Newton covariance s² (JᵀWJ)⁻¹ of the flat parameters at the solution (`layout` order), as a
    `blocks.SchurCovariance` (per-view blocks: never a (P, P) matrix) or `blocks.DenseCovariance`; `.dense()`
    gives the matrix, `.diagonal()` the variances, `.matmul(X)` the product with (P, n).

    Raises:
        SolverError: the normal matrix is singular or not positive definite (parameters the data do not
            determine).
    """
    try:
        cov = result.normal.covariance()
    except RuntimeError:
        raise SolverError("the free parameters are not all determined by the data") from None
    d = cov.diagonal()
    if not torch.isfinite(d).all() or (d <= 0).any():
        raise SolverError("the free parameters are not all determined by the data")
    return cov.scaled(variance_factor)


def least_squares(residual_fn, x0: torch.Tensor, options: LMOptions = LMOptions(), jacobian_fn=None) -> LMResult:
    """Minimise ½ Σ ρ(r_i(x)²) over one dense parameter vector: `levenberg_marquardt` with a single block
    "x"; the result's `x` is the vector.

    Args:
        residual_fn: (P,) -> (M,) float64 residuals, already divided by their σ.
        x0: (P,) start.
        options: `LMOptions`.
        jacobian_fn: (P,) -> (M, P); default `torch.func.jacfwd(residual_fn)`.
    Raises:
        SolverError: non-finite residuals at the start, or no convergence within `options.max_iterations`.
    """
    from torch.func import jacfwd

    jac = jacobian_fn or jacfwd(residual_fn)

    def evaluate(x: dict, with_jacobian: bool):
        v = x["x"]
        return residual_fn(v).detach(), ({"x": jac(v).detach()} if with_jacobian else None)

    res = levenberg_marquardt(evaluate, {"x": x0.detach().to(torch.float64)}, [Block("x", tuple(x0.shape))],
                              None, options)
    res.x = res.x_flat
    return res


__all__ = ["Block", "LMOptions", "LMResult", "SolverError", "covariance", "least_squares", "levenberg_marquardt"]
