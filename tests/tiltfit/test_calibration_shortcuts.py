"""The calibration's shortcuts (issue 32 §0) give what the long way gives: the per-view leverage eigenproblem from
the smaller Gram matrix, the projection σ map's Jacobian by central differences, a free board started at another
board's points."""
from __future__ import annotations

import pytest
import torch

from tiltfit.target.shape import Board, free_board_at
from tiltfit.uncertainty.columns import _leverage_eigen
from tiltfit.uncertainty.covariance import _jac


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


def test_deferred_per_view_sigma_equal_those_made_at_once():
    """A geometric fit whose per-view σ are deferred (a blur fit usually replaces it) gets, when asked, exactly the σ
    the refit made at once gives; until then it carries the classical ones."""
    from dataclasses import replace

    import cv2
    import numpy as np

    from tiltfit.calibrate.fit import FitOptions, with_deferred_sigma
    from tiltfit.calibrate.model import Observations, board_points_mm
    from tiltfit.calibrate.start import initialize
    from tiltfit.select.board import fit_board
    from tiltfit.select.held_out import _with_uncertainties

    points = board_points_mm(8, 6, 15.0, centred=False).numpy()
    rng = np.random.default_rng(7)
    K = np.array([[2000.0, 0, 650.0], [0, 2000.0, 505.0], [0, 0, 1]])
    corners = []
    for _ in range(8):
        rv = rng.uniform(-1, 1, 3) * np.radians([25, 25, 10])
        t = np.array([rng.uniform(-20, 20), rng.uniform(-20, 20), 600.0]) - cv2.Rodrigues(rv)[0] @ points.mean(0)
        uv = cv2.projectPoints(points, rv, t, K, np.array([-0.1, 0, 0, 0, 0.0]))[0][:, 0]
        corners.append(uv + rng.normal(0, 0.1, uv.shape))
    C = np.stack(corners)
    obs = Observations(torch.as_tensor(points), C, np.full(C.shape[:2], np.nan), (1280, 1024), 0.005)
    opts = FitOptions(distortion="k1", free_principal_point=True, model_selection=False, uncertainties=False)
    fit = fit_board(initialize(obs, "unified", options=opts, blur=False), obs, opts, "free")
    with_sigma = replace(opts, uncertainties=True)
    at_once = _with_uncertainties(fit, obs, with_sigma, "unified")
    later = _with_uncertainties(fit, obs, with_sigma, "unified", defer=True)
    assert at_once.sigma_model["name"] == "views" and at_once.deferred_sigma is None
    assert later.sigma_model["name"] == "classical" and later.deferred_sigma is not None, "classical σ until asked"
    assert later.sigma == at_once.sigma_classical, "the classical σ meanwhile"
    with_deferred_sigma(later)
    assert later.deferred_sigma is None
    assert later.sigma == at_once.sigma and later.sigma_model == at_once.sigma_model, "the same per-view σ"
    assert torch.equal(later.board.sigma, at_once.board.sigma), "the board's σ too"
    assert later.values == at_once.values


def _synthetic_views(n_views: int = 10, seed: int = 7):
    """Observations of an 8 × 6 board seen by a camera with k1 = −0.1 (0.1 px corner noise), no blur widths."""
    import cv2
    import numpy as np

    from tiltfit.calibrate.model import Observations, board_points_mm

    points = board_points_mm(8, 6, 15.0, centred=False).numpy()
    rng = np.random.default_rng(seed)
    K = np.array([[2000.0, 0, 650.0], [0, 2000.0, 505.0], [0, 0, 1]])
    corners = []
    for _ in range(n_views):
        rv = rng.uniform(-1, 1, 3) * np.radians([25, 25, 10])
        t = np.array([rng.uniform(-20, 20), rng.uniform(-20, 20), 600.0]) - cv2.Rodrigues(rv)[0] @ points.mean(0)
        uv = cv2.projectPoints(points, rv, t, K, np.array([-0.1, 0, 0, 0, 0.0]))[0][:, 0]
        corners.append(uv + rng.normal(0, 0.1, uv.shape))
    C = np.stack(corners)
    return Observations(torch.as_tensor(points), C, np.full(C.shape[:2], np.nan), (1280, 1024), 0.005)


