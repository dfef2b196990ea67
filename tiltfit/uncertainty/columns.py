"""The fit's global columns with each view's pose profiled out, as the cluster-robust covariance
(`covariance.view_cluster_covariance`) uses them: dense (`_DenseColumns`) or, with a free board, through each
row's 3 point columns without forming the dense board block (`_PointColumns`); each view's residuals with the CR2
correction (I − H̃_vv)^(−1/2) r_v (`corrected`): from the hat block's eigenvectors (`_leverage_eigen`) where the
Gram matrix is small, by the Lanczos process on H̃_vv (`_lanczos_correction`) where it is not."""
from __future__ import annotations

import torch

#: The clamp of a view's leverages, below 1 (a view whose corners the fit follows exactly).
MAX_LEVERAGE = 1.0 - 1e-3


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

    def rows_touch(self, rows: torch.Tensor) -> bool:
        """Whether any of the rows (V, R) bool has a non-zero J̃ row."""
        return bool((self.J[rows] != 0).any())

    def hat_eigen(self, L, S_inv):
        """(U, λ) of each view's hat block H̃_vv = J̃_v S⁻¹ J̃_vᵀ = B Bᵀ (B = J̃_v L): `_leverage_eigen`."""
        return _leverage_eigen(self.right(L))

    def corrected(self, r: torch.Tensor, L, S_inv, krylov: bool = True) -> torch.Tensor:
        """(V, R) each view's residuals with the CR2 correction, (I − H̃_vv)^(−1/2) r_v, λ clamped as `_hat_eigen`
        says: from the eigenvectors of the hat block (`hat_eigen`; its Gram matrix is at most S × S here, so
        `krylov` is not needed)."""
        return _apply_correction(*self.hat_eigen(L, S_inv), r)


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
        self._P = None

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

    def _points(self) -> torch.Tensor:
        """The point columns' part of every row, E's 3 non-zeros a row, as a sparse (V·R, S) matrix (made once)."""
        if self._P is None:
            V, R, _ = self.jq.shape
            rows = torch.arange(V * R).repeat_interleave(3)
            self._P = torch.sparse_coo_tensor(torch.stack([rows, self.col.reshape(-1)]), self.jq.reshape(-1),
                                              (V * R, self.S), check_invariants=True).coalesce()
        return self._P

    def right(self, M: torch.Tensor) -> torch.Tensor:
        S0 = self.Es.shape[-1]
        if M.dim() == 2:                                                # one M for all views: one sparse product
            V, R, _ = self.Es.shape
            return (self.Es @ M[:S0] + torch.sparse.mm(self._points(), M).view(V, R, -1)
                    - self.Jp @ (self.Y @ M))
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

    def rows_touch(self, rows: torch.Tensor) -> bool:
        """Whether any of the rows (V, R) bool can have a non-zero J̃ row (J̃_i = E_i − J_p,i Y_v: E_i or J_p,i
        non-zero)."""
        return bool((self.Es[rows] != 0).any() or (self.jq[rows] != 0).any() or (self.Jp[rows] != 0).any())

    def hat_eigen(self, L, S_inv):
        """H̃_vv = F_v J̃_vᵀ with F_v = J̃_v S⁻¹, both through E_v's non-zeros: (R, R) a view (a view has at most
        3 rows a point, the board 3 parameters a point less its gauge: R is never much above S, and B = J̃_v L
        would cost R S² a view)."""
        H = self.right(self.times(S_inv).transpose(1, 2)).transpose(1, 2)
        return _hat_eigen(0.5 * (H + H.transpose(1, 2)))

    def corrected(self, r: torch.Tensor, L, S_inv, krylov: bool = True) -> torch.Tensor:
        """(V, R) (I − H̃_vv)^(−1/2) r_v by the Lanczos process on H̃_vv x = F_v (J̃_vᵀ x) (`_lanczos_correction`:
        no R × R hat block nor its eigenproblem); a view it leaves unconverged (a leverage near the clamp) from the
        hat block's eigenvectors (`hat_eigen`). `krylov` False: every view from them (where S is so badly
        conditioned that H̃_vv itself carries rounding near the recorded digits, `KRYLOV_MAX_CONDITION`, the
        products are kept in the order the hat block is formed in)."""
        if not krylov:
            return _apply_correction(*self.hat_eigen(L, S_inv), r)
        F = self.times(S_inv)
        e, done = _lanczos_correction(lambda X: (F @ self.left(X[..., None])).squeeze(-1), r)
        if not bool(done.all()):
            U, lam = self.hat_eigen(L, S_inv)
            e = torch.where(done[:, None], e, _apply_correction(U, lam, r))
        return e


