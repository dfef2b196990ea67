"""Normal equations with a third kind of parameter block: per-point blocks, eliminated as bundle adjustment does.

A point block (`blocks.Block` with `points`) holds up to 3 numbers for each of N points (a free board's target
points, OpenCV's release-object method), and residual row i depends only on the point of row i (`row_points`):
its Jacobian is kept as (M, 3), the derivatives with respect to the 3 coordinates of row i's own point, never as
the dense (M, 3N) block. Coordinates fixed by a gauge have no parameter (index −1 in `Block.points`): their
columns are zero and they are left out of the flat vector.

With z the global and per-view parameters (S + V·K of them) and q the points (3N), the normal matrix is
    A = [[A_zz, A_zq], [A_qz, A_qq]],  A_qq block diagonal (one 3×3 block per point),
and the damped system is reduced to z by the Schur complement of the points (Triggs et al., "Bundle
adjustment — a modern synthesis", 2000, §6.1; the "reduced camera system"):
    (A_zz − A_zq A_qq⁻¹ A_qz) δ_z = g_z − A_zq A_qq⁻¹ g_q,   then δ_q = A_qq⁻¹ (g_q − A_qz δ_z).
Every point is seen in every view, so the reduced system couples all poses and is solved as one dense
(S + V·K) system: O(M (S + K + 3)² + (S + V·K)² · 3N + (S + V·K)³) where a dense board block costs
O(M (S + 3N)²) an iteration.
"""
from __future__ import annotations

import torch

from .blocks import BlockJacobian, DenseNormal, SchurNormal, _rows_in_order


def _row_views(rows: torch.Tensor, n_rows: int) -> torch.Tensor:
    """(M,) long, the view of each residual row (from (V, R) rows of each view)."""
    out = torch.full((n_rows,), -1, dtype=torch.long)
    out[rows] = torch.arange(rows.shape[0])[:, None].expand_as(rows)
    return out


def _rows_by_point(rows: torch.Tensor, row_points: torch.Tensor, n_points: int) -> torch.Tensor | None:
    """(V, N, c) long: each view's rows grouped by their point, where every point has the same number c of rows in
    every view (a calibration's: its 2 corner rows, and its blur row where widths are fitted; rows of unobserved
    corners are there with zero Jacobian rows); None otherwise."""
    V, R = rows.shape
    if R % n_points:
        return None
    c = R // n_points
    rp = row_points[rows]                                                           # (V, R)
    order = torch.argsort(rp, dim=1, stable=True)
    grouped = torch.gather(rp, 1, order).view(V, n_points, c)
    if not bool((grouped == torch.arange(n_points)[None, :, None]).all()):
        return None
    return torch.gather(rows, 1, order).view(V, n_points, c)