@pytest.mark.parametrize("board", [None, "free"])
def test_held_out_folds_started_from_the_fit_agree_with_pnp_starts(board, monkeypatch):
    """The held-out folds start their training views' poses at the fit on all views (`held_out_start` "fit", the
    default; with a fitted board its points too) and the held-out views' predictions at its poses of those views,
    instead of PnP's: no PnP at all, and the same held-out error (each fold and each prediction converges to its own
    minimum)."""
    from dataclasses import replace

    from tiltfit.calibrate import start as start_module
    from tiltfit.calibrate.fit import FitOptions, fit_geometry
    from tiltfit.calibrate.start import initialize
    from tiltfit.select.held_out import held_out_rms

    obs = _synthetic_views()
    opts = FitOptions(distortion="k1", free_principal_point=True, model_selection=False, uncertainties=False)
    assert opts.held_out_start == "fit", "the default"
    full = fit_geometry(initialize(obs, "unified", options=opts, blur=False), obs, opts,
                        board=None if board is None else Board(obs.points_mm, board))
    fitted = None if board is None else full.board
    pnp = held_out_rms(obs, replace(opts, held_out_start="pnp"), 5, start=full.camera, board=fitted)
    calls = []
    real_pnp = start_module.poses_from_pnp
    monkeypatch.setattr(start_module, "poses_from_pnp", lambda o, *a: calls.append(o.n_views) or real_pnp(o, *a))
    warm = held_out_rms(obs, opts, 5, start=full.camera, board=fitted)
    assert calls == [], f"no PnP (the fit's poses start every fold and prediction), got views {calls}"
    assert warm["rms_px"] == pytest.approx(pnp["rms_px"], rel=1e-4), (warm["rms_px"], pnp["rms_px"])
    assert warm["per_view_px"] == pytest.approx(pnp["per_view_px"], rel=1e-3)


def test_fit_with_deferred_sigma_gets_those_made_at_once():
    """`_fit_camera(defer_sigma=True)` (the blur fit's) carries the classical σ until asked, then exactly the per-view
    σ the same fit made at once has (from the same solve: no refit), the free board's included."""
    from tiltfit.calibrate.fit import FitOptions, _fit_camera, _set_free_geometry, with_deferred_sigma
    from tiltfit.calibrate.start import initialize

    obs = _synthetic_views(8)
    opts = FitOptions(distortion="k1", free_principal_point=True, model_selection=False)

    def fit(defer):
        cam = initialize(obs, "unified", options=opts, blur=False)
        _set_free_geometry(cam, "unified", True, "k1")
        return _fit_camera(cam, obs, opts, mode="unified", board=Board(obs.points_mm, "free"), defer_sigma=defer)

    at_once, later = fit(False), fit(True)
    assert at_once.sigma_model["name"] == "views" and at_once.deferred_sigma is None
    assert later.sigma_model["name"] == "classical", "classical σ until asked"
    assert later.sigma == at_once.sigma_classical
    with_deferred_sigma(later)
    assert later.deferred_sigma is None and later.sigma_model == at_once.sigma_model
    no_blur = [[{k: x for k, x in v.items() if k != "rms_blur_px"} for v in f.views] for f in (later, at_once)]  # NaN
    assert later.sigma == at_once.sigma and no_blur[0] == no_blur[1], "the same per-view σ, poses' included"
    assert torch.equal(later.board.sigma, at_once.board.sigma), "the board's too"
    assert later.values == at_once.values


@pytest.mark.parametrize("classical_sigma, asked", [(10.0, False), (0.01, True)])
def test_undetermined_focus_asks_for_per_view_sigma_only_where_the_classical_leave_it_open(classical_sigma, asked):
    """The per-view σ are never below the classical ones: where the classical σ already put 1/U and d within 2σ of 0,
    the blur fit is not reported and its per-view σ are not made; otherwise they decide."""
    from types import SimpleNamespace

    from tiltfit.calibrate.blur_checks import undetermined_focus_deferred
    from tiltfit.calibrate.fit import _SIGMA_FIELDS

    calls = []
    camera = SimpleNamespace(inv_U_per_m=torch.tensor(1.0), d_mm=torch.tensor(1.0))
    views_sigma = {"inv_U_per_m": 5.0, "d_mm": 0.1}   # U undetermined, d determined
    full = SimpleNamespace(**{k: None for k in _SIGMA_FIELDS} | {"sigma": views_sigma, "board": None})
    fit = SimpleNamespace(camera=camera, sigma={"inv_U_per_m": classical_sigma, "d_mm": classical_sigma},
                          parameter_names=["inv_U_per_m", "d_scaled"], board=None,
                          deferred_sigma=lambda: calls.append(1) or full)
    out = undetermined_focus_deferred(fit)
    assert bool(calls) == asked
    assert out == (["U_mm"] if asked else ["U_mm", "d_mm"])


