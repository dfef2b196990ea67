"""Least-squares solvers shared by the calibration's fits (the project's only Levenberg–Marquardt loops;
tests/test_one_solver.py keeps it so).

    lm.py       Levenberg–Marquardt over named parameter blocks (one large problem: the corner fit, the blur
                fit); `least_squares` for one dense vector; Gauss–Newton covariance
    blocks.py   parameter blocks (global, per view, per point), their flat vector, and the normal equations
                (dense, or the Schur complement of the per-view blocks)
    points.py   the normal equations with a per-point block (a free board's points) eliminated point by point,
                as bundle adjustment's, and their covariance
    batched.py  Levenberg–Marquardt on many small independent problems at once (the detector's and the blur
                measurement's per-corner fits)
"""
from .batched import BatchedOptions, BatchedResult, Normal, batched_levenberg_marquardt, normal_from_residuals
from .blocks import Block, BlockJacobian, Layout, dense_jacobian
from .points import normal_equations
from .lm import LMOptions, LMResult, SolverError, covariance, least_squares, levenberg_marquardt, solve_rescaling

__all__ = ["BatchedOptions", "BatchedResult", "Block", "BlockJacobian", "LMOptions", "LMResult", "Layout", "Normal",
           "SolverError", "batched_levenberg_marquardt", "covariance", "dense_jacobian", "least_squares",
           "levenberg_marquardt", "normal_equations", "normal_from_residuals", "solve_rescaling"]
