"""tiltfit.calibrate.model: projection, blur, parametrisation, residuals and synthetic observations."""
import math

import numpy as np
import pytest
import torch
from torch.func import functional_call

from renderer.cameras import optics
from tiltfit.calibrate.model import (BLUR_MODELS, PAPER_LENS, PAPER_SENSOR, Observations, LensCamera,
                           axis_angle_to_matrix, blur_diameter_mm, board_points_mm, loss,
                           matrix_to_axis_angle, normalized_residual_vector, random_poses, residuals,
                           robust_rho, robust_weight, synthesize_observations)

F_PAPER = PAPER_LENS["w_mm"] * PAPER_LENS["U_mm"] / (PAPER_LENS["w_mm"] + PAPER_LENS["U_mm"])


def paper_camera(n_views=3, seed=0, theta_L_deg=0.0, **kw):
    rvec, T = random_poses(n_views, seed)
    if theta_L_deg:
        return LensCamera.from_tilted_lens(n_views, **PAPER_SENSOR, w_mm=PAPER_LENS["w_mm"], f_mm=F_PAPER,
                                               d_mm=PAPER_LENS["d_mm"], theta_L=math.radians(theta_L_deg),
                                               rvec=rvec, T_mm=T, **kw)
    return LensCamera(n_views, **PAPER_SENSOR, **PAPER_LENS, rvec=rvec, T_mm=T, **kw)


# --- projection ----------------------------------------------------------------------------------------------

def test_pixel_convention_odd_non_square_image():
    cam = LensCamera(1, (7, 4), pixel_pitch_mm=0.5, w_mm=10.0, U_mm=100.0, d_mm=1.0, T_mm=[[0.0, 0.0, 0.0]])
    on_axis = cam.project(torch.tensor([0.0, 0.0, 50.0]), 0)
    assert torch.allclose(on_axis, torch.tensor([3.0, 1.5], dtype=torch.float64)), \
        f"the optical axis must land on ((W-1)/2, (H-1)/2) = (3, 1.5), got {on_axis.tolist()}"
    # One pixel pitch on the sensor (0.5 mm at w = 10) is x/z = 0.05: one pixel right / down.
    right_down = cam.project(torch.tensor([[2.5, 0.0, 50.0], [0.0, 2.5, 50.0]]), 0)
    expected = torch.tensor([[4.0, 1.5], [3.0, 2.5]], dtype=torch.float64)
    assert torch.allclose(right_down, expected), f"x right and y down by one pixel, got {right_down.tolist()}"


def test_principal_point_moves_the_image():
    cam = LensCamera(1, (7, 4), 0.5, 10.0, 100.0, 1.0, T_mm=[[0.0, 0.0, 0.0]], principal_point_px=(3.5, 2.0))
    uv = cam.project(torch.tensor([0.0, 0.0, 50.0]), 0)
    assert torch.allclose(uv, torch.tensor([3.5, 2.0], dtype=torch.float64)), f"principal point ignored: {uv}"


def test_project_matches_opencv():
    import cv2

    cam = paper_camera(3, seed=4)
    pts = board_points_mm()
    W, H = cam.image_size_px
    F = float(cam.focal_px.detach())
    K = np.array([[F, 0, (W - 1) / 2], [0, F, (H - 1) / 2], [0, 0, 1.0]])
    for v in range(3):
        ref, _ = cv2.projectPoints(pts.numpy(), cam.rvec[v].detach().numpy(), cam.T_mm[v].detach().numpy(), K, None)
        ours = cam.project(pts, v).detach().numpy()
        err = np.abs(ours - ref[:, 0]).max()
        assert err < 1e-6, f"view {v}: projection differs from cv2.projectPoints by {err} px"


