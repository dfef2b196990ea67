"""Named parameter blocks, the flat vector they form, and the normal equations of their Jacobian.

A least-squares problem's parameters are named blocks (`Block`): a global block is shared by every residual
(a lens's focal length, its distortion coefficients); a per-view block holds one small vector per view (a
pose), and view v's residual rows depend only on view v's vector. The flat parameter vector is the blocks in
the order given, each flattened row-major, so a per-view block of shape (V, K) is view-major, as
`torch.nn.Parameter`s of the same shapes flatten (`Layout`).

With per-view blocks the normal equations A = Jᵀ W J have the arrow structure of bundle adjustment: the
per-view part is block diagonal (one K×K block per view) and is eliminated by the Schur complement
(Triggs et al., "Bundle adjustment — a modern synthesis", 2000, §6.1), so a solve costs
O(M (S + K)² + V K³ + S³) instead of O(M P² + P³) for M residuals, S global and P = S + V K parameters
(`SchurNormal`; `DenseNormal` without per-view blocks). A point block (a free board's target points) holds up
to 3 numbers for each point, and row i depends only on its own point: its Jacobian stays (M, 3) and the points
are eliminated like bundle adjustment's (`tiltfit.solve.points`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
import torch


@dataclass(frozen=True)
class Block:
    """A named block of parameters.

    Attributes:
        name: the block's name (the key of the state dict and of the Jacobian dict).
        shape: the block's tensor shape; for a per-view block (V, K).
        per_view: each view has its own row of the block, and only that view's residuals depend on it.
        points: for a point block, (N, 3) long: the position in the block of each point's x, y, z, or −1 where a
            gauge fixes it; residual row i depends only on the 3 coordinates of its point (`Layout`'s
            `row_points`), and the callback's Jacobian of the block is (M, 3). None: not a point block.
    """

    name: str
    shape: tuple
    per_view: bool = False
    points: object = field(default=None, compare=False)

    @property
    def size(self) -> int:
        """Numbers per instance: K for a per-view block, all of them for a global one."""
        dims = self.shape[1:] if self.per_view else self.shape
        return int(math.prod(dims))


def side_by_side(columns: list) -> list:
    """Column blocks (..., k_i) in order, each run of blocks that lie side by side in one tensor's memory (the
    distortion coefficients' columns are slices of one (V, N, 3, 8) tensor) joined into one view of that memory.

    The views hold the same numbers; each strided copy into the Jacobian costs about as much for one column as
    for eight, so fewer, wider blocks are cheaper, and blocks of one matrix side by side need no copy at all."""
    joined = []
    for block in columns:
        if joined:
            last = joined[-1]
            if (block.dim() == last.dim() and block.shape[:-1] == last.shape[:-1] and block.stride() == last.stride()
                    and block.stride(-1) == 1 and block.dtype == last.dtype
                    and block.untyped_storage().data_ptr() == last.untyped_storage().data_ptr()
                    and block.storage_offset() == last.storage_offset() + last.shape[-1]):
                joined[-1] = last.as_strided(last.shape[:-1] + (last.shape[-1] + block.shape[-1],), last.stride(),
                                             last.storage_offset())
                continue
        joined.append(block)
    return joined


def _joined(columns: list) -> torch.Tensor:
    """Column blocks (M, k_i) side by side as one (M, Σ k_i) tensor: a view where they lie side by side in one
    tensor's memory (`side_by_side`), else a copy."""
    runs = side_by_side(columns)
    return runs[0] if len(runs) == 1 else torch.cat(runs, 1)


def _rows_in_order(rows: torch.Tensor, n_rows: int) -> bool:
    """Whether the views' rows (V, R) are all `n_rows` rows in order (view 0's, then view 1's, …): a geometric fit's,
    whose rows are each view's corners. Then each view's rows of a matrix are a reshape of it, not a gather."""
    return rows.numel() == n_rows and bool((rows.reshape(-1) == torch.arange(n_rows)).all())


