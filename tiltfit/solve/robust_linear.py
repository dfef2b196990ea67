"""Linear least squares with outliers left out: fit, drop the rows beyond k robust σ of the residuals, refit, until
the rows kept no longer change (the report's brightness and level fits; one loop, kept here by
tests/test_one_solver.py)."""
from __future__ import annotations

import numpy as np

#: The MAD's scale to a Gaussian σ.
MAD_TO_SIGMA = 1.4826


def clipped_lstsq(A: np.ndarray, y: np.ndarray, clip_sigma: float, iterations: int = 5,
                  keep: np.ndarray | None = None, min_rows: int | None = None, sigma_floor: float = 1e-9):
    """Coefficients x of A x ≈ y over the rows kept, and the (N,) bool mask of those rows.

    Rows whose residual exceeds `clip_sigma` × the robust σ (MAD × 1.4826, of the kept rows' residuals, at least
    `sigma_floor`) are left out and the fit repeated, at most `iterations` times or until the mask is stable.
    `keep`: the rows to start with [all]; `min_rows`: stop (keeping the last fit) when fewer rows remain [the
    number of coefficients]. Returns (x, keep); x is None where the first fit had fewer rows than `min_rows`."""
    A, y = np.asarray(A, dtype=np.float64), np.asarray(y, dtype=np.float64)
    keep = np.ones(len(y), bool) if keep is None else np.asarray(keep, bool).copy()
    min_rows = A.shape[1] if min_rows is None else int(min_rows)
    x = None
    for _ in range(max(1, int(iterations))):
        if int(keep.sum()) < min_rows:
            break
        x = np.linalg.lstsq(A[keep], y[keep], rcond=None)[0]
        r = y - A @ x
        sigma = MAD_TO_SIGMA * float(np.median(np.abs(r[keep] - np.median(r[keep]))))
        new = np.abs(r) <= clip_sigma * max(sigma, sigma_floor)
        if (new == keep).all():
            break
        keep = new
    return x, keep
