"""tiltfit.solve: Levenberg–Marquardt over named blocks on problems with a known minimum; the Schur complement of
per-view blocks, and the elimination of per-point blocks, against the dense normal equations; the Gauss–Newton
covariance against linear regression."""
import math

import pytest
import torch

from tiltfit.solve import Block, LMOptions, SolverError, covariance, least_squares, levenberg_marquardt
from tiltfit.solve.blocks import DenseCovariance, DenseNormal, Layout, SchurCovariance, SchurNormal
from tiltfit.solve.points import PointCovariance, PointSchurNormal

F64 = torch.float64


def _exponential():
    t = torch.linspace(0, 1, 20, dtype=F64)
    y = 2.0 * torch.exp(-1.5 * t) + 0.3

    def evaluate(x, with_jacobian):
        a, k, c = x["amplitude"], x["rate"], x["offset"]
        e = torch.exp(k * t)
        r = a * e + c - y
        jac = {"amplitude": e[:, None], "rate": (a * t * e)[:, None], "offset": torch.ones(20, 1, dtype=F64)}
        return r, (jac if with_jacobian else None)

    blocks = [Block("amplitude", ()), Block("rate", ()), Block("offset", ())]
    x0 = {"amplitude": torch.tensor(1.0, dtype=F64), "rate": torch.tensor(0.0, dtype=F64),
          "offset": torch.tensor(0.0, dtype=F64)}
    return evaluate, blocks, x0


def test_recovers_a_known_minimum_by_name():
    evaluate, blocks, x0 = _exponential()
    # The decrement test is absolute (residuals in units of their σ): 1e-9 leaves the parameters within
    # ~sqrt(2e-9) / sensitivity of the minimum; a tighter one reaches it to rounding.
    for tol, atol in ((1e-9, 1e-5), (1e-24, 1e-10)):
        res = levenberg_marquardt(evaluate, x0, blocks, options=LMOptions(decrement_tol=tol))
        for name, true in (("amplitude", 2.0), ("rate", -1.5), ("offset", 0.3)):
            assert abs(float(res.x[name]) - true) < atol, f"{name}: {float(res.x[name])} vs {true} (tol {tol})"
        assert res.stop in ("decrement", "ftol", "xtol"), f"converged, stopped by {res.stop}"
        assert 2 <= res.iterations < 30, f"iterations {res.iterations}"
    assert res.cost < 1e-20, f"zero-residual problem, cost {res.cost}"


def test_non_finite_start_and_no_convergence_are_errors():
    evaluate, blocks, x0 = _exponential()
    with pytest.raises(SolverError, match="undefined at the starting point"):
        levenberg_marquardt(lambda x, j: (evaluate(x, j)[0] / 0.0 * 0.0, evaluate(x, j)[1]), x0, blocks)
    with pytest.raises(SolverError, match="did not converge in 1 iterations"):
        levenberg_marquardt(evaluate, x0, blocks, options=LMOptions(max_iterations=1))


def test_linear_problem_gives_the_regression_covariance():
    """For r = X β − y the minimum is the least-squares solution and s² (XᵀX)⁻¹ its covariance, exactly."""
    gen = torch.Generator().manual_seed(0)
    X = torch.randn(50, 3, generator=gen, dtype=F64)
    y = X @ torch.tensor([1.0, -2.0, 0.5], dtype=F64) + 0.1 * torch.randn(50, generator=gen, dtype=F64)

    def evaluate(x, with_jacobian):
        return X @ x["beta"] - y, ({"beta": X} if with_jacobian else None)

    res = levenberg_marquardt(evaluate, {"beta": torch.zeros(3, dtype=F64)}, [Block("beta", (3,))])
    beta = torch.linalg.lstsq(X, y[:, None]).solution[:, 0]
    assert torch.allclose(res.x["beta"], beta, atol=1e-10), f"{res.x['beta'].tolist()} vs {beta.tolist()}"
    s2 = float((res.r ** 2).sum()) / (50 - 3)
    C = covariance(res, s2).dense()
    expected = s2 * torch.linalg.inv(X.T @ X)
    assert torch.allclose(C, expected, rtol=1e-10, atol=0), "Gauss–Newton covariance s² (XᵀX)⁻¹"