def _long_correction(H, r):
    """(I − H)^(−1/2) r for each view's hat block H (V, R, R) through its eigenproblem, λ clamped as
    `view_cluster_covariance` clamps it."""
    from tiltfit.uncertainty.columns import _apply_correction, _hat_eigen

    return _apply_correction(*_hat_eigen(H), r)


@pytest.mark.parametrize("rows, rank, scale", [(40, 60, 0.3), (40, 8, 1.0), (200, 300, 0.05)])
def test_lanczos_correction_equals_the_hat_blocks_eigenproblem(rows, rank, scale):
    """(I − H)^(−1/2) r by the Lanczos process equals it through H's eigenvectors: leverages of many views (small),
    of few (up to 0.4), a low-rank block whose Krylov space ends early, and one view clamped below 1."""
    from tiltfit.uncertainty.columns import _lanczos_correction

    g = torch.Generator().manual_seed(11)
    B = scale * torch.randn(4, rows, rank, generator=g, dtype=torch.float64) / rank ** 0.5
    B[0] *= 3.0
    H = B @ B.transpose(1, 2)
    r = torch.randn(4, rows, generator=g, dtype=torch.float64)
    got, done = _lanczos_correction(lambda X: (H @ X[..., None]).squeeze(-1), r)
    want = _long_correction(H, r)
    assert bool(done.all()), "every view converges"
    err = float(((got - want).norm(dim=-1) / want.norm(dim=-1)).max())
    assert err < 1e-12, f"relative difference {err:.3g}"
    if rank < rows:
        assert float(torch.linalg.eigvalsh(H[0]).max()) > 1.0 - 1e-3, "the test should clamp a leverage"


def test_free_board_sandwich_solves_no_hat_block_eigenproblem(monkeypatch):
    """A free board's per-view sandwich makes (I − H̃_vv)^(−1/2) r_v by the Lanczos process: no eigenproblem of a
    view's R × R hat block, and the covariance the hat blocks' eigenvectors give (forced: every view unconverged)."""
    from tests.tiltfit.test_solve import _points_seen_by_cameras
    from tiltfit.solve import levenberg_marquardt
    from tiltfit.uncertainty import columns
    from tiltfit.uncertainty.covariance import view_cluster_covariance

    evaluate, blocks, view_rows, row_points, x0 = _points_seen_by_cameras()
    res = levenberg_marquardt(evaluate, x0, blocks, view_rows, row_points=row_points)
    s2 = 2.0 * res.cost / (res.r.numel() - res.x_flat.numel())
    R = view_rows.shape[1]
    sizes = []
    eigh = torch.linalg.eigh

    def recording(A, *args, **kwargs):
        sizes.append(tuple(A.shape))
        return eigh(A, *args, **kwargs)

    monkeypatch.setattr(torch.linalg, "eigh", recording)
    got = view_cluster_covariance(res, s2)[0].dense()
    hat = [s for s in sizes if len(s) == 3 and s[0] == view_rows.shape[0] and s[-1] == R]
    assert not hat, f"an eigenproblem of each view's {R} × {R} hat block: {hat}"
    monkeypatch.setattr(columns, "LANCZOS_STEPS", 1)                    # no view converges: the eigenproblem
    want = view_cluster_covariance(res, s2)[0].dense()
    assert any(len(s) == 3 and s[-1] == R for s in sizes), "the fallback solves the hat blocks' eigenproblem"
    assert torch.allclose(got, want, rtol=1e-10, atol=1e-14), \
        f"largest difference {float((got - want).abs().max()):.3g} of {float(want.abs().max()):.3g}"


