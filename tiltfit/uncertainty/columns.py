"""The fit's global columns with each view's pose profiled out, as the cluster-robust covariance
(`covariance.view_cluster_covariance`) uses them: dense (`_DenseColumns`) or, with a free board, through each
row's 3 point columns without forming the dense board block (`_PointColumns`); each view's hat block's
eigenvectors (`_hat_eigen`, `_leverage_eigen`)."""
from __future__ import annotations

import torch


class _DenseColumns:
    """Each view's global columns with its pose profiled out, J̃_v = J_g,v − J_p,v Y_v (Y_v = A_vv⁻¹ A_vg), held as
    the (V, R, S) tensor, and the products with it the sandwich needs.

    Attributes: Y (V, K, S); s_idx (S,) the globals' flat positions; J (V, R, S) J̃."""

    def __init__(self, bj, a, Jp, App_inv):
        Js = (bj.Js * a[:, None])[bj.rows]                              # (V, R, S)
        self.Y = App_inv @ (Jp.transpose(1, 2) @ Js)                    # (V, K, S)
        self.J = Js - Jp @ self.Y
        self.s_idx = bj.s_idx
        self._F = None

    def times(self, S_inv: torch.Tensor) -> torch.Tensor:
        """(V, R, S) J̃_v S⁻¹, made once (the leverages and the poses' part both read it)."""
        if self._F is None:
            self._F = self.right(S_inv)
        return self._F

    def gram(self) -> torch.Tensor:
        """(S, S) Σ_v J̃_vᵀ J̃_v, the Schur complement of the poses."""
        return (self.J.transpose(1, 2) @ self.J).sum(0)

    def right(self, M: torch.Tensor) -> torch.Tensor:
        """J̃_v M for M (S, n) or (V, S, n): (V, R, n)."""
        return self.J @ M

    def left(self, Z: torch.Tensor) -> torch.Tensor:
        """J̃_vᵀ Z_v for Z (V, R, m): (V, S, m)."""
        return self.J.transpose(1, 2) @ Z

    def rowdot(self, F: torch.Tensor) -> torch.Tensor:
        """(V, R) each row of F (V, R, S) dotted with the same row of J̃."""
        return (F * self.J).sum(-1)

    def hat_eigen(self, L, S_inv):
        """(U, λ) of each view's hat block H̃_vv = J̃_v S⁻¹ J̃_vᵀ = B Bᵀ (B = J̃_v L): `_leverage_eigen`."""
        return _leverage_eigen(self.right(L))