def test_shapes_all_views_and_batches():
    cam = paper_camera(4)
    pts = board_points_mm()[:6].reshape(2, 3, 3)
    assert cam.project(pts, 2).shape == (2, 3, 2), "one view keeps the points' batch shape"
    assert cam.project(pts).shape == (4, 2, 3, 2), "view=None adds a leading view dimension"
    assert cam.blur(pts).shape == (4, 2, 3), "blur of all views"
    uv, b = cam(board_points_mm())
    assert uv.shape == (4, 40, 2) and b.shape == (4, 40), f"forward shapes {uv.shape}, {b.shape}"
    assert torch.allclose(uv[2], cam.project(board_points_mm(), 2)), "forward equals per-view project"


def test_float32_follows_module_dtype():
    cam = paper_camera(2).float()
    uv = cam.project(board_points_mm().float())
    assert uv.dtype == torch.float32 and torch.isfinite(uv).all(), "float32 camera gives float32 pixels"


# --- blur ---------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("model", BLUR_MODELS)
def test_blur_untilted_is_eq2(model):
    cam = paper_camera(2, blur_model=model)
    pts = board_points_mm()
    p_cam = cam.to_camera(pts)
    w, U, d = PAPER_LENS["w_mm"], PAPER_LENS["U_mm"], PAPER_LENS["d_mm"]
    eq2 = w * d * torch.abs(1 / U - 1 / p_cam[..., 2]) / PAPER_SENSOR["pixel_pitch_mm"]
    err = (cam.blur(pts) - eq2).abs().max()
    assert err < 1e-9, f"{model}: untilted blur must equal eq (2), max error {err} px"


@pytest.mark.parametrize("model", BLUR_MODELS)
def test_blur_vanishes_on_the_tilted_plane_of_focus(model):
    cam = paper_camera(1, theta_L_deg=5.0, blur_model=model)
    y = torch.linspace(-100, 100, 9, dtype=torch.float64)
    z = cam.U_mm + y * torch.tan(cam.theta_F)
    p_cam = torch.stack([torch.linspace(-80, 80, 9, dtype=torch.float64), y, z], -1).detach()
    b = cam.blur_camera(p_cam)
    assert b.abs().max() < 1e-9, f"{model}: points on z = U + y tan θF must be sharp, got {b.max()} px"


def test_blur_models_against_optics():
    cam = paper_camera(1, theta_L_deg=5.0)
    p_cam = cam.to_camera(board_points_mm(), 0).detach()
    args = (cam.w_mm, cam.U_mm, cam.d_mm, cam.theta_F)
    exact = optics.blur_diameter_exact(p_cam, *args)
    first = optics.blur_diameter_first_order(p_cam, *args)
    assert torch.allclose(blur_diameter_mm(p_cam, *args, blur_model="ellipse"), exact), "ellipse = exact area"
    assert torch.allclose(blur_diameter_mm(p_cam, *args, blur_model="first_order"), first), "first order"
    rel = ((exact - first) / first).abs().max()
    assert rel < 0.03, f"at θL = 5° the exact and first-order blur differ by under 3 %, got {rel:.3%}"


def test_tilted_lens_relations_paper_numbers():
    cam = paper_camera(1, theta_L_deg=5.0)
    s = cam.summary()
    assert abs(s["U_mm"] - 648.4) < 0.1, f"hinge rule: U moves 618.4 -> 648.4 mm, got {s['U_mm']}"
    assert abs(s["theta_F_deg"] - 48.03) < 0.01, f"Scheimpflug: θF = 48.03°, got {s['theta_F_deg']}"
    assert abs(s["theta_L_deg"] - 5.0) < 1e-9, f"exact θL round trip, got {s['theta_L_deg']}"
    assert abs(s["theta_L_paper_deg"] - 4.62) < 0.01, f"eq (1) maps back to 4.62°, got {s['theta_L_paper_deg']}"
    assert abs(s["f_mm"] - F_PAPER) < 1e-9, f"focal length kept, got {s['f_mm']}"


# --- rotations, parametrisation ------------------------------------------------------------------------------