def _circles(n_views=6, n_points=9, seed=3):
    """Points on V circles with one shared radius and per-view centres: a problem with per-view blocks."""
    gen = torch.Generator().manual_seed(seed)
    centres = 5 * torch.randn(n_views, 2, generator=gen, dtype=F64)
    radius, squash = 3.0, 0.8
    phi = 2 * math.pi * torch.rand(n_views, n_points, generator=gen, dtype=F64)
    pts = centres[:, None, :] + torch.stack([radius * torch.cos(phi), squash * radius * torch.sin(phi)], -1)
    pts = pts + 0.01 * torch.randn(pts.shape, generator=gen, dtype=F64)

    def evaluate(x, with_jacobian):
        d = pts - x["centre"][:, None, :]                                  # (V, N, 2)
        q = torch.stack([d[..., 0], d[..., 1] / x["squash"]], -1)
        n = q.norm(dim=-1)
        r = (n - x["radius"]).reshape(-1)                                   # view v's rows: v N … v N + N − 1
        if not with_jacobian:
            return r, None
        dn_dc = -torch.stack([q[..., 0], q[..., 1] / x["squash"]], -1) / n[..., None]
        dn_ds = -(q[..., 1] ** 2 / x["squash"]) / n
        jac = {"radius": -torch.ones(r.shape[0], 1, dtype=F64), "squash": dn_ds.reshape(-1, 1),
               "centre": dn_dc.reshape(-1, 2)}
        return r, jac

    blocks = [Block("radius", ()), Block("centre", (n_views, 2), per_view=True), Block("squash", ())]
    view_rows = torch.arange(n_views * n_points).reshape(n_views, n_points)
    x0 = {"radius": torch.tensor(2.0, dtype=F64), "centre": centres + 0.3, "squash": torch.tensor(1.0, dtype=F64)}
    return evaluate, blocks, view_rows, x0, (radius, squash, centres)


def test_per_view_blocks_by_schur_complement_match_the_dense_solve():
    evaluate, blocks, view_rows, x0, (radius, squash, centres) = _circles()
    res = levenberg_marquardt(evaluate, x0, blocks, view_rows)
    assert isinstance(res.normal, SchurNormal), "per-view blocks use the Schur complement"
    assert abs(float(res.x["radius"]) - radius) < 0.01 and abs(float(res.x["squash"]) - squash) < 0.01, \
        f"radius {float(res.x['radius'])}, squash {float(res.x['squash'])}"
    assert float((res.x["centre"] - centres).abs().max()) < 0.02, "centres recovered"
    # The same problem as one dense block: same minimum, same covariance.
    layout = Layout(blocks, view_rows)

    def dense_eval(x, with_jacobian):
        r, jac = evaluate(layout.unflatten(x["all"]), with_jacobian)
        return r, ({"all": layout.jacobian(jac).dense()} if with_jacobian else None)

    dense = levenberg_marquardt(dense_eval, {"all": layout.flatten(x0)}, [Block("all", (layout.n_params,))])
    assert isinstance(dense.normal, DenseNormal)
    assert torch.allclose(res.x_flat, dense.x_flat, atol=1e-9), "Schur and dense solves agree"
    C_schur, C_dense = covariance(res).dense(), covariance(dense).dense()
    assert torch.allclose(C_schur, C_dense, rtol=1e-8, atol=1e-14), "block inverse equals the dense inverse"
    cov = covariance(res)
    assert isinstance(cov, SchurCovariance), "per-view blocks keep the covariance by blocks (no (P, P) matrix)"
    lev = res.normal.leverages(cov)
    assert torch.allclose(cov.diagonal(), torch.diagonal(C_dense), rtol=1e-8, atol=1e-14), "block variances"
    X = torch.randn(layout.n_params, 4, dtype=F64, generator=torch.Generator().manual_seed(0))
    assert torch.allclose(cov.matmul(X), C_dense @ X, rtol=1e-8, atol=1e-12), "block product A⁻¹ X"
    assert torch.allclose(cov.submatrix([5, 0, 2]), C_dense[[5, 0, 2]][:, [5, 0, 2]], rtol=1e-8, atol=1e-14), \
        "entries of chosen positions"
    assert abs(float(lev.sum()) - layout.n_params) < 1e-8, \
        f"the hat matrix's trace is the number of parameters: {float(lev.sum())} vs {layout.n_params}"
    assert layout.flat_names()[:3] == ["radius", "centre[0,0]", "centre[0,1]"], layout.flat_names()[:3]