class Layout:
    """The flat parameter vector of named blocks, and which residual rows belong to which view.

    Args:
        blocks: the blocks, in flat order.
        view_rows: (V, R) long, the residual rows of each view (needed when a block is per view).
        row_points: (M,) long, the point of each residual row (needed with a point block, which needs per-view
            blocks too).
    """

    def __init__(self, blocks, view_rows: torch.Tensor | None = None, row_points: torch.Tensor | None = None):
        self.blocks = tuple(blocks)
        if not self.blocks:
            raise ValueError("blocks: expected at least one parameter block")
        names = [b.name for b in self.blocks]
        if len(set(names)) != len(names):
            raise ValueError(f"blocks: duplicate names in {names}")
        self.view_blocks = tuple(b for b in self.blocks if b.per_view)
        self.point_blocks = tuple(b for b in self.blocks if b.points is not None)
        self.global_blocks = tuple(b for b in self.blocks if not b.per_view and b.points is None)
        if self.point_blocks and (len(self.point_blocks) > 1 or not self.view_blocks or row_points is None):
            raise ValueError("a point block: at most one, beside per-view blocks, with row_points")
        self.row_points = row_points
        if self.view_blocks and view_rows is None:
            raise ValueError("view_rows: needed for per-view blocks")
        n_views = {b.shape[0] for b in self.view_blocks}
        if len(n_views) > 1:
            raise ValueError(f"per-view blocks disagree on the number of views: {sorted(n_views)}")
        self.n_views = n_views.pop() if n_views else 0
        if self.view_blocks and view_rows.shape[0] != self.n_views:
            raise ValueError(f"view_rows: expected {self.n_views} views, got {view_rows.shape[0]}")
        self.view_rows = view_rows
        self.offsets, i = {}, 0
        for b in self.blocks:
            n = int(math.prod(b.shape))
            self.offsets[b.name] = (i, n)
            i += n
        self.n_params = i
        V = self.n_views
        self.s_idx = torch.cat([torch.arange(self.offsets[b.name][0], sum(self.offsets[b.name]))
                                for b in self.global_blocks]) if self.global_blocks \
            else torch.zeros(0, dtype=torch.long)
        self.p_idx = torch.cat([self.offsets[b.name][0] + b.size * torch.arange(V)[:, None] + torch.arange(b.size)
                                for b in self.view_blocks], 1) if self.view_blocks else None
        self.q_idx = None
        if self.point_blocks:
            b = self.point_blocks[0]
            pts = torch.as_tensor(b.points, dtype=torch.long)
            self.q_idx = torch.where(pts >= 0, self.offsets[b.name][0] + pts, -1)
            self._row_point_free = (pts >= 0)[row_points]                  # (M, 3): 0 at gauge coordinates

    def flatten(self, x: dict) -> torch.Tensor:
        """{name: tensor} -> (P,) flat vector."""
        return torch.cat([x[b.name].reshape(-1) for b in self.blocks])

    def unflatten(self, v: torch.Tensor) -> dict:
        """(P,) flat vector -> {name: tensor of the block's shape} (views into `v`)."""
        return {b.name: v[self.offsets[b.name][0]:sum(self.offsets[b.name])].reshape(b.shape) for b in self.blocks}

    def flat_names(self) -> list[str]:
        """Names of the flat vector's entries: `name` for a scalar block, `name[i,j]` otherwise."""
        out = []
        for b in self.blocks:
            if len(b.shape) == 0:
                out.append(b.name)
            else:
                out += [f"{b.name}[{','.join(map(str, idx))}]" for idx in np.ndindex(*b.shape)]
        return out

    def jacobian(self, jac: dict) -> "BlockJacobian | torch.Tensor":
        """Assemble a callback's Jacobian {name: (M, size)} into a `BlockJacobian` (per-view blocks: row i
        holds the derivatives with respect to the block of row i's view) or a dense (M, P) tensor."""
        Js = _joined([jac[b.name] for b in self.global_blocks]) if self.global_blocks else None
        if not self.view_blocks:
            return Js
        Jp = _joined([jac[b.name] for b in self.view_blocks])
        if Js is None:
            Js = Jp.new_zeros(Jp.shape[0], 0)
        if not self.point_blocks:
            return BlockJacobian(Js, Jp, self.view_rows, self.s_idx, self.p_idx, self.n_params)
        Jq = jac[self.point_blocks[0].name] * self._row_point_free
        return BlockJacobian(Js, Jp, self.view_rows, self.s_idx, self.p_idx, self.n_params, Jq, self.row_points,
                             self.q_idx)