def test_axis_angle_round_trip_and_zero():
    rvec = torch.tensor([[0.3, -0.2, 0.1], [0.0, 0.0, 0.0], [1e-6, 0.0, 0.0]], dtype=torch.float64)
    R = axis_angle_to_matrix(rvec)
    assert torch.allclose(R @ R.transpose(-1, -2), torch.eye(3, dtype=torch.float64).expand(3, 3, 3)), \
        "rotations must be orthonormal"
    assert torch.allclose(matrix_to_axis_angle(R), rvec, atol=1e-12), "axis-angle round trip, small angles too"
    r0 = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    axis_angle_to_matrix(r0).sum().backward()
    assert torch.isfinite(r0.grad).all(), "the gradient at the identity must be finite"


def test_free_and_freeze():
    cam = paper_camera(2)
    assert cam.free_parameter_names() == ["log_w_mm", "inv_U_per_m", "d_scaled", "theta_F", "rvec", "T_scaled"], \
        "default: everything free but the principal point"
    cam.freeze("lens", "theta_F")
    assert cam.free_parameter_names() == ["rvec", "T_scaled"], "lens and θF frozen"
    cam.free("principal_point", "w")
    assert cam.free_parameter_names() == ["log_w_mm", "rvec", "T_scaled", "pp_scaled"], "w and pp freed"
    obs = synthesize_observations(paper_camera(2, seed=1), board_points_mm(), 0.1, 0.5, seed=0)
    loss(cam, obs).backward()
    assert cam.inv_U_per_m.grad is None and cam.theta_F.grad is None, "frozen parameters get no gradient"
    assert cam.log_w_mm.grad is not None and cam.pp_scaled.grad is not None, "free parameters get one"
    with pytest.raises(ValueError, match="unknown parameter"):
        cam.free("focal")


def test_parametrisation_round_trip():
    cam = LensCamera(2, (100, 80), 0.01, 50.0, 700.0, 12.0, theta_F=0.3, T_mm=[[1, 2, 600], [3, 4, 500]],
                         principal_point_px=(50.0, 41.0))
    s = cam.summary()
    assert abs(s["w_mm"] - 50) < 1e-12 and abs(s["U_mm"] - 700) < 1e-9, "lengths stored as logarithms"
    assert torch.allclose(cam.T_mm, torch.tensor([[1, 2, 600], [3, 4, 500]], dtype=torch.float64)), "T scaled"
    assert torch.allclose(cam.principal_point_px, torch.tensor([50.0, 41.0], dtype=torch.float64)), "pp"
    with pytest.raises(ValueError, match="w_mm"):
        LensCamera(1, (10, 10), 0.01, -5.0, 700.0, 12.0)
    with pytest.raises(ValueError, match="blur_model"):
        LensCamera(1, (10, 10), 0.01, 5.0, 700.0, 12.0, blur_model="gauss")


# --- gradcheck -----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("model", BLUR_MODELS)
def test_gradcheck_project_and_blur(model):
    cam = paper_camera(2, theta_L_deg=3.0, blur_model=model)
    cam.free("all")
    names = [n for n, _ in cam.named_parameters()]
    values = tuple(p.detach().clone().requires_grad_(True) for _, p in cam.named_parameters())
    pts = board_points_mm()[::7].clone().requires_grad_(True)

    def f(X, *params):
        uv, b = functional_call(cam, dict(zip(names, params)), (X,))
        return uv / 1000.0, b

    assert torch.autograd.gradcheck(f, (pts, *values), eps=1e-6, atol=1e-6, rtol=1e-5), \
        f"{model}: analytic gradients of project/blur differ from finite differences"


# --- residuals, loss, robust ---------------------------------------------------------------------------------

def test_residuals_zero_at_truth_and_masked():
    cam = paper_camera(3)
    obs = synthesize_observations(cam, board_points_mm(), 0.0, 0.0, seed=0)
    obs.corners_px[1, 5] = float("nan")
    obs.blur_px[2, 7] = float("nan")
    r = residuals(cam, obs)
    assert r.corners_px.abs().max() < 1e-9 and r.blur_px.abs().max() < 1e-9, "noise-free data fit exactly"
    assert not r.corner_mask[1, 5] and not r.blur_mask[2, 7], "NaN marks a missing observation"
    vec = normalized_residual_vector(cam, obs)
    assert vec.shape == (3 * 40 * 3,) and torch.isfinite(vec).all(), "fixed-length finite residual vector"