def _points_seen_by_cameras(n_views=5, n_points=7, seed=4):
    """A small bundle adjustment: N points seen by V translated pinhole views of one focal length, the points'
    gauge fixed (point 0, which fixes the translation, and point 1's x and z, which fix the scales of x, y and z
    that the focal length offsets): global, per-view and per-point blocks."""
    gen = torch.Generator().manual_seed(seed)
    pts = torch.randn(n_points, 3, generator=gen, dtype=F64) + torch.tensor([0.0, 0.0, 8.0], dtype=F64)
    shift = 0.8 * torch.randn(n_views, 3, generator=gen, dtype=F64)
    focal = 2.0
    obs = focal * (pts[None] + shift[:, None])[..., :2] / (pts[None] + shift[:, None])[..., 2:]
    obs = obs + 1e-3 * torch.randn(obs.shape, generator=gen, dtype=F64)
    index = torch.full((n_points, 3), -1, dtype=torch.long)
    free = torch.ones(n_points, 3, dtype=torch.bool)
    free[0] = False
    free[1, 0] = False
    free[1, 2] = False
    index[free] = torch.arange(int(free.sum()))

    def points_of(x):
        p = pts.clone().reshape(-1)
        p[index.reshape(-1) >= 0] = x["points"]
        return p.reshape(n_points, 3)

    def evaluate(x, with_jacobian):
        X = points_of(x)[None] + x["shift"][:, None]                      # (V, N, 3)
        z = X[..., 2:]
        r = (x["focal"] * X[..., :2] / z - obs).reshape(-1)               # rows (v, n, u|v)
        if not with_jacobian:
            return r, None
        f = x["focal"]
        dX = torch.zeros(*X.shape[:2], 2, 3, dtype=F64)                   # ∂(u, v)/∂X
        dX[..., 0, 0] = f / z[..., 0]
        dX[..., 1, 1] = f / z[..., 0]
        dX[..., :, 2] = -f * X[..., :2] / z ** 2
        dX = dX.reshape(-1, 3)
        jac = {"focal": (X[..., :2] / z).reshape(-1, 1), "shift": dX, "points": dX}
        return r, jac

    blocks = [Block("focal", ()), Block("shift", (n_views, 3), per_view=True),
              Block("points", (int(free.sum()),), points=index)]
    view_rows = torch.arange(n_views * n_points * 2).reshape(n_views, -1)
    row_points = torch.arange(n_points).repeat(n_views).repeat_interleave(2)
    x0 = {"focal": torch.tensor(1.9, dtype=F64), "shift": shift + 0.05,
          "points": (pts.reshape(-1)[index.reshape(-1) >= 0] + 0.05)}
    return evaluate, blocks, view_rows, row_points, x0