@dataclass
class BlockJacobian:
    """A Jacobian with the multi-view block structure: each view's block touches only its own residual rows.

    Attributes:
        Js: (M, S) columns of the global parameters.
        Jp: (M, K) columns of the per-view parameters: row i holds the derivatives with respect to the block of
            the view that row i belongs to.
        rows: (V, R) long, the residual rows of each view.
        s_idx: (S,) long, positions of the global parameters in the flat parameter vector.
        p_idx: (V, K) long, positions of each view's parameters.
        n_params: P = S + V·K (+ the point block's).
        Jq: (M, 3) or None: columns of a point block, row i's derivatives with respect to its own point's
            coordinates (0 at gauge coordinates); row_points: (M,) long, the point of each row; q_idx: (N, 3) long,
            positions of each point's coordinates (−1: fixed by the gauge).
    """

    Js: torch.Tensor
    Jp: torch.Tensor
    rows: torch.Tensor
    s_idx: torch.Tensor
    p_idx: torch.Tensor
    n_params: int
    Jq: torch.Tensor | None = None
    row_points: torch.Tensor | None = None
    q_idx: torch.Tensor | None = None

    def dense(self) -> torch.Tensor:
        """(M, P) the full Jacobian."""
        J = self.Js.new_zeros(self.Js.shape[0], self.n_params + 1)
        J[:, self.s_idx] = self.Js
        J[self.rows[:, :, None], self.p_idx[:, None, :]] = self.Jp[self.rows]
        if self.Jq is not None:
            J[torch.arange(J.shape[0])[:, None], self._point_columns()] = self.Jq
        return J[:, :self.n_params]

    def _point_columns(self) -> torch.Tensor:
        """(M, 3) each row's point columns in the flat vector (n_params for gauge coordinates)."""
        return torch.where(self.q_idx < 0, self.n_params, self.q_idx)[self.row_points]

    def scaled(self, factor) -> "BlockJacobian":
        """The Jacobian times `factor` (a scalar or (M,) per row)."""
        f = factor[:, None] if torch.is_tensor(factor) and factor.dim() == 1 else factor
        return replace(self, Js=self.Js * f, Jp=self.Jp * f, Jq=None if self.Jq is None else self.Jq * f)


