"""The least-squares problem of a camera fit: residuals of corners and blur widths over the free parameters and
their Jacobian (`_Problem`), and the Levenberg–Marquardt call with its robust loss (`_lm`)."""
from __future__ import annotations

import torch

from tiltfit.calibrate.model import Observations, LensCamera, robust_rho, robust_weight
from tiltfit.solve import Block, LMOptions, LMResult, SolverError
from tiltfit.solve import levenberg_marquardt as solve_lm
from tiltfit.solve.blocks import side_by_side as _side_by_side


class FitError(RuntimeError):
    """A calibration that cannot be done or did not converge; the message is one line."""


# ---------------------------------------------------------------------------------------------------------
# The least-squares problem over a camera's free parameters
# ---------------------------------------------------------------------------------------------------------

class _Problem:
    """The calibration as a least-squares problem over a camera's free parameters (`tiltfit.solve` blocks).

    Residuals, flat: corners (V·N·2, pixels) then blur widths (V·N, pixels; none when no width was measured),
    model − observation, 0 where unobserved, each divided by its group's σ (`scale`). Parameters: the camera's free stored parameters by
    name (`LensCamera.named_parameters` order); the poses (`rvec`, `T_scaled`) are per-view blocks. The
    Jacobian is the camera's closed form (`LensCamera.jacobian`). With a `board` (`tiltfit.target.shape.Board`) that
    has parameters, the target points are the board's and its parameters are one more block, "board"
    (∂uv/∂θ = ∂uv/∂p_cam · R_v · ∂X/∂θ): global for a shape of a few parameters (warp); a point block where each
    parameter is one coordinate of one point (free: `_point_index`), whose Jacobian is each row's ∂/∂X of its own
    point (M, 3) and whose points the solve eliminates (`tiltfit.solve.points`).
    """

    POSE = ("rvec", "T_scaled")
    BOARD = "board"

    def __init__(self, camera: LensCamera, obs: Observations, names: list[str] | None = None, board=None):
        self.camera = camera
        self.obs = obs
        self.board = board if board is not None and board.n_params > 0 else None
        self.names = names if names is not None else camera.free_parameter_names()
        if self.board is not None and self.BOARD not in self.names:
            self.names = list(self.names) + [self.BOARD]
        if not self.names:
            raise FitError("no free parameters to fit")
        params = dict(camera.named_parameters())
        if self.board is not None:
            params[self.BOARD] = self.board.params
        self.shapes = [params[n].shape for n in self.names]
        # copies: a deferred σ reads them after the fit, when the result's camera may have been edited in place
        self.held = {n: p.detach().clone() for n, p in params.items() if n not in self.names}
        # columns per parameter in a residual row (a pose's: its own view's 3; a point block's: its point's 3)
        self._sizes = {n: (p.shape[-1] if n in self.POSE else p.numel()) for n, p in params.items()}
        self.point_index = _point_index(self.board.basis) if self.board is not None else None
        if self.point_index is not None:
            self._sizes[self.BOARD] = 3
        self.work = camera.copy().requires_grad_(False)  # evaluated at trial parameters, never autograd
        self._work_params = dict(self.work.named_parameters())
        self._overridden = set()  # held parameters `_load` replaced (restored on the next call)
        self.points = obs.points_mm.to(torch.float64) if self.board is None else self.board.points()
        self.cmask = obs.corner_mask
        self.bmask = obs.blur_mask
        self.corners = torch.nan_to_num(obs.corners_px)
        self.blur = torch.nan_to_num(obs.blur_px)
        dist_names = camera.parameter_names("distortion")
        self.with_distortion = any(n in self.names or bool(self.held[n] != 0) for n in dist_names)
        self.n_corner = int(self.cmask.sum()) * 2
        self.n_blur = int(self.bmask.sum())
        # Without blur widths (a geometric fit) the residual vector has no blur rows at all.
        self.blur_rows_kept = self.n_blur > 0
        nc = self.cmask.numel() * 2
        nb = self.bmask.numel() if self.blur_rows_kept else 0
        self.corner_rows = torch.zeros(nc + nb, dtype=torch.bool)
        self.corner_rows[:nc] = self.cmask[..., None].expand(-1, -1, 2).reshape(-1)
        self.blur_rows = torch.zeros_like(self.corner_rows)
        self.blur_rows[nc:] = self.bmask.reshape(-1) if nb else False
        # the unobserved rows, whose Jacobian rows are 0: a few, so zeroing them by index is cheaper than a mask
        self.unobserved_rows = (~(self.corner_rows | self.blur_rows)).nonzero().squeeze(1)
        V, N = self.cmask.shape
        self.blocks = [Block(n, tuple(shape), per_view=n in self.POSE,
                             points=self.point_index if n == self.BOARD else None)
                       for n, shape in zip(self.names, self.shapes)]
        # rows of view v: its 2N corner entries (and its N blur entries)
        self.view_rows = 2 * N * torch.arange(V)[:, None] + torch.arange(2 * N)[None]
        if nb:
            self.view_rows = torch.cat([self.view_rows, 2 * V * N + N * torch.arange(V)[:, None]
                                        + torch.arange(N)[None]], 1)
        # the point of each row: corner rows (v, n, u|v), then blur rows (v, n)
        points = torch.arange(N).repeat(V)
        self.row_points = torch.cat([points.repeat_interleave(2)] + ([points] if nb else []))
        if self.point_index is None:
            self.row_points = None

    def x0(self) -> dict:
        params = dict(self.camera.named_parameters())
        if self.board is not None:
            params[self.BOARD] = self.board.params
        return {n: params[n].detach().to(torch.float64).clone() for n in self.names}

    def params(self, x: dict, held: dict | None = None) -> dict:
        return {**(held if held is not None else self.held), **x}

    def _load(self, x: dict, held: dict | None = None):
        """Put x (and `held` in place of the held values) into the working camera."""
        wp = self._work_params
        with torch.no_grad():
            for n in self._overridden:
                wp[n].copy_(self.held[n])
            self._overridden = set()
            for n, v in x.items():
                if n == self.BOARD:
                    self.points = self.board.points(v)
                    continue
                wp[n].copy_(v)
            for n, v in (held or {}).items():
                if n not in x:
                    wp[n].copy_(v)
                    self._overridden.add(n)

    def _flat(self, uv: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        rc = torch.where(self.cmask[..., None], uv - self.corners, torch.zeros_like(uv)).reshape(-1)
        if not self.blur_rows_kept:
            return rc
        rb = torch.where(self.bmask, b - self.blur, torch.zeros_like(b)).reshape(-1)
        return torch.cat([rc, rb])

    def raw(self, x: dict, held: dict | None = None) -> torch.Tensor:
        """Model − observation, flat: corners (V·N·2, pixels) then blur (V·N, pixels, if kept); 0 where
        unobserved."""
        self._load(x, held)
        with torch.no_grad():
            uv, b = self.work(self.points, with_blur=self.n_blur > 0, with_distortion=self.with_distortion)
        return self._flat(uv, b)

    def raw_jacobian(self, x: dict, names, held: dict | None = None) -> tuple[torch.Tensor, dict]:
        """`raw(x)` and its derivatives {name: (M, size)} with respect to the named stored parameters (free or
        held; a pose's row i with respect to the pose of row i's view)."""
        J, r = self._raw_jacobian_matrix(x, names, held)
        return r, dict(zip(names, torch.split(J, [self._sizes[n] for n in names], 1)))

    def _raw_jacobian_matrix(self, x: dict, names, held: dict | None = None):
        """((M, Σ sizes) derivatives of `raw` by the named parameters side by side, raw(x))."""
        self._load(x, held)
        cam_names = [n for n in names if n != self.BOARD]
        if self.BOARD in names and "T_scaled" not in cam_names:
            cam_names.append("T_scaled")  # ∂/∂p_cam, for the board's chain rule
        uv, b, jac = self.work.jacobian(self.points, with_blur=self.n_blur > 0, with_distortion=self.with_distortion,
                                        names=cam_names)
        if self.BOARD in names:
            d_pcam = jac["T_scaled"] / self.work.length_scale_mm                # (V, N, 3, 3) ∂(u, v, b)/∂p_cam
            V, N = d_pcam.shape[:2]                                             # ∂/∂X_world, one product a view
            d_world = torch.bmm(d_pcam.reshape(V, N * 3, 3), self.work.R.detach()).reshape(V, N, 3, 3)
            jac[self.BOARD] = d_world if self.point_index is not None else \
                torch.einsum("vnij,njk->vnik", d_world, self.board.basis)
        # written once into the (M, P) matrix: corner rows (V, N, 2) then blur rows (V, N), 0 where unobserved
        blocks = _side_by_side([jac[n] for n in names])
        V, N = self.cmask.shape
        nc = 2 * V * N
        J = uv.new_empty(nc + (V * N if self.blur_rows_kept else 0), sum(b.shape[-1] for b in blocks))
        # the blocks side by side (V, N, 3, P), then its corner and blur rows copied into place: a quarter faster
        # than concatenating the blocks' row slices into place (a strided copy a block)
        rows = blocks[0] if len(blocks) == 1 else torch.cat(blocks, -1)
        J[:nc].view(V, N, 2, -1).copy_(rows[..., :2, :])
        if self.blur_rows_kept:
            J[nc:].view(V, N, -1).copy_(rows[..., 2, :])
        J.index_fill_(0, self.unobserved_rows, 0.0)
        return J, self._flat(uv, b)

    def evaluate(self, scale: torch.Tensor):
        """The `tiltfit.solve.levenberg_marquardt` callback of the residuals `raw(x) * scale`."""
        # the columns in the solver's order (globals, poses, board): its blocks are then views of one matrix
        order = sorted(self.names, key=lambda n: (n in self.POSE) + 2 * (n == self.BOARD))
        sizes = [self._sizes[n] for n in order]
        unit = bool((scale == 1.0).all())  # σ = 1 (a fit without σ estimates): x · 1 is x, bit for bit

        def evaluate(x: dict, with_jacobian: bool):
            if not with_jacobian:
                r = self.raw(x)
                return (r if unit else r * scale), None
            J, r = self._raw_jacobian_matrix(x, order)
            if not unit:
                r, J = r * scale, J.mul_(scale[:, None])
            return r, dict(zip(order, torch.split(J, sizes, 1)))

        return evaluate

    def scale(self, sigma_c: float, sigma_b: float) -> torch.Tensor:
        """(M,) 1/σ of each residual row."""
        nc = self.cmask.numel() * 2
        s = torch.full((self.corner_rows.numel(),), 1.0 / sigma_c, dtype=torch.float64)
        s[nc:] = 1.0 / sigma_b
        return s

    def write_back(self, x: dict):
        with torch.no_grad():
            params = dict(self.camera.named_parameters())
            for n, v in x.items():
                if n == self.BOARD:
                    self.board.params = v.detach().clone()
                    continue
                params[n].copy_(v)


def _point_index(basis: torch.Tensor) -> torch.Tensor | None:
    """(N, 3) long: the parameter that is each coordinate of each point, −1 where none (a gauge), when every
    parameter of a board's shape is one coordinate of one point (`basis` (N, 3, K) a selection: the free model);
    else None (the parameters move many points: a global block)."""
    N, _, K = basis.shape
    B = basis.reshape(3 * N, K)
    if K == 0 or not bool(((B != 0).sum(0) == 1).all()) or not bool((B.sum(0) == 1).all()) \
            or bool(((B != 0).sum(1) > 1).any()):
        return None
    return torch.where((B != 0).any(1), B.argmax(1), -1).reshape(N, 3)


def _robust_options(robust: str | None, scale: float, max_iterations: int) -> LMOptions:
    """`LMOptions` with the robust loss of `tiltfit.calibrate.model` (ρ and its IRLS weight)."""
    if robust in (None, "none"):
        return LMOptions(max_iterations=max_iterations)
    return LMOptions(max_iterations=max_iterations, rho=lambda s2: robust_rho(s2, robust, scale),
                     weight=lambda s2: robust_weight(s2, robust, scale))


def _lm(evaluate, x0: dict, blocks, view_rows, options: LMOptions, row_points=None) -> LMResult:
    try:
        return solve_lm(evaluate, x0, blocks, view_rows, options, row_points)
    except SolverError as e:
        raise FitError(str(e)) from None
