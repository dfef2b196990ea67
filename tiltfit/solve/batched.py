"""Levenberg–Marquardt on many small independent least-squares problems at once (B problems × P parameters).

    batched_levenberg_marquardt(evaluate, x0, options=BatchedOptions(), small_step=None, project=None)
        -> BatchedResult

The detector's per-corner fits (`tiltfit.detect.chessboard.refine_symmetric`: a corner's position from the point symmetry
of its patch) and the blur measurement's per-corner fits (`tiltfit.detect.blur.fit_corners`: blur diameter and edge
levels) are thousands of problems of 2 to ~20 parameters that share nothing; one batched solve replaces a loop
over them. `tiltfit.solve.levenberg_marquardt` is the solver of one large problem with block structure.

`evaluate(x, idx)` gets the parameters x (k, P) of the problems idx (k,) (a subset of the batch: the problems
still running) and returns their linearisation, either as
- `(r, J)`: residuals r (k, M), model − observation, and their Jacobian J (k, M, P); or
- a `Normal` (cost, JᵀWJ, JᵀWr) directly, when the Jacobian has structure a dense (k, M, P) tensor would waste
  (`normal_from_residuals` builds one from residuals, a Jacobian and weights).

Each problem minimises ½ Σ w r² (the `Normal`'s cost) on its own, with its own damping λ:
- step: (A + λ (diag A + `diagonal_floor`)) δ = −g, Marquardt's scaling of the damping by the diagonal
  (Marquardt, "An algorithm for least-squares estimation of nonlinear parameters", 1963), optionally capped to
  a Euclidean length `max_step` and the trial point projected onto the problem's bounds (`project`);
- acceptance: a trial point is taken when it lowers the cost; then λ ← λ · `damping_decrease`, else
  λ ← λ · `damping_increase` (Marquardt's rule with his factors 1/3 and 10, here 0.3 and 10), λ kept within
  [`min_damping`, `max_damping`];
- a problem leaves the batch when its step is small (`small_step`, default: |δ|∞ ≤ xtol (|x|∞ + xtol)) or
  its damping exceeds `give_up_damping` (no decreasing step: a stationary point to working precision), so the
  work follows the slow problems.
`tiltfit.solve.lm` decides acceptance by the gain ratio instead; on problems this small, with a handful of
iterations, the plain cost test is as good and needs no model prediction.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import torch


@dataclass
class Normal:
    """The linearisation of k problems at their current parameters.

    Attributes:
        cost: (k,) ½ Σ w r² per problem (any monotone equivalent works: only differences are compared).
        A: (k, P, P) JᵀWJ; g: (k, P) JᵀWr (r model − observation).
    """

    cost: torch.Tensor
    A: torch.Tensor
    g: torch.Tensor


def normal_from_residuals(r: torch.Tensor, J: torch.Tensor, weights: torch.Tensor | None = None) -> Normal:
    """`Normal` of residuals r (k, M) with Jacobian J (k, M, P) and weights w (k, M) or (M,) (None: 1)."""
    Jw = J if weights is None else J * weights[..., None]
    wr = r if weights is None else r * weights
    return Normal(0.5 * (wr * r).sum(-1), Jw.transpose(-1, -2) @ J, (Jw * r[..., None]).sum(-2))


@dataclass(frozen=True)
class BatchedOptions:
    """Settings of `batched_levenberg_marquardt` (defaults in brackets).

    Attributes:
        max_iterations: trial steps per problem at most [30].
        initial_damping: λ at the start [1e-3].
        damping_decrease, damping_increase: factors of λ after an accepted and a rejected step [0.3, 10].
        min_damping, max_damping: the range λ is kept in [1e-9, 1e9].
        give_up_damping: a problem whose λ exceeds this leaves the batch (no step decreases its cost) [1e6].
        diagonal_floor: added to diag A in the damping term, so a parameter with no curvature still gets some
            [1e-9].
        max_step: Euclidean length a step is capped to (a trust region on the first, possibly wild, steps) [inf].
        xtol: the default small-step test's relative tolerance [1e-8].
    """

    max_iterations: int = 30
    initial_damping: float = 1e-3
    damping_decrease: float = 0.3
    damping_increase: float = 10.0
    min_damping: float = 1e-9
    max_damping: float = 1e9
    give_up_damping: float = 1e6
    diagonal_floor: float = 1e-9
    max_step: float = math.inf
    xtol: float = 1e-8


@dataclass
class BatchedResult:
    """Outcome of a batched solve.

    Attributes:
        x: (B, P) the parameters; cost: (B,); A: (B, P, P) JᵀWJ at x; g: (B, P) JᵀWr at x.
        damping: (B,) the final λ; converged: (B,) bool, the step became small or no step decreased the cost
            any more (a minimum to working precision); False: the iterations ran out first.
        iterations: trial steps of the slowest problem.
    """

    x: torch.Tensor
    cost: torch.Tensor
    A: torch.Tensor
    g: torch.Tensor
    damping: torch.Tensor
    converged: torch.Tensor
    iterations: int


def _linearise(evaluate, x: torch.Tensor, idx: torch.Tensor) -> Normal:
    out = evaluate(x, idx)
    return out if isinstance(out, Normal) else normal_from_residuals(*out)


def batched_levenberg_marquardt(evaluate: Callable, x0: torch.Tensor, options: BatchedOptions = BatchedOptions(),
                                small_step: Callable | None = None, project: Callable | None = None
                                ) -> BatchedResult:
    """Minimise each of B independent least-squares problems (module docstring).

    Args:
        evaluate: (x (k, P), idx (k,) long) -> (r (k, M), J (k, M, P)) or `Normal`.
        x0: (B, P) starting parameters (float64 keeps the iterates exact; the linearisation may be float32).
        options: `BatchedOptions`.
        small_step: (step (k, P), x (k, P) after the step's acceptance or rejection, idx (k,)) -> (k,) bool,
            the problems whose step is small enough to stop; default |δ|∞ ≤ xtol (|x|∞ + xtol).
        project: (x (k, P), idx (k,)) -> x, the trial point moved onto the problems' bounds (None: no bounds).
    Returns:
        `BatchedResult`.
    """
    x = x0.clone()
    B = x.shape[0]
    every = torch.arange(B)
    lin = _linearise(evaluate, x, every)
    cost, A, g = lin.cost.clone(), lin.A.clone(), lin.g.clone()
    lam = torch.full((B,), options.initial_damping, dtype=torch.float64)
    converged = torch.zeros(B, dtype=torch.bool)
    if small_step is None:
        def small_step(step, xa, idx):
            return step.abs().amax(-1) <= options.xtol * (xa.abs().amax(-1) + options.xtol)
    active, it = every, 0
    # the active problems' state, compact: written back to the batch's when a problem leaves and at the end, so an
    # iteration gathers and scatters nothing
    xa, Aa, ga, ca, la = x, A, g, cost, lam
    for it in range(1, options.max_iterations + 1):
        diag = torch.diagonal(Aa, dim1=1, dim2=2)
        damped = Aa + la[:, None, None].to(Aa.dtype) * torch.diag_embed(diag + options.diagonal_floor)
        step = -torch.linalg.solve(damped, ga[..., None])[..., 0]
        if math.isfinite(options.max_step):
            length = torch.linalg.vector_norm(step, dim=1, keepdim=True)
            step = torch.where(length > options.max_step, step * (options.max_step / length), step)
        trial = xa + step.to(xa.dtype)
        if project is not None:
            trial = project(trial, active)
        new = _linearise(evaluate, trial, active)
        better = new.cost < ca
        xa = torch.where(better[:, None], trial, xa)
        Aa = torch.where(better[:, None, None], new.A, Aa)
        ga = torch.where(better[:, None], new.g, ga)
        ca = torch.where(better, new.cost, ca)
        la = torch.where(better, la * options.damping_decrease,
                         la * options.damping_increase).clamp(options.min_damping, options.max_damping)
        done = small_step(step, xa, active) | (la > options.give_up_damping)
        if bool(done.any()):
            gone = active[done]
            x[gone], A[gone], g[gone], cost[gone], lam[gone] = xa[done], Aa[done], ga[done], ca[done], la[done]
            converged[gone] = True
            stay = ~done
            active, xa, Aa, ga, ca, la = active[stay], xa[stay], Aa[stay], ga[stay], ca[stay], la[stay]
            if active.numel() == 0:
                break
    x[active], A[active], g[active], cost[active], lam[active] = xa, Aa, ga, ca, la
    return BatchedResult(x, cost, A, g, lam, converged, it)


__all__ = ["BatchedOptions", "BatchedResult", "Normal", "batched_levenberg_marquardt", "normal_from_residuals"]