def test_point_blocks_eliminated_as_in_bundle_adjustment_match_the_dense_solve():
    evaluate, blocks, view_rows, row_points, x0 = _points_seen_by_cameras()
    res = levenberg_marquardt(evaluate, x0, blocks, view_rows, row_points=row_points)
    assert isinstance(res.normal, PointSchurNormal), "a point block is eliminated point by point"
    layout = Layout(blocks, view_rows, row_points)
    J = layout.jacobian(evaluate(layout.unflatten(res.x_flat), True)[1])
    assert J.Jq.shape == (row_points.numel(), 3), "the point block's Jacobian is kept as 3 columns a row"
    Jd = J.dense()
    A = Jd.T @ Jd
    assert torch.allclose(res.normal.dense(), A, rtol=1e-12, atol=1e-12), "normal matrix from its blocks"

    def dense_eval(x, with_jacobian):
        r, jac = evaluate(layout.unflatten(x["all"]), with_jacobian)
        return r, ({"all": layout.jacobian(jac).dense()} if with_jacobian else None)

    dense = levenberg_marquardt(dense_eval, {"all": layout.flatten(x0)}, [Block("all", (layout.n_params,))])
    assert torch.allclose(res.x_flat, dense.x_flat, rtol=1e-10, atol=1e-12), "point elimination and dense agree"
    g = torch.randn(layout.n_params, dtype=F64, generator=torch.Generator().manual_seed(1))
    d = torch.rand(layout.n_params, dtype=F64, generator=torch.Generator().manual_seed(2))
    assert torch.allclose(res.normal.solve(d, g), torch.linalg.solve(res.normal.dense() + torch.diag(d), g),
                          rtol=1e-9, atol=1e-12), "damped solve"
    assert torch.allclose(res.normal.matvec(g), res.normal.dense() @ g, rtol=1e-12, atol=1e-12), "A v"
    assert torch.allclose(res.normal.gradient(res.r), dense.normal.gradient(res.r), rtol=1e-10, atol=1e-14), "Jᵀr"
    C_dense = covariance(dense).dense()
    cov = covariance(res)
    assert isinstance(cov, PointCovariance), "the covariance kept by blocks"
    assert torch.allclose(cov.dense(), C_dense, rtol=1e-7, atol=1e-12), "block inverse equals the dense inverse"
    assert torch.allclose(cov.diagonal(), torch.diagonal(C_dense), rtol=1e-7, atol=1e-14), "block variances"
    X = torch.randn(layout.n_params, 3, dtype=F64, generator=torch.Generator().manual_seed(0))
    assert torch.allclose(cov.matmul(X), C_dense @ X, rtol=1e-7, atol=1e-10), "block product A⁻¹ X"
    lev = res.normal.leverages(cov)
    lev_dense = ((Jd @ C_dense) * Jd).sum(-1)
    assert torch.allclose(lev, lev_dense, rtol=1e-7, atol=1e-10), "each row's leverage"
    assert abs(float(lev.sum()) - layout.n_params) < 1e-7, "the hat matrix's trace is the number of parameters"
    # where A is singular the fit's σ falls back to a pseudo-inverse held densely (fit._group_sigma)
    lev_pinv = res.normal.leverages(DenseCovariance(torch.linalg.pinv(res.normal.dense())))
    assert torch.allclose(lev_pinv, lev_dense, rtol=1e-7, atol=1e-10), "leverages of a dense covariance"


@pytest.mark.parametrize("layout", ["views in order", "rows of a point apart", "rows a point unequal"])
def test_point_block_normal_equations_for_any_row_layout(layout):
    """The point block's products with the other columns, summed over each point's rows: as batched products where
    every point has the same rows in every view (in order, or a point's rows apart as a calibration's corner and
    blur rows are), row by row otherwise (a point with more rows than another in a view); each equals JᵀJ of the
    dense Jacobian."""
    from tiltfit.solve.points import _rows_by_point

    evaluate, blocks, view_rows, row_points, x0 = _points_seen_by_cameras()
    r, jac = evaluate(x0, True)
    V, R = view_rows.shape
    N = R // 2
    if layout == "rows of a point apart":   # each view's u rows first, then its v rows
        order = torch.cat([view_rows[:, 0::2], view_rows[:, 1::2]], 1)
        view_rows = order
    elif layout == "rows a point unequal":  # in view 0 one row of point 3 counted as point 4's (the algebra holds)
        row_points = row_points.clone()
        row_points[7] = 4
    grouped = _rows_by_point(view_rows, row_points, N) if layout != "rows a point unequal" else None
    assert (grouped is None) == (layout == "rows a point unequal"), "batched exactly where the layout allows"
    bj = Layout(blocks, view_rows, row_points).jacobian(jac)
    ne = PointSchurNormal(bj, torch.ones_like(r))
    Jd = bj.dense()
    assert torch.allclose(ne.dense(), Jd.T @ Jd, rtol=1e-12, atol=1e-12), f"normal matrix, {layout}"