class _PointColumns(_DenseColumns):
    """J̃_v of a Jacobian with a point block (a free board): the global columns are the lens's (S₀, dense) and the
    points' free coordinates, of which row i touches only its own point's 3 (`BlockJacobian.Jq`). J̃_v = E_v −
    J_p,v Y_v is never formed: the products go through E_v's 3 non-zeros a row (gathers and scatters) and the
    rank-K pose part, so a product J̃_v M costs R (S₀ + 3 + K) n instead of R S n (S = S₀ + 3N − gauge)."""

    def __init__(self, bj, a, Jp, App_inv):
        free = bj.q_idx >= 0
        cols = bj.q_idx[free]
        order = torch.argsort(cols)
        self.s_idx = torch.cat([bj.s_idx, cols[order]])
        S0, Q = bj.s_idx.numel(), cols.numel()
        self.S = S0 + Q
        col = torch.zeros_like(bj.q_idx)                                # each coordinate's global column
        col[free] = S0 + torch.argsort(order)
        self.Es = (bj.Js * a[:, None])[bj.rows]                         # (V, R, S₀)
        self.jq = (bj.Jq * a[:, None])[bj.rows]                         # (V, R, 3), 0 at gauge coordinates
        self.col = col[bj.row_points][bj.rows]                          # (V, R, 3)
        self.Jp = Jp
        self.Y = App_inv @ self._e_left(Jp).transpose(1, 2)             # (V, K, S)
        self.App = Jp.transpose(1, 2) @ Jp
        self._F = None

    def _e_left(self, Z: torch.Tensor) -> torch.Tensor:
        """E_vᵀ Z_v for Z (V, R, m): (V, S, m)."""
        V, R, m = Z.shape
        out = Z.new_zeros(V, self.S, m)
        if m == 0:                                                      # e.g. no pose columns: nothing to add
            return out
        out[:, :self.Es.shape[-1]] = self.Es.transpose(1, 2) @ Z
        idx = (self.col + self.S * torch.arange(V)[:, None, None]).reshape(-1)
        out.view(V * self.S, m).index_add_(0, idx, (self.jq[..., None] * Z[:, :, None, :]).reshape(-1, m))
        return out

    def gram(self) -> torch.Tensor:
        """Σ_v E_vᵀ E_v − Y_vᵀ A_vv Y_v (E_vᵀ J_p,v = A_vv Y_v)."""
        S0 = self.Es.shape[-1]
        G = self.Es.new_zeros(self.S, self.S)
        Es = self.Es.flatten(0, 1)                                     # (V·R, S₀), S₀ may be 0
        G[:S0, :S0] = Es.T @ Es
        sq = self._e_left(self.Es)[:, S0:].sum(0)                       # (Q, S₀) the points' rows against the lens
        G[S0:, :S0] = sq
        G[:S0, S0:] = sq.T
        ci, cj = self.col[..., :, None].expand(-1, -1, 3, 3), self.col[..., None, :].expand(-1, -1, 3, 3)
        G.index_put_((ci.reshape(-1), cj.reshape(-1)),
                     (self.jq[..., :, None] * self.jq[..., None, :]).reshape(-1), accumulate=True)
        return G - (self.Y.transpose(1, 2) @ self.App @ self.Y).sum(0)

    def right(self, M: torch.Tensor) -> torch.Tensor:
        S0 = self.Es.shape[-1]
        out = []
        for v in range(self.Es.shape[0]):                               # one view at a time: gathers of (R, 3, n)
            Mv = M if M.dim() == 2 else M[v]
            out.append(self.Es[v] @ Mv[:S0] + torch.bmm(self.jq[v][:, None, :], Mv[self.col[v]]).squeeze(1)
                       - self.Jp[v] @ (self.Y[v] @ Mv))
        return torch.stack(out)

    def left(self, Z: torch.Tensor) -> torch.Tensor:
        return self._e_left(Z) - self.Y.transpose(1, 2) @ (self.Jp.transpose(1, 2) @ Z)

    def rowdot(self, F: torch.Tensor) -> torch.Tensor:
        S0 = self.Es.shape[-1]
        return (F[..., :S0] * self.Es).sum(-1) + (torch.gather(F, 2, self.col) * self.jq).sum(-1) \
            - ((F @ self.Y.transpose(1, 2)) * self.Jp).sum(-1)

    def hat_eigen(self, L, S_inv):
        """H̃_vv = F_v J̃_vᵀ with F_v = J̃_v S⁻¹, both through E_v's non-zeros: (R, R) a view (a view has at most
        3 rows a point, the board 3 parameters a point less its gauge: R is never much above S, and B = J̃_v L
        would cost R S² a view)."""
        H = self.right(self.times(S_inv).transpose(1, 2)).transpose(1, 2)
        return _hat_eigen(0.5 * (H + H.transpose(1, 2)))


def _hat_eigen(H: torch.Tensor):
    """(U, λ) of each view's hat block H (V, R, R): λ its eigenvalues clamped to [0, 1 − 1e-3], U the eigenvectors
    scaled by √(λ_raw / λ) (above 1 where λ was clamped)."""
    lam_raw, U = torch.linalg.eigh(H)                                   # (V, R), (V, R, R)
    lam = lam_raw.clamp(0.0, 1.0 - 1e-3)
    return U * (lam_raw.clamp_min(0.0) / lam.clamp_min(1e-30)).sqrt()[:, None, :], lam


def _leverage_eigen(B: torch.Tensor):
    """(U, λ) of each view's H̃_vv = B Bᵀ (B: (V, R, S)): λ its eigenvalues clamped to [0, 1 − 1e-3] and U the
    matching eigenvectors scaled as B Q / √λ (Q the eigenvectors of Bᵀ B), so √(λ_raw / λ) above 1 where λ was
    clamped. From the smaller Gram matrix: Bᵀ B (S × S) or, where a view has fewer rows than global
    parameters (a free board: R = 2N rows, S ≈ 3N), B Bᵀ (R × R) itself, which has the same non-zero
    eigenvalues."""
    if B.shape[1] < B.shape[2]:
        return _hat_eigen(B @ B.transpose(1, 2))
    lam_raw, Q = torch.linalg.eigh(B.transpose(1, 2) @ B)                  # (V, S), (V, S, S)
    lam = lam_raw.clamp(0.0, 1.0 - 1e-3)
    return B @ Q / lam.clamp_min(1e-30).sqrt()[:, None, :], lam