def _hat_eigen(H: torch.Tensor):
    """(U, λ) of each view's hat block H (V, R, R): λ its eigenvalues clamped to [0, 1 − 1e-3], U the eigenvectors
    scaled by √(λ_raw / λ) (above 1 where λ was clamped)."""
    lam_raw, U = torch.linalg.eigh(H)                                   # (V, R), (V, R, R)
    lam = lam_raw.clamp(0.0, MAX_LEVERAGE)
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
    lam = lam_raw.clamp(0.0, MAX_LEVERAGE)
    return B @ Q / lam.clamp_min(1e-30).sqrt()[:, None, :], lam


def _correction_factor(lam: torch.Tensor) -> torch.Tensor:
    """f(λ) with (I − H̃_vv)^(−1/2) = f(H̃_vv) as `_hat_eigen` and `_apply_correction` make it: (1 − λ)^(−1/2) for λ
    in (1e-12, MAX_LEVERAGE], 1 at or below 1e-12, and above the clamp 1 + (λ / λ_c)((1 − λ_c)^(−1/2) − 1)."""
    lc = lam.clamp(0.0, MAX_LEVERAGE)
    gain = (1.0 - lc) ** -0.5 - 1.0
    return 1.0 + torch.where(lc > 1e-12, lam / lc.clamp_min(1e-30) * gain, torch.zeros_like(lam))


def _apply_correction(U: torch.Tensor, lam: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
    """(V, R) r_v + U_v diag(g) U_vᵀ r_v, g = (1 − λ)^(−1/2) − 1, from `_hat_eigen`'s or `_leverage_eigen`'s (U, λ)."""
    U = torch.where(lam[:, None, :] > 1e-12, U, torch.zeros_like(U))
    gain = (1.0 - lam) ** -0.5 - 1.0
    return r + (U @ (gain[..., None] * (U.transpose(1, 2) @ r[..., None]))).squeeze(-1)


#: The Lanczos correction is used where the Schur complement S in its diagonal scaling has a condition number below
#: this: H̃_vv = J̃_v S⁻¹ J̃_vᵀ carries rounding of about this times 1e-16 whichever way it is multiplied out (the
#: hat block formed, or its products with a vector), so above it the two ways differ in digits a record keeps
#: (industrial_ds1's refused rational free-board candidate, condition 3e12: the correction 1e-8 apart, its k4's σ
#: 1 %). Every chosen fit on the six real sets is below 3e5.
KRYLOV_MAX_CONDITION = 1e10


#: The Lanczos correction stops where one more step changes no view's result by more than this, relative to it.
LANCZOS_TOLERANCE = 1e-14
#: ... or after this many steps; the views not converged by then take the eigenproblem.
LANCZOS_STEPS = 60


def _lanczos_correction(matvec, r: torch.Tensor):
    """((V, R) f(H_v) r_v, (V,) converged) for symmetric positive semi-definite H_v of eigenvalues in [0, 1] given
    by their products `matvec` ((V, R) -> (V, R)), f `_correction_factor`: f(H) r ≈ |r| Q_k f(T_k) e₁ over the
    Krylov space of r (Q_k its orthonormal basis, fully re-orthogonalised; T_k = Q_kᵀ H Q_k tridiagonal). f is
    analytic away from λ = 1, so with the leverages of many views (λ ≲ 0.2) each step gains over a decade; near
    the clamp it is slow, and such a view is reported unconverged (its eigenproblem is the way there)."""
    V, R = r.shape
    beta0 = r.norm(dim=-1)
    Q = [r / beta0.clamp_min(1e-300)[:, None]]
    alphas, betas = [], []
    y_prev = r.new_zeros(V, 0)
    done = beta0 == 0
    y = y_prev
    for k in range(min(R, LANCZOS_STEPS)):
        w = matvec(Q[-1])
        a = (w * Q[-1]).sum(-1)
        Qk = torch.stack(Q, -1)                                        # (V, R, k + 1)
        for _ in range(2):                                              # Gram–Schmidt twice: orthogonal to rounding
            w = w - (Qk @ (Qk.transpose(1, 2) @ w[..., None])).squeeze(-1)
        alphas.append(a)
        T = torch.diag_embed(torch.stack(alphas, -1))
        if betas:
            b = torch.stack(betas, -1)
            T = T + torch.diag_embed(b, 1) + torch.diag_embed(b, -1)
        theta, Z = torch.linalg.eigh(T)
        y = Z @ (_correction_factor(theta) * Z[:, 0, :])[..., None]    # f(T) e₁, (V, k + 1, 1)
        y = y.squeeze(-1)
        step = (y[:, :-1] - y_prev).square().sum(-1) + y[:, -1].square()
        beta = w.norm(dim=-1)
        done = done | (step.sqrt() <= LANCZOS_TOLERANCE * y.norm(dim=-1)) | (beta <= 1e-13)
        if bool(done.all()):
            break
        y_prev = y
        betas.append(beta)
        Q.append(torch.where((beta > 1e-13)[:, None], w / beta.clamp_min(1e-300)[:, None], torch.zeros_like(w)))
    Qk = torch.stack(Q[:y.shape[1]], -1)
    return beta0[:, None] * (Qk @ y[..., None]).squeeze(-1), done