def test_views_rows_in_order_are_read_in_place():
    """Where the views' rows are all rows in order (a geometric fit's), the normal equations read each view's rows
    of the Jacobian as a view of it, not a copy; in another order they gather them, and both equal JᵀJ."""
    evaluate, blocks, view_rows, x0, _ = _circles()
    r, jac = evaluate(x0, True)
    layout = Layout(blocks, view_rows)
    bj = layout.jacobian(jac)
    ne = SchurNormal(bj, torch.ones_like(r))
    assert ne.Jp_v.untyped_storage().data_ptr() == bj.Jp.untyped_storage().data_ptr(), "a copy, not a view"
    shuffled = Layout(blocks, view_rows.flip(1)).jacobian(jac)
    ne2 = SchurNormal(shuffled, torch.ones_like(r))
    Jd = bj.dense()
    for n in (ne, ne2):
        assert torch.allclose(n.dense(), Jd.T @ Jd, rtol=1e-12, atol=1e-12), "normal matrix"


def test_cluster_covariance_with_a_point_block_equals_it_with_the_points_as_dense_globals():
    """The per-view sandwich through the point block's 3 columns a row equals the one written for dense global
    columns (the points' columns spelt out), poses' random-effect part included."""
    from dataclasses import replace

    from tiltfit.solve.blocks import BlockJacobian
    from tiltfit.uncertainty.covariance import view_cluster_covariance

    evaluate, blocks, view_rows, row_points, x0 = _points_seen_by_cameras()
    res = levenberg_marquardt(evaluate, x0, blocks, view_rows, row_points=row_points)
    bj = res.jacobian
    q = bj.q_idx[bj.q_idx >= 0].sort().values
    dense = BlockJacobian(torch.cat([bj.Js, bj.dense()[:, q]], 1), bj.Jp, bj.rows, torch.cat([bj.s_idx, q]),
                          bj.p_idx, bj.n_params)
    gen = torch.Generator().manual_seed(5)
    modes = torch.randn(*view_rows.shape, 3, generator=gen, dtype=F64)
    kinds = torch.ones(view_rows.shape, dtype=torch.long)
    s2 = 2.0 * res.cost / (res.r.numel() - res.x_flat.numel())
    got, info = view_cluster_covariance(res, s2, modes, kinds)
    want, info_dense = view_cluster_covariance(replace(res, jacobian=dense), s2, modes, kinds)
    assert torch.allclose(got.dense(), want.dense(), rtol=1e-7, atol=1e-12), \
        f"largest difference {float((got.dense() - want.dense()).abs().max()):.3g}"
    for k in ("design_effect", "view_error_px", "pose_ratio_min", "pose_ratio_max"):
        assert info[k] == pytest.approx(info_dense[k], rel=1e-7), k


def test_huber_loss_down_weights_an_outlier():
    evaluate, blocks, x0 = _exponential()

    def with_outlier(x, with_jacobian):
        r, jac = evaluate(x, with_jacobian)
        return r + torch.nn.functional.one_hot(torch.tensor(5), 20).to(F64) * 5.0, jac

    k = 0.01

    def rho(s2):
        return torch.where(s2 <= k * k, s2, 2 * k * s2.sqrt() - k * k)

    def weight(s2):
        return torch.where(s2 <= k * k, torch.ones_like(s2), k / s2.clamp(min=k * k).sqrt())

    plain = levenberg_marquardt(with_outlier, x0, blocks)
    robust = levenberg_marquardt(with_outlier, x0, blocks, options=LMOptions(rho=rho, weight=weight))
    err_plain = abs(float(plain.x["rate"]) + 1.5)
    err_robust = abs(float(robust.x["rate"]) + 1.5)
    assert err_robust < 0.2 * err_plain, f"rate error robust {err_robust:.3g} vs plain {err_plain:.3g}"