def test_pose_random_effect_of_corner_rows_only_reads_the_trace(monkeypatch):
    """Where every row with a Jacobian is a corner row (a geometric fit), Σ_i J̃_i S⁻¹ GG S⁻¹ J̃_iᵀ is tr(S⁻¹ GG):
    one product of the point columns with an (S, S) matrix (J̃ S⁻¹) instead of two, and the same τ² and poses' σ as
    the sum over the rows."""
    from tests.tiltfit.test_solve import _points_seen_by_cameras
    from tiltfit.solve import levenberg_marquardt
    from tiltfit.uncertainty import columns
    from tiltfit.uncertainty.covariance import view_cluster_covariance

    evaluate, blocks, view_rows, row_points, x0 = _points_seen_by_cameras()
    res = levenberg_marquardt(evaluate, x0, blocks, view_rows, row_points=row_points)
    s2 = 2.0 * res.cost / (res.r.numel() - res.x_flat.numel())
    gen = torch.Generator().manual_seed(5)
    modes = torch.randn(*view_rows.shape, 3, generator=gen, dtype=torch.float64)
    kinds = torch.ones(view_rows.shape, dtype=torch.long)
    right = columns._PointColumns.right
    products = []

    def counted(self, M):
        products.append(tuple(M.shape))
        return right(self, M)

    monkeypatch.setattr(columns._PointColumns, "right", counted)
    got, info = view_cluster_covariance(res, s2, modes, kinds)
    square = [s for s in products if len(s) == 2 and s[0] == s[1]]
    assert len(square) == 1, f"products with an (S, S) matrix: {square}"
    monkeypatch.setattr(columns._PointColumns, "rows_touch", lambda self, rows: True)   # the sum over the rows
    want, info_rows = view_cluster_covariance(res, s2, modes, kinds)
    assert torch.allclose(got.dense(), want.dense(), rtol=1e-10, atol=1e-14)
    for k in ("view_error_px", "pose_ratio_min", "pose_ratio_max"):
        assert info[k] == pytest.approx(info_rows[k], rel=1e-9), k
    assert info["view_error_px"] > 0, "the random effect should be estimated (τ² > 0)"


def test_initialize_reads_its_start_without_copying_it(monkeypatch):
    """`initialize(init=camera)` (each held-out fold's and prediction's start) reads the camera's lens without copying
    it, and leaves it as it was (its values and free/frozen state); unobserved corners' Jacobian rows stay 0."""
    from renderer.cameras.lens_model import LensCamera
    from tiltfit.calibrate.fit import FitOptions, fit_geometry
    from tiltfit.calibrate.problem import _Problem
    from tiltfit.calibrate.start import initialize

    obs = _synthetic_views(6)
    obs.corners_px[2, :5] = float("nan")  # five unobserved corners
    opts = FitOptions(distortion="k1", model_selection=False, uncertainties=False)
    start = fit_geometry(initialize(obs, "unified", options=opts, blur=False), obs, opts).camera
    before = {n: (p.detach().clone(), p.requires_grad) for n, p in start.named_parameters()}
    real = LensCamera.copy
    monkeypatch.setattr(LensCamera, "copy", lambda self: pytest.fail("initialize copied its start"))
    poses = (start.rvec.detach(), start.T_mm.detach())
    cam = initialize(obs, "unified", init=start, options=opts, blur=False, poses=poses)
    monkeypatch.setattr(LensCamera, "copy", real)
    for n, p in start.named_parameters():
        assert torch.equal(p.detach(), before[n][0]) and p.requires_grad == before[n][1], n
    assert float(cam.w_mm.detach()) == float(start.w_mm.detach())
    assert torch.equal(cam.distortion.detach(), start.distortion.detach())
    prob = _Problem(cam, obs)
    J, r = prob._raw_jacobian_matrix(prob.x0(), prob.names)
    rows = ~prob.corner_rows
    assert int(rows.sum()) == 10 and bool((J[rows] == 0).all()) and bool((r[rows] == 0).all())
    assert bool((J[prob.corner_rows] != 0).any(1).all()), "observed rows keep their derivatives"


def test_residuals_without_blur_widths_model_no_blur(monkeypatch):
    """`residuals` of observations without blur widths (every geometric fit's report) leaves the blur model out: the
    same corner residuals, blur residuals 0, and no blur computed."""
    from renderer.cameras.lens_model import LensCamera
    from tiltfit.calibrate.fit import FitOptions
    from tiltfit.calibrate.model import residuals
    from tiltfit.calibrate.start import initialize

    obs = _synthetic_views(4)
    obs.corners_px[1, :3] = float("nan")
    cam = initialize(obs, "unified", options=FitOptions(), blur=False)
    with torch.no_grad():
        uv, _ = cam(obs.points_mm)
        monkeypatch.setattr(LensCamera, "blur_camera", lambda *a: pytest.fail("blur computed"))
        got = residuals(cam, obs)
    want = torch.where(obs.corner_mask[..., None], uv - torch.nan_to_num(obs.corners_px), torch.zeros_like(uv))
    assert torch.equal(got.corners_px, want) and torch.equal(got.blur_px, torch.zeros_like(got.blur_px))
    assert not bool(got.blur_mask.any())