def _in_order(rows: torch.Tensor, row_points: torch.Tensor, n_points: int) -> bool:
    """Whether the rows are 0 … M − 1 view after view, each view's grouped by point in order (c rows a point: a
    geometric calibration's corner rows u, v), so that (V, N, c) views of (M, …) tensors are its rows by point."""
    V, R = rows.shape
    if R % n_points or not _rows_in_order(rows, row_points.numel()):
        return False
    points = torch.arange(n_points, dtype=row_points.dtype)[None, :, None].expand(V, n_points, R // n_points)
    return torch.equal(row_points.view(V, n_points, -1), points)


def _point_products(bj, Jqw: torch.Tensor):
    """The point block's normal-matrix blocks: A_qq (N, 3, 3), A_sq (N, S, 3) against the globals and A_pq
    (V, N, K, 3) against each view's pose. Where each point has the same rows in every view (`_rows_by_point`),
    as batched products over the views' rows of each point; otherwise summed row by row (`index_add_`)."""
    N = bj.q_idx.shape[0]
    V, K = bj.p_idx.shape
    in_order = _in_order(bj.rows, bj.row_points, N)  # a geometric fit's rows: (V, N, c) views, no copies
    grouped = None if in_order else _rows_by_point(bj.rows, bj.row_points, N)
    if in_order or grouped is not None:
        if in_order:
            shape = (V, N, bj.rows.shape[1] // N)
            Jq, Jqw_g, Js, Jp = (t.view(shape + t.shape[1:]) for t in (bj.Jq, Jqw, bj.Js, bj.Jp))
        else:
            Jq, Jqw_g, Js, Jp = bj.Jq[grouped], Jqw[grouped], bj.Js[grouped], bj.Jp[grouped]   # (V, N, c, ·)
        return (torch.einsum("vnci,vncj->nij", Jq, Jqw_g), torch.einsum("vncs,vncj->nsj", Js, Jqw_g),
                torch.einsum("vnck,vncj->vnkj", Jp, Jqw_g))
    rp, Jq, S = bj.row_points, bj.Jq, bj.Js.shape[1]
    rv = _row_views(bj.rows, bj.Js.shape[0])
    A_qq = Jq.new_zeros(N, 3, 3).index_add_(0, rp, Jq[:, :, None] * Jqw[:, None, :])
    A_sq = Jq.new_zeros(N, S, 3).index_add_(0, rp, bj.Js[:, :, None] * Jqw[:, None, :])
    A_pq = Jq.new_zeros(V * N, K, 3).index_add_(0, rv * N + rp, bj.Jp[:, :, None] * Jqw[:, None, :])
    return A_qq, A_sq, A_pq.view(V, N, K, 3)


class PointSchurNormal:
    """Normal equations of a `blocks.BlockJacobian` with a point block (`Jq`, `row_points`, `q_idx`), solved by
    eliminating the points' 3×3 blocks (module docstring). Same interface as `blocks.SchurNormal`."""

    def __init__(self, bj, wts: torch.Tensor):
        self.bj = bj
        self.wts = wts
        self.base = SchurNormal(bj, wts)                           # the z part: A_ss, A_sp, A_pp
        V, K = bj.p_idx.shape
        S = bj.s_idx.numel()
        N = bj.q_idx.shape[0]
        self.V, self.K, self.S, self.N = V, K, S, N
        self.Z = S + V * K
        self.z_idx = torch.cat([bj.s_idx, bj.p_idx.reshape(-1)])
        self.fixed = bj.q_idx < 0                                   # (N, 3) gauge coordinates
        Jq, Jqw = bj.Jq, bj.Jq * wts[:, None]
        self.Jqw = Jqw
        self.A_qq, A_sq, A_pq = _point_products(bj, Jqw)
        self.A_zq = torch.cat([A_sq.permute(1, 0, 2).reshape(S, 3 * N),
                               A_pq.permute(0, 2, 1, 3).reshape(V * K, 3 * N)])                  # (Z, 3N)
        A_zz = Jq.new_zeros(self.Z, self.Z)
        b = self.base
        A_zz[:S, :S] = b.A_ss
        A_zz[:S, S:] = b.A_sp.permute(1, 0, 2).reshape(S, V * K)
        A_zz[S:, :S] = A_zz[:S, S:].T
        pp = A_zz[S:, S:].view(V, K, V, K)
        pp[torch.arange(V), :, torch.arange(V), :] = b.A_pp
        self.A_zz = A_zz

    # --- the flat vector's parts ---------------------------------------------------------------------------
    def _split(self, v: torch.Tensor):
        """(P, ...) -> z part (Z, ...), q part (N, 3, ...) (0 at gauge coordinates)."""
        q = v[self.bj.q_idx.clamp_min(0)]
        return v[self.z_idx], torch.where(self.fixed.reshape(self.fixed.shape + (1,) * (v.dim() - 1)), 0.0, q)

    def _join(self, vz: torch.Tensor, vq: torch.Tensor) -> torch.Tensor:
        out = vz.new_zeros((self.bj.n_params,) + vz.shape[1:])
        out[self.z_idx] = vz
        free = ~self.fixed
        out[self.bj.q_idx[free]] = vq[free]
        return out

    def _inv_qq(self, dq: torch.Tensor) -> torch.Tensor:
        """(N, 3, 3) (A_qq + diag(dq))⁻¹, the gauge coordinates' rows and columns the identity."""
        return torch.linalg.inv(self.A_qq + torch.diag_embed(dq + self.fixed.to(dq.dtype)))

    # --- the interface of blocks.SchurNormal --------------------------------------------------------------
    def gradient(self, r: torch.Tensor) -> torch.Tensor:
        """Jᵀ W r."""
        g = self.base.gradient(r)
        gq = self.Jqw.new_zeros(self.N, 3).index_add_(0, self.bj.row_points, self.Jqw * r[:, None])
        return self._join(g[self.z_idx], gq)

    def diag(self) -> torch.Tensor:
        return self._join(torch.diagonal(self.A_zz), torch.diagonal(self.A_qq, dim1=-2, dim2=-1))

    def matvec(self, v: torch.Tensor) -> torch.Tensor:
        vz, vq = self._split(v)
        q = vq.reshape(-1)
        out_z = self.A_zz @ vz + self.A_zq @ q
        out_q = (self.A_zq.T @ vz).view(self.N, 3) + (self.A_qq @ vq[..., None]).squeeze(-1)
        return self._join(out_z, out_q)

    def _reduce(self, dz: torch.Tensor, dq: torch.Tensor):
        """(A_qq⁻¹ damped (N, 3, 3), A_zq A_qq⁻¹ (Z, 3N), the reduced matrix (Z, Z))."""
        Q_inv = self._inv_qq(dq)
        AQ = torch.einsum("zni,nij->znj", self.A_zq.view(self.Z, self.N, 3), Q_inv).reshape(self.Z, 3 * self.N)
        H = self.A_zz + torch.diag(dz) - AQ @ self.A_zq.T
        return Q_inv, AQ, H

    def solve(self, damping: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
        """(A + diag(damping))⁻¹ rhs by the Schur complement of the points."""
        dz, dq = self._split(damping)
        gz, gq = self._split(rhs)
        Q_inv, AQ, H = self._reduce(dz, dq)
        xz = torch.linalg.solve(H, gz - AQ @ gq.reshape(-1))
        xq = (Q_inv @ (gq - (self.A_zq.T @ xz).view(self.N, 3))[..., None]).squeeze(-1)
        return self._join(xz, xq)

    def dense(self) -> torch.Tensor:
        """(P, P) A (P² memory)."""
        P = self.bj.n_params
        A = self.A_zz.new_zeros(P + 1, P + 1)                        # the last row and column take the gauge's
        qi = torch.where(self.fixed, P, self.bj.q_idx).reshape(-1)
        A[self.z_idx[:, None], self.z_idx[None, :]] = self.A_zz
        A[self.z_idx[:, None], qi[None, :]] = self.A_zq
        A[qi[:, None], self.z_idx[None, :]] = self.A_zq.T
        blk = qi.view(self.N, 3)
        A[blk[:, :, None], blk[:, None, :]] = self.A_qq
        return A[:P, :P]

    def covariance(self) -> "PointCovariance":
        """A⁻¹ by its blocks (`PointCovariance`). Raises RuntimeError where A is singular."""
        zero = self.A_zz.new_zeros(self.N, 3)
        Q_inv, AQ, H = self._reduce(self.A_zz.new_zeros(self.Z), zero)
        return PointCovariance(torch.linalg.inv(H), Q_inv, AQ, self.z_idx, self.bj.q_idx, self.bj.n_params)

    def leverages(self, cov) -> torch.Tensor:
        """(M,) diagonal of the hat matrix W J A⁻¹ Jᵀ: row i (view v, point n) touches A⁻¹'s blocks of the
        globals, view v's pose and point n. `cov` another covariance (a pseudo-inverse's `DenseCovariance`, where A
        is singular): through the dense Jacobian."""
        if not isinstance(cov, PointCovariance):
            J = self.bj.dense()
            return self.wts * ((J @ cov.dense()) * J).sum(-1)
        bj, S, K, N = self.bj, self.S, self.K, self.N
        Cz = cov.Cz
        rv = _row_views(bj.rows, bj.Js.shape[0])
        rp = bj.row_points
        V = self.V
        C_ss = Cz[:S, :S]
        C_sv = Cz[:S, S:].view(S, V, K).permute(1, 0, 2)                # (V, S, K)
        C_vv = Cz[S:, S:].view(V, K, V, K)[torch.arange(V), :, torch.arange(V), :]   # (V, K, K)
        F = -(Cz @ cov.AQ).view(self.Z, N, 3)                           # (A⁻¹)_zq
        F_s = F[:S].permute(1, 0, 2)                                    # (N, S, 3)
        F_v = F[S:].view(V, K, N, 3).permute(0, 2, 1, 3)                # (V, N, K, 3)
        C_qq = cov.point_blocks()                                       # (N, 3, 3)
        js, jp, jq = bj.Js, bj.Jp, bj.Jq
        q = ((js @ C_ss) * js).sum(-1) \
            + 2 * (torch.einsum("ms,msk->mk", js, C_sv[rv]) * jp).sum(-1) \
            + (torch.einsum("mk,mkl->ml", jp, C_vv[rv]) * jp).sum(-1) \
            + 2 * (torch.einsum("ms,msc->mc", js, F_s[rp]) * jq).sum(-1) \
            + 2 * (torch.einsum("mk,mkc->mc", jp, F_v[rv, rp]) * jq).sum(-1) \
            + (torch.einsum("mc,mcd->md", jq, C_qq[rp]) * jq).sum(-1)
        return self.wts * q


class PointCovariance:
    """A⁻¹ of normal equations with a point block, kept as the blocks that define it: with Cz the inverse of the
    reduced system (Z, Z) and AQ = A_zq A_qq⁻¹,
        (A⁻¹)_zz = Cz,  (A⁻¹)_zq = −Cz AQ,  (A⁻¹)_qq = A_qq⁻¹ + AQᵀ Cz AQ.
    Methods as `blocks.SchurCovariance`: diagonal, matmul, submatrix, dense, scaled; `point_blocks` the
    points' own 3×3 blocks.

    Attributes:
        Cz: (Z, Z); Q_inv: (N, 3, 3); AQ: (Z, 3N); z_idx (Z,), q_idx (N, 3) (−1: gauge): flat positions;
        n_params: P.
    """

    def __init__(self, Cz, Q_inv, AQ, z_idx, q_idx, n_params: int):
        self.Cz, self.Q_inv, self.AQ = Cz, Q_inv, AQ
        self.z_idx, self.q_idx, self.n_params = z_idx, q_idx, n_params
        self.fixed = q_idx < 0

    def point_blocks(self) -> torch.Tensor:
        """(N, 3, 3) (A⁻¹)_qq's diagonal blocks (gauge rows and columns 0)."""
        N = self.q_idx.shape[0]
        AQ = self.AQ.view(-1, N, 3)
        C = self.Q_inv + torch.einsum("zni,zy,ynj->nij", AQ, self.Cz, AQ)
        keep = (~self.fixed).to(C.dtype)
        return C * keep[:, :, None] * keep[:, None, :]

    def diagonal(self) -> torch.Tensor:
        """(P,) the variances."""
        out = self.Cz.new_zeros(self.n_params)
        out[self.z_idx] = torch.diagonal(self.Cz)
        d = torch.diagonal(self.point_blocks(), dim1=-2, dim2=-1)
        out[self.q_idx[~self.fixed]] = d[~self.fixed]
        return out

    def matmul(self, X: torch.Tensor) -> torch.Tensor:
        """A⁻¹ X for X (P, n): t = Cz (X_z − AQ X_q), then (A⁻¹X)_z = t, (A⁻¹X)_q = A_qq⁻¹ X_q − AQᵀ t."""
        N = self.q_idx.shape[0]
        xz = X[self.z_idx]
        xq = torch.where(self.fixed[..., None], 0.0, X[self.q_idx.clamp_min(0)])      # (N, 3, n)
        t = self.Cz @ (xz - self.AQ @ xq.reshape(3 * N, -1))
        out_q = self.Q_inv @ xq - (self.AQ.T @ t).view(N, 3, -1)
        out = X.new_zeros(self.n_params, X.shape[1])
        out[self.z_idx] = t
        out[self.q_idx[~self.fixed]] = out_q[~self.fixed]
        return out

    def submatrix(self, idx) -> torch.Tensor:
        """(n, n) the entries of the flat positions idx."""
        idx = torch.as_tensor(idx, dtype=torch.long)
        E = self.Cz.new_zeros(self.n_params, idx.numel())
        E[idx, torch.arange(idx.numel())] = 1.0
        return self.matmul(E)[idx]

    def dense(self) -> torch.Tensor:
        """(P, P) A⁻¹ (P² memory: tests and small problems)."""
        return self.matmul(torch.eye(self.n_params, dtype=self.Cz.dtype))

    def scaled(self, factor: float) -> "PointCovariance":
        """factor · A⁻¹ (AQ does not change)."""
        return PointCovariance(self.Cz * factor, self.Q_inv * factor, self.AQ, self.z_idx, self.q_idx,
                               self.n_params)


def normal_equations(J, wts: torch.Tensor):
    """`SchurNormal` of a `BlockJacobian` (`PointSchurNormal` with a point block), `DenseNormal` of a dense
    (M, P) tensor."""
    if not isinstance(J, BlockJacobian):
        return DenseNormal(J, wts)
    if J.Jq is not None:
        return PointSchurNormal(J, wts)
    return SchurNormal(J, wts)