def test_calibration_problem_jacobian_equals_autograd_of_its_residuals():
    """The fit's problem (masks, σ scaling, per-view pose blocks) assembles the closed-form Jacobian into the
    same matrix autograd gives for its residual vector, with corners and blur widths missing here and there."""
    from torch.func import functional_call

    from tiltfit.calibrate.problem import _Problem
    from tiltfit.calibrate.model import LensCamera, board_points_mm, random_poses, synthesize_observations

    rvec, T = random_poses(3, seed=7)
    cam = LensCamera(3, (1368, 912), 0.026, 55.0, 640.0, 18.0, 0.3, rvec=rvec, T_mm=T,
                         distortion=[0.05, -0.02, 0.001, 0.002, 0.01, 0.0, 0.0, 0.0])
    obs = synthesize_observations(cam, board_points_mm(5, 3, 25.0), 0.1, 0.1, seed=3)
    obs.corners_px[1, 3] = math.nan
    obs.blur_px[2, 5:8] = math.nan
    cam.free("all", "principal_point", "blur_offset", "k1", "k2", "p1", "p2", "k3")
    with torch.no_grad():
        cam.log_w_mm.add_(0.01)
        cam.rvec.add_(0.01)
    prob = _Problem(cam, obs)
    scale = prob.scale(0.3, 1.7)
    x0 = prob.x0()
    r, jac = prob.evaluate(scale)(x0, True)
    layout = Layout(prob.blocks, prob.view_rows)
    ours = layout.jacobian(jac).dense()

    def residuals(v):
        params = {**prob.held, **layout.unflatten(v)}
        uv, b = functional_call(cam, params, (prob.points,))
        rc = torch.where(prob.cmask[..., None], uv - prob.corners, torch.zeros_like(uv)).reshape(-1)
        rb = torch.where(prob.bmask, b - prob.blur, torch.zeros_like(b)).reshape(-1)
        return torch.cat([rc, rb]) * scale

    v0 = layout.flatten(x0)
    assert torch.allclose(r, residuals(v0), rtol=0, atol=1e-10), "residuals"
    auto = torch.autograd.functional.jacobian(residuals, v0)
    err = float((ours - auto).abs().max() / auto.abs().max())
    assert ours.shape == auto.shape and err < 1e-9, f"problem Jacobian vs autograd: {err:.2e}"


def test_jacobian_columns_side_by_side_in_memory_are_copied_as_one_block():
    """The distortion coefficients' columns are slices of one tensor: adjacent ones join into one block of the
    same numbers; a gap, another order or another tensor keeps blocks apart."""
    from tiltfit.calibrate.problem import _side_by_side

    dk = torch.arange(2 * 3 * 8, dtype=torch.float64).reshape(2, 3, 8)
    other = torch.arange(2 * 3 * 2, dtype=torch.float64).reshape(2, 3, 2) + 1000
    columns = [other, dk[..., 0:1], dk[..., 1:2], dk[..., 2:5], dk[..., 6:7], dk[..., 5:6], other[..., 1:2]]
    joined = _side_by_side(columns)
    assert [b.shape[-1] for b in joined] == [2, 5, 1, 1, 1], [b.shape for b in joined]
    assert torch.equal(torch.cat(joined, -1), torch.cat(columns, -1)), "joined blocks change the numbers"
    assert joined[1].untyped_storage().data_ptr() == dk.untyped_storage().data_ptr(), "a copy, not a view"


def test_least_squares_on_a_small_dense_problem():
    t = torch.linspace(0, 1, 20, dtype=torch.float64)
    y = 2.0 * torch.exp(-1.5 * t) + 0.3

    def r(x):
        return x[0] * torch.exp(x[1] * t) + x[2] - y

    res = least_squares(r, torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))
    assert torch.allclose(res.x, torch.tensor([2.0, -1.5, 0.3], dtype=torch.float64), atol=1e-6), \
        f"LM should recover (2, -1.5, 0.3), got {res.x.tolist()}"
    assert res.iterations < 30, f"converges quickly, took {res.iterations}"


