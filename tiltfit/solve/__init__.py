"""Least-squares solvers shared by the calibration's fits.

    lm.py      Levenberg–Marquardt over named parameter blocks; Gauss–Newton covariance
    blocks.py  parameter blocks (global and per view), their flat vector, and the normal equations
               (dense, or the Schur complement of the per-view blocks)
"""
from .blocks import Block, BlockJacobian, Layout, dense_jacobian, normal_equations
from .lm import LMOptions, LMResult, SolverError, covariance, levenberg_marquardt

__all__ = ["Block", "BlockJacobian", "LMOptions", "LMResult", "Layout", "SolverError", "covariance",
           "dense_jacobian", "levenberg_marquardt", "normal_equations"]