def test_robust_losses():
    s2 = torch.tensor([0.0, 1.0, 4.0, 100.0], dtype=torch.float64)
    assert torch.equal(robust_rho(s2), s2), "no robust loss is quadratic"
    for kind in ("huber", "cauchy"):
        rho = robust_rho(s2, kind, 3.0)
        assert torch.allclose(rho[:2], s2[:2], rtol=0.06), f"{kind}: quadratic near zero"
        assert rho[3] < 0.7 * s2[3], f"{kind}: outliers cost less than quadratic"
        # The IRLS weight is dρ/ds².
        s = s2.clone().requires_grad_(True)
        robust_rho(s, kind, 3.0).sum().backward()
        assert torch.allclose(s.grad, robust_weight(s2, kind, 3.0)), f"{kind}: weight = dρ/ds²"


def test_loss_with_torch_optimizer_improves_fit():
    truth = paper_camera(2, seed=2)
    obs = synthesize_observations(truth, board_points_mm(), 0.05, 0.5, seed=3)
    cam = truth.copy()
    with torch.no_grad():
        cam.log_w_mm += 0.01
        cam.rvec += 0.002
    cam.freeze("lens", "theta_F")
    cam.free("w")
    opt = torch.optim.LBFGS([p for p in cam.parameters() if p.requires_grad], max_iter=40,
                            line_search_fn="strong_wolfe")
    start = float(loss(cam, obs, 0.05, 0.5).detach())

    def closure():
        opt.zero_grad()
        value = loss(cam, obs, 0.05, 0.5)
        value.backward()
        return value

    opt.step(closure)
    end = float(loss(cam, obs, 0.05, 0.5).detach())
    assert end < 0.01 * start, f"LBFGS on the public loss should reduce it a hundredfold: {start} -> {end}"
    w = cam.summary()["w_mm"]
    assert abs(w / PAPER_LENS["w_mm"] - 1) < 1e-3, f"w recovered to 0.1 %, got {w}"


# --- synthetic observations ----------------------------------------------------------------------------------

def test_synthesize_noise_levels_and_seed():
    cam = paper_camera(6, seed=5)
    pts = board_points_mm()
    clean = synthesize_observations(cam, pts, 0.0, 0.0, seed=0)
    noisy = synthesize_observations(cam, pts, 0.1, 0.8, seed=11)
    again = synthesize_observations(cam, pts, 0.1, 0.8, seed=11)
    assert torch.equal(noisy.corners_px, again.corners_px), "same seed, same observations"
    dc = (noisy.corners_px - clean.corners_px)[noisy.corner_mask]
    db = (noisy.blur_px - clean.blur_px)[noisy.blur_mask & (clean.blur_px > 4)]
    assert 0.085 < float(dc.std()) < 0.115, f"corner noise σ should be 0.1 px, got {float(dc.std())}"
    assert 0.6 < float(db.std()) < 1.0, f"blur noise σ should be 0.8 px, got {float(db.std())}"
    assert (noisy.blur_px[noisy.blur_mask] >= 0).all(), "blur widths are never negative"


def test_synthesize_marks_points_outside_the_image():
    cam = LensCamera(1, (100, 80), 0.01, 10.0, 500.0, 5.0, T_mm=[[0.0, 0.0, 500.0]])
    pts = torch.tensor([[0.0, 0.0, 0.0], [400.0, 0.0, 0.0], [0.0, 0.0, -600.0]], dtype=torch.float64)
    obs = synthesize_observations(cam, pts, 0.0, 0.0)
    assert obs.corner_mask.tolist() == [[True, False, False]], "off-image and behind-camera points are missing"
    assert isinstance(obs, Observations) and obs.names == ["view0"], "default view names"


def test_observations_validate_shapes():
    with pytest.raises(ValueError, match="corners_px"):
        Observations(torch.zeros(4, 3), torch.zeros(2, 5, 2), torch.zeros(2, 4), (10, 10), 0.01)