def test_batched_solves_each_problem_as_the_single_solver_does():
    from tiltfit.solve import BatchedOptions, Normal, batched_levenberg_marquardt

    gen = torch.Generator().manual_seed(3)
    t = torch.linspace(0, 1, 30, dtype=F64)
    truth = torch.stack([1 + torch.rand(40, generator=gen, dtype=F64), -1 - 2 * torch.rand(40, generator=gen, dtype=F64),
                         torch.rand(40, generator=gen, dtype=F64) - 0.5], 1)           # (B, 3)
    y = truth[:, :1] * torch.exp(truth[:, 1:2] * t) + truth[:, 2:] + 1e-3 * torch.randn(40, 30, generator=gen,
                                                                                          dtype=F64)

    def evaluate(x, idx):
        e = torch.exp(x[:, 1:2] * t)
        r = x[:, :1] * e + x[:, 2:] - y[idx]
        return r, torch.stack([e, x[:, :1] * t * e, torch.ones_like(e)], -1)

    x0 = torch.tensor([1.0, 0.0, 0.0], dtype=F64).expand(40, 3)
    sol = batched_levenberg_marquardt(evaluate, x0, BatchedOptions(max_iterations=100))
    assert bool(sol.converged.all()), f"{int((~sol.converged).sum())} of 40 problems did not converge"
    for b in (0, 17, 39):
        one = least_squares(lambda v: (v[0] * torch.exp(v[1] * t) + v[2] - y[b]) / 1e-3, x0[b])  # in units of σ
        assert torch.allclose(sol.x[b], one.x, atol=1e-6), \
            f"problem {b}: batched {sol.x[b].tolist()} vs the single solver's {one.x.tolist()}"
    err = (sol.x - truth).abs().max(0).values
    assert bool((err < torch.tensor([0.02, 0.1, 0.02], dtype=F64)).all()), f"recovered parameters off by {err.tolist()}"
    # the same through the normal-equations form, with the first parameter bounded and steps capped
    def normal(x, idx):
        r, J = evaluate(x, idx)
        return Normal(0.5 * (r * r).sum(-1), J.transpose(1, 2) @ J, (J * r[..., None]).sum(1))

    def bound(x, idx):
        x[:, 0] = x[:, 0].clamp(max=1.5)
        return x

    capped = batched_levenberg_marquardt(normal, x0, BatchedOptions(max_iterations=200, max_step=0.1), project=bound)
    assert float(capped.x[:, 0].max()) <= 1.5, "the bound holds"
    free = truth[:, 0] < 1.45
    assert torch.allclose(capped.x[free], sol.x[free], atol=1e-5), "where the bound is not active the minimum is the same"


def test_an_iteration_at_tiny_damping_solves_once(monkeypatch):
    """Where λ ≤ `DECREMENT_DAMPING`, an iteration's first trial is the decrement's own solve: one linear solve an
    iteration, not two (the old code's were at least 2 × iterations + 1), and the same minimum."""
    import tiltfit.solve.lm as lm

    t = torch.linspace(0.0, 3.0, 40, dtype=torch.float64)
    y = 2.0 * torch.exp(-1.3 * t) + 0.5 + 1e-3 * torch.sin(7.0 * t)
    fn = lambda p: p[0] * torch.exp(-p[1] * t) + p[2] - y  # noqa: E731
    start = torch.tensor([1.8, 1.1, 0.45])
    solves = []
    plain = DenseNormal.solve
    monkeypatch.setattr(DenseNormal, "solve", lambda self, damping, rhs: solves.append(1) or plain(self, damping, rhs))
    monkeypatch.setattr(lm, "INITIAL_DAMPING", 1e-13)  # λ below the decrement's damping from the first iteration
    with pytest.raises(SolverError):  # five steps, the sixth point's decrement, no tolerance met
        least_squares(fn, start, LMOptions(decrement_tol=0.0, ftol=0.0, xtol=0.0, max_iterations=5))
    assert len(solves) < 2 * 5 + 1, len(solves)
    res = least_squares(fn, start)
    monkeypatch.setattr(lm, "DECREMENT_DAMPING", 1e-30)  # no λ reaches it: every iteration solves twice
    ref = least_squares(fn, start)
    assert res.stop == ref.stop and torch.allclose(res.x, ref.x, rtol=1e-10, atol=0.0), (res.x, ref.x)