class DenseNormal:
    """Normal equations A = Jᵀ W J of a dense Jacobian (M, P); W = diag(wts)."""

    def __init__(self, J: torch.Tensor, wts: torch.Tensor):
        self.J = J
        self.Jw = J * wts[:, None]
        self.A = J.T @ self.Jw

    def gradient(self, r: torch.Tensor) -> torch.Tensor:
        """Jᵀ W r."""
        return self.Jw.T @ r

    def diag(self) -> torch.Tensor:
        return torch.diagonal(self.A)

    def matvec(self, v: torch.Tensor) -> torch.Tensor:
        return self.A @ v

    def solve(self, damping: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
        """(A + diag(damping))⁻¹ rhs."""
        return torch.linalg.solve(self.A + torch.diag(damping), rhs)

    def dense(self) -> torch.Tensor:
        """(P, P) A."""
        return self.A

    def covariance(self) -> "DenseCovariance":
        """A⁻¹ (raises RuntimeError where A is singular)."""
        return DenseCovariance(torch.linalg.inv(self.A))

    def leverages(self, cov: "DenseCovariance") -> torch.Tensor:
        """(M,) diagonal of the hat matrix W J A⁻¹ Jᵀ (each residual's share of the fitted parameters)."""
        return ((self.Jw @ cov.dense()) * self.J).sum(-1)


class SchurNormal:
    """Normal equations of a `BlockJacobian`, solved by the Schur complement of the per-view blocks.

    With A = [[A_ss, A_sp], [A_ps, A_pp]] where A_pp is block diagonal (one K×K block per view), the damped
    system is reduced to the global parameters:
        (A_ss − Σ_v A_sv A_vv⁻¹ A_vs) δ_s = g_s − Σ_v A_sv A_vv⁻¹ g_v,
    then δ_v = A_vv⁻¹ (g_v − A_vs δ_s).
    """

    def __init__(self, bj: BlockJacobian, wts: torch.Tensor):
        self.bj = bj
        self.w = wts
        self.Jsw = bj.Js * wts[:, None]
        self.A_ss = bj.Js.T @ self.Jsw
        self._in_order = _rows_in_order(bj.rows, bj.Js.shape[0])
        self.Jp_v = self._by_view(bj.Jp)                 # (V, R, K)
        self.w_v = self._by_view(wts)                    # (V, R)
        self.Js_v = self._by_view(bj.Js)                 # (V, R, S)
        Jpw_v = self.Jp_v * self.w_v[..., None]
        self.A_pp = Jpw_v.transpose(1, 2) @ self.Jp_v    # (V, K, K)
        self.A_sp = self.Js_v.transpose(1, 2) @ Jpw_v    # (V, S, K)

    def _by_view(self, rows: torch.Tensor) -> torch.Tensor:
        """(M, ...) rows -> (V, R, ...) each view's (a view of them where the views' rows are all rows in order)."""
        return rows.reshape(self.bj.rows.shape + rows.shape[1:]) if self._in_order else rows[self.bj.rows]

    def _split(self, v: torch.Tensor):
        return v[self.bj.s_idx], v[self.bj.p_idx]

    def _join(self, vs: torch.Tensor, vp: torch.Tensor) -> torch.Tensor:
        out = vs.new_zeros(self.bj.n_params)
        out[self.bj.s_idx] = vs
        out[self.bj.p_idx] = vp
        return out

    def gradient(self, r: torch.Tensor) -> torch.Tensor:
        """Jᵀ W r."""
        gs = self.Jsw.T @ r
        gp = (self.Jp_v * (self.w_v * self._by_view(r))[..., None]).sum(1)
        return self._join(gs, gp)

    def diag(self) -> torch.Tensor:
        return self._join(torch.diagonal(self.A_ss), torch.diagonal(self.A_pp, dim1=-2, dim2=-1))

    def matvec(self, v: torch.Tensor) -> torch.Tensor:
        vs, vp = self._split(v)
        out_s = self.A_ss @ vs + (self.A_sp @ vp[..., None]).squeeze(-1).sum(0)
        out_p = torch.einsum("vsk,s->vk", self.A_sp, vs) + (self.A_pp @ vp[..., None]).squeeze(-1)
        return self._join(out_s, out_p)

    def solve(self, damping: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
        """(A + diag(damping))⁻¹ rhs by the Schur complement."""
        ds, dp = self._split(damping)
        gs, gp = self._split(rhs)
        App_inv = torch.linalg.inv(self.A_pp + torch.diag_embed(dp))   # (V, K, K)
        B = self.A_sp                                                  # (V, S, K)
        BAi = B @ App_inv                                              # (V, S, K)
        S = self.A_ss + torch.diag(ds) - (BAi @ B.transpose(1, 2)).sum(0)
        rhs_s = gs - (BAi @ gp[..., None]).squeeze(-1).sum(0)
        xs = torch.linalg.solve(S, rhs_s)
        xp = (App_inv @ (gp - torch.einsum("vsk,s->vk", B, xs))[..., None]).squeeze(-1)
        return self._join(xs, xp)

    def dense(self) -> torch.Tensor:
        """(P, P) A, assembled from its blocks (P² memory; never the (M, P) Jacobian)."""
        bj = self.bj
        A = self.A_ss.new_zeros(bj.n_params, bj.n_params)
        s, p = bj.s_idx, bj.p_idx
        A[s[:, None], s[None, :]] = self.A_ss
        A[p[:, :, None], p[:, None, :]] = self.A_pp
        A[s[None, :, None], p[:, None, :]] = self.A_sp
        A[p[:, :, None], s[None, None, :]] = self.A_sp.transpose(1, 2)
        return A

    def covariance(self) -> "SchurCovariance":
        """A⁻¹ by its blocks, never as a (P, P) matrix (`SchurCovariance`). Raises RuntimeError where A is
        singular."""
        App_inv = torch.linalg.inv(self.A_pp)                          # (V, K, K)
        Y = App_inv @ self.A_sp.transpose(1, 2)                        # (V, K, S)
        S_inv = torch.linalg.inv(self.A_ss - (self.A_sp @ Y).sum(0))
        return SchurCovariance(S_inv, App_inv, Y, self.bj.s_idx, self.bj.p_idx, self.bj.n_params)

    def leverages(self, cov) -> torch.Tensor:
        """(M,) diagonal of the hat matrix W J A⁻¹ Jᵀ, from the blocks of A⁻¹ that each row touches:
        row i of view v has w_i (j_s C_ss j_sᵀ + 2 j_s C_sv j_pᵀ + j_p C_vv j_pᵀ)."""
        C_ss, C_sv, C_vv = cov.blocks(self.bj.s_idx, self.bj.p_idx)
        js, jp = self.Js_v, self.Jp_v                                   # (V, R, S), (V, R, K)
        q = (js @ C_ss * js).sum(-1) + 2 * (js @ C_sv * jp).sum(-1) + (jp @ C_vv * jp).sum(-1)
        out = torch.zeros_like(self.w)
        out[self.bj.rows] = self.w_v * q
        return out


class DenseCovariance:
    """A covariance held as its (P, P) matrix (problems without per-view blocks, or small ones).

    Methods as `SchurCovariance`: diagonal, matmul, submatrix, blocks, dense, scaled."""

    def __init__(self, C: torch.Tensor):
        self.C = C

    def diagonal(self) -> torch.Tensor:
        return torch.diagonal(self.C)

    def matmul(self, X: torch.Tensor) -> torch.Tensor:
        return self.C @ X

    def submatrix(self, idx) -> torch.Tensor:
        idx = torch.as_tensor(idx, dtype=torch.long)
        return self.C[idx[:, None], idx[None, :]]

    def blocks(self, s_idx: torch.Tensor, p_idx: torch.Tensor):
        C = self.C
        return (C[s_idx[:, None], s_idx[None, :]], C[s_idx[None, :, None], p_idx[:, None, :]],
                C[p_idx[:, :, None], p_idx[:, None, :]])

    def dense(self) -> torch.Tensor:
        return self.C

    def scaled(self, factor: float) -> "DenseCovariance":
        return DenseCovariance(self.C * factor)


class SchurCovariance:
    """A⁻¹ of arrow-structured normal equations, kept as the blocks that define it: with Y_v = A_vv⁻¹ A_vs and
    S = A_ss − Σ_v A_sv Y_v,
        (A⁻¹)_ss = S⁻¹,  (A⁻¹)_sv = −S⁻¹ Y_vᵀ,  (A⁻¹)_vu = δ_vu A_vv⁻¹ + Y_v S⁻¹ Y_uᵀ.
    Memory O(V K S + S²) instead of O(P²): the (P, P) matrix of 2,000 views (P ≈ 12,000) alone is 1.2 GB, and
    a calibration needs it several times (noise levels, uncertainties, model selection, held-out folds).

    Attributes:
        S_inv: (S, S); App_inv: (V, K, K) the per-view blocks A_vv⁻¹; Y: (V, K, S); s_idx (S,), p_idx (V, K):
        positions in the flat vector; n_params: P.
    """

    def __init__(self, S_inv, App_inv, Y, s_idx, p_idx, n_params: int):
        self.S_inv, self.App_inv, self.Y = S_inv, App_inv, Y
        self.s_idx, self.p_idx, self.n_params = s_idx, p_idx, n_params

    def diagonal(self) -> torch.Tensor:
        """(P,) the variances."""
        out = self.S_inv.new_zeros(self.n_params)
        out[self.s_idx] = torch.diagonal(self.S_inv)
        YS = self.Y @ self.S_inv                                        # (V, K, S)
        out[self.p_idx] = torch.diagonal(self.App_inv, dim1=-2, dim2=-1) + (YS * self.Y).sum(-1)
        return out

    def matmul(self, X: torch.Tensor) -> torch.Tensor:
        """A⁻¹ X for X (P, n): t = S⁻¹ (X_s − Σ_v Y_vᵀ X_v), then (A⁻¹X)_s = t, (A⁻¹X)_v = A_vv⁻¹ X_v − Y_v t."""
        xs, xp = X[self.s_idx], X[self.p_idx]                          # (S, n), (V, K, n)
        t = self.S_inv @ (xs - torch.einsum("vks,vkn->sn", self.Y, xp))
        out = X.new_zeros(self.n_params, X.shape[1])
        out[self.s_idx] = t
        out[self.p_idx] = self.App_inv @ xp - torch.einsum("vks,sn->vkn", self.Y, t)
        return out

    def submatrix(self, idx) -> torch.Tensor:
        """(n, n) the entries of the flat positions idx."""
        idx = torch.as_tensor(idx, dtype=torch.long)
        E = self.S_inv.new_zeros(self.n_params, idx.numel())
        E[idx, torch.arange(idx.numel())] = 1.0
        return self.matmul(E)[idx]

    def blocks(self, s_idx=None, p_idx=None):
        """(C_ss (S, S), C_sv (V, S, K), C_vv (V, K, K)): the blocks a view's rows touch."""
        YS = self.Y @ self.S_inv                                        # (V, K, S)
        return self.S_inv, -YS.transpose(1, 2), self.App_inv + YS @ self.Y.transpose(1, 2)

    def dense(self) -> torch.Tensor:
        """(P, P) A⁻¹ (P² memory: tests and small problems)."""
        return self.matmul(torch.eye(self.n_params, dtype=self.S_inv.dtype))

    def scaled(self, factor: float) -> "SchurCovariance":
        """factor · A⁻¹ (Y does not change)."""
        return SchurCovariance(self.S_inv * factor, self.App_inv * factor, self.Y, self.s_idx, self.p_idx,
                               self.n_params)


def dense_jacobian(J) -> torch.Tensor:
    """The (M, P) matrix of a dense or block Jacobian."""
    return J.dense() if isinstance(J, BlockJacobian) else J
