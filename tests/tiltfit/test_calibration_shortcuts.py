"""The calibration's shortcuts (issue 32 §0) give what the long way gives: the per-view leverage eigenproblem from
the smaller Gram matrix, the projection σ map's Jacobian by central differences, a free board started at another
board's points."""
from __future__ import annotations

import pytest
import torch

from tiltfit.target.shape import Board, free_board_at
from tiltfit.uncertainty.covariance import _jac, _leverage_eigen


def _correction(U, lam):
    """Σ_k g_k u_k u_kᵀ with g = (1 − λ)^(−1/2) − 1 (the bias correction `view_cluster_covariance` applies)."""
    U = torch.where(lam[:, None, :] > 1e-12, U, torch.zeros_like(U))
    g = (1.0 - lam) ** -0.5 - 1.0
    return U @ (g[..., None] * U.transpose(1, 2))


def _long_way(B):
    lam_raw, Q = torch.linalg.eigh(B.transpose(1, 2) @ B)
    lam = lam_raw.clamp(0.0, 1.0 - 1e-3)
    return B @ Q / lam.clamp_min(1e-30).sqrt()[:, None, :], lam


@pytest.mark.parametrize("rows, cols", [(12, 30), (30, 12)])
def test_leverage_eigen_matches_the_global_gram_matrix(rows, cols):
    """Fewer rows than globals (a free board's views) and more: the same correction, including a view whose
    leverage is clamped below 1."""
    g = torch.Generator().manual_seed(3)
    B = 0.15 * torch.randn(4, rows, cols, generator=g, dtype=torch.float64)
    B[0] *= 4.0  # eigenvalues above 1 − 1e-3: clamped
    got, want = _correction(*_leverage_eigen(B)), _correction(*_long_way(B))
    assert torch.allclose(got, want, rtol=1e-9, atol=1e-9), \
        f"largest difference {float((got - want).abs().max()):.3g} of {float(want.abs().max()):.3g}"
    assert float(_long_way(B)[1][0].max()) == pytest.approx(1.0 - 1e-3), "the test should clamp a leverage"


def test_central_difference_jacobian_matches_autograd():
    """A smooth map with inputs of very different sizes (a focal length of 3,000 px, distortion terms near 0)."""
    x = torch.tensor([3000.0, 640.0, 0.02, -0.3, 1e-4], dtype=torch.float64)
    t = torch.linspace(-1.0, 1.0, 7, dtype=torch.float64)

    def f(p):
        return p[0] * t * (1 + p[2] * t ** 2 + p[3] * t ** 4) / (1 + p[4] * t ** 2) + p[1]

    want = torch.autograd.functional.jacobian(f, x)
    got = _jac(f, x)
    assert torch.allclose(got, want, rtol=1e-7, atol=1e-6), f"{(got - want).abs().max():.3g}"


def test_free_board_at_keeps_the_points_but_its_gauge():
    nominal = torch.stack(torch.meshgrid(torch.arange(4.0), torch.arange(3.0), indexing="xy"), -1).reshape(-1, 2) * 10
    nominal = torch.cat([nominal, torch.zeros(len(nominal), 1)], -1).double()
    warp = Board(nominal, "warp", [0.3, -0.2, 0.01])
    free = free_board_at(warp)
    moved = (free.points() - warp.points()).norm(dim=-1)
    gauge = [0, 3, len(nominal) - 1]  # the first point, the last of the first row, the last point's Z
    others = [i for i in range(len(nominal)) if i not in gauge]
    assert float(moved[others].max()) < 1e-12, f"free points moved by {float(moved[others].max()):.3g} mm"
    assert torch.allclose(free.points()[gauge[:2]], nominal[gauge[:2]]), "the gauge points stay nominal"
