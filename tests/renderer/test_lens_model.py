"""renderer.LensCamera, the one camera model: its views render with the renderer's thin lens and agree with its
own closed-form projection; gradients of a rendered image reach the module's parameters (finite differences).

Also the one pinhole projection (`project_pinhole`) against OpenCV, and the one Rodrigues / look-at.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from renderer import (CameraTransform, LensCamera, ThinLensCamera, axis_angle_to_matrix, load_scene,
                      matrix_to_axis_angle, project_pinhole, write_image)
from renderer.tracing.integrator import trace
from renderer.core.transforms import look_at_rotation


def _random_camera(seed: int, n_views: int = 3) -> LensCamera:
    """A lens state with θF ≠ 0, distortion and an off-centre principal point, and random poses (mm)."""
    g = np.random.default_rng(seed)
    rvec = g.uniform(-0.35, 0.35, (n_views, 3))
    T = np.stack([g.uniform(-40, 40, n_views), g.uniform(-30, 30, n_views), g.uniform(400, 900, n_views)], -1)
    W, H = 641, 427  # odd, non-square
    pp = (W / 2 + g.uniform(-25, 25), H / 2 + g.uniform(-20, 20))
    k = (g.uniform(-0.2, 0.05), g.uniform(-0.05, 0.1), g.uniform(-2e-3, 2e-3), g.uniform(-2e-3, 2e-3),
         g.uniform(-0.02, 0.02))
    return LensCamera(n_views, (W, H), 0.02, w_mm=g.uniform(20, 60), U_mm=g.uniform(300, 1200),
                      d_mm=g.uniform(2, 20), theta_F=math.radians(g.uniform(-45, 45)), rvec=rvec, T_mm=T,
                      principal_point_px=pp, distortion=k)


def _points_in_view(cam: LensCamera, view: int, n: int = 200, seed: int = 0) -> torch.Tensor:
    """(n, 3) world points whose images fall inside the frame of `view` (made in the camera frame, moved out)."""
    g = torch.Generator().manual_seed(seed)
    z = 300 + 900 * torch.rand(n, generator=g, dtype=torch.float64)
    W, H = cam.image_size_px
    half = torch.tensor([0.4 * W, 0.4 * H], dtype=torch.float64) * cam.pixel_pitch_mm / float(cam.w_mm.detach())
    xy = (2 * torch.rand(n, 2, generator=g, dtype=torch.float64) - 1) * half * z[:, None]
    p_cam = torch.cat([xy, z[:, None]], -1)
    with torch.no_grad():
        R, T = cam.R[view], cam.T_mm[view]
        return (p_cam - T) @ R  # X = Rᵀ (p − T)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_view_camera_projects_like_the_module_and_its_chief_rays_hit_the_points(seed):
    cam = _random_camera(seed)
    tilted, distorted = abs(float(cam.theta_F.detach())) > 1e-3, bool(cam.distortion.detach().abs().sum() > 0)
    assert tilted and distorted, "a tilted plane of focus and a distorting lens"
    for v in range(cam.n_views):
        X = _points_in_view(cam, v, seed=seed + 10 * v)
        with torch.no_grad():
            view = cam.view_camera(v)
            assert isinstance(view, ThinLensCamera), "a renderer camera"
            uv_module = cam.project(X, v)
            uv_view = view.project(X)
            err = float((uv_module - uv_view).abs().max())
            assert err < 1e-9, f"view {v}: ThinLensCamera.project vs LensCamera.project differ by {err:.3g} px"
            W, H = cam.image_size_px
            assert bool(((uv_view > -0.5) & (uv_view < torch.tensor([W - 0.5, H - 0.5]))).all()), "in frame"
            # The chief ray (lens sample at the disc centre) of that pixel passes through the point.
            rays = view.generate_rays(uv_view, torch.full_like(uv_view, 0.5))
            assert bool(rays.valid.all()), "every pixel could be undistorted"
            to_X = X - rays.origin
            miss = torch.linalg.cross(to_X, rays.direction).norm(dim=-1) / to_X.norm(dim=-1)
            assert float(miss.max()) < 1e-11, f"view {v}: chief ray misses its point by {float(miss.max()):.3g} rad"
            centre = -(cam.R[v].T @ cam.T_mm[v])
            assert float((rays.origin - centre).abs().max()) < 1e-9, "chief rays start at the lens centre"


def test_view_camera_carries_the_lens_state():
    cam = _random_camera(3).requires_grad_(False)
    view = cam.view_camera(1)
    lens = view.lens
    checks = {"w": (lens.w, cam.w_mm), "U": (lens.U, cam.U_mm), "d": (lens.d, cam.d_mm),
              "theta_F": (lens.theta_F, cam.theta_F), "theta_L": (lens.theta_L, cam.theta_L), "f": (lens.f, cam.f_mm)}
    for name, (a, b) in checks.items():
        assert float(a) == pytest.approx(float(b), rel=1e-14), f"{name}: view {float(a)} vs module {float(b)}"
    assert tuple(float(c) for c in view.screen.center_px) == pytest.approx(
        tuple(float(c) for c in cam.principal_point_px), abs=1e-12), "principal point"
    assert (view.width, view.height) == cam.image_size_px, "image size"
    # A camera whose distortion is all zero and held has none (the renderer's fast path), and out-of-range views fail.
    plain = LensCamera(2, (40, 30), 0.1, 30.0, 500.0, 5.0)
    assert plain.view_camera(0).distortion is None or plain.view_camera(0).distortion.is_identity, "no distortion"
    with pytest.raises(IndexError, match="view"):
        plain.view_camera(2)


# --------------------------------------------------------------------------- gradients of a rendered image

W_PX, H_PX, PITCH_MM = 9, 7, 0.5


@pytest.fixture(scope="module")
def board(tmp_path_factory):
    """A textured board on the world plane Z = 0 (a smooth random image texture) under a point light, mm."""
    folder = tmp_path_factory.mktemp("tex")
    tex = np.random.default_rng(1).uniform(0.2, 0.9, (6, 6, 3)).astype(np.float32)
    write_image(str(folder / "tex.exr"), tex)
    cfg = {
        "image": {"width": W_PX, "height": H_PX},
        "camera": {"type": "pinhole", "screen_distance": 1.0, "screen_size": [1.0, 1.0]},
        "lights": [{"type": "point", "position": [60.0, -90.0, -450.0], "intensity": [1e5, 1e5, 1e5]}],
        "objects": [{"name": "board",
                     "shape": {"type": "rectangle", "center": [0.0, 0.0, 0.0], "size": [900.0, 900.0],
                               "rotation_deg": [0.0, 0.0, 0.0]},
                     "material": {"texture": {"type": "image", "file": "tex.exr", "size": [150.0, 150.0]}}}],
    }
    return load_scene(cfg, base_dir=str(folder))


#: (stored parameter, index or None, step) checked against central differences.
FD_PARAMETERS = [("log_w_mm", None, 1e-6), ("inv_U_per_m", None, 1e-6), ("d_scaled", None, 1e-6),
                 ("theta_F", None, 1e-6), ("rvec", (0, 1), 1e-6), ("T_scaled", (0, 2), 1e-6),
                 ("pp_scaled", 0, 1e-6), ("dist_k1", None, 1e-6)]


def test_rendered_image_gradients_reach_the_module_parameters(board):
    cam = LensCamera(1, (W_PX, H_PX), PITCH_MM, w_mm=50.0, U_mm=600.0, d_mm=20.0, theta_F=math.radians(30.0),
                     rvec=[[0.3, -0.2, 0.05]], T_mm=[[5.0, -3.0, 620.0]], principal_point_px=(4.3, 2.8),
                     distortion=(-0.05, 0.01)).free("all")
    g = torch.Generator().manual_seed(5)
    uv = torch.rand(10, 2, generator=g, dtype=torch.float64) * torch.tensor([W_PX - 1.0, H_PX - 1.0])
    lens = 0.15 + 0.7 * torch.rand(10, 2, generator=g, dtype=torch.float64)  # off the lens centre
    weights = torch.rand(10, 3, generator=g, dtype=torch.float64)

    def objective():
        rays = cam.view_camera(0).generate_rays(uv, lens)
        rgb, found = trace(board, rays.origin, rays.direction)
        assert bool(found.all()) and bool(rays.valid.all()), "every ray hits the board (no visibility edge)"
        return (weights * rgb).sum(), rgb

    value, rgb = objective()
    assert float(rgb.detach().min()) > 0, "lit and textured: no black sample"
    grads = dict(zip([n for n, _ in cam.named_parameters()], torch.autograd.grad(value, list(cam.parameters()),
                                                                                 allow_unused=True)))
    for name, index, eps in FD_PARAMETERS:
        p = getattr(cam, name)
        analytic = grads[name] if index is None else grads[name][index]
        assert analytic is not None, f"{name}: no gradient reaches it"
        with torch.no_grad():
            x0 = p[index].clone() if index is not None else p.clone()
            p[index if index is not None else ...] = x0 + eps
            up = float(objective()[0])
            p[index if index is not None else ...] = x0 - eps
            down = float(objective()[0])
            p[index if index is not None else ...] = x0
        fd = (up - down) / (2 * eps)
        assert abs(fd) > 1e-6, f"{name}: moves the image (d/d{name} = {fd:.3g})"
        assert float(analytic) == pytest.approx(fd, rel=2e-4, abs=1e-7), \
            f"{name}: autograd {float(analytic):.9g} vs central difference {fd:.9g}"


# --------------------------------------------------------------------------- the one projection and rotation

def test_project_pinhole_equals_opencv_and_handles_anisotropic_pixels():
    cv2 = pytest.importorskip("cv2")
    g = np.random.default_rng(4)
    p = np.stack([g.uniform(-200, 200, 50), g.uniform(-150, 150, 50), g.uniform(300, 900, 50)], -1)
    k = np.array([-0.12, 0.03, 1e-3, -5e-4, 0.01, 0.002, -0.001, 0.0005])
    fx, fy, cx, cy = 2400.0, 2390.0, 655.3, 470.1
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    ref, _ = cv2.projectPoints(p, np.zeros(3), np.zeros(3), K, k)
    got = project_pinhole(torch.tensor(p), (fx, fy), (cx, cy), torch.tensor(k)).numpy()
    err = np.abs(got - ref.reshape(-1, 2)).max()
    assert err < 1e-6, f"project_pinhole vs cv2.projectPoints (rational model, fx ≠ fy): {err:.3g} px"
    plain = project_pinhole(torch.tensor(p), fx, (cx, cy)).numpy()
    expect = np.stack([cx + fx * p[:, 0] / p[:, 2], cy + fx * p[:, 1] / p[:, 2]], -1)
    assert np.abs(plain - expect).max() < 1e-9, "without distortion: uv = c + f (x/z, y/z)"


def test_rodrigues_and_look_at_are_the_rotations_of_both_packages():
    cv2 = pytest.importorskip("cv2")
    g = np.random.default_rng(7)
    rv = g.normal(0, 1.0, (20, 3))
    R = axis_angle_to_matrix(torch.tensor(rv)).numpy()
    ref = np.stack([cv2.Rodrigues(r)[0] for r in rv])
    assert np.abs(R - ref).max() < 1e-12, "Rodrigues equals OpenCV's"
    back = matrix_to_axis_angle(torch.tensor(R)).numpy()
    assert np.abs(axis_angle_to_matrix(torch.tensor(back)).numpy() - R).max() < 1e-9, "axis-angle round trip"
    small = torch.tensor([1e-7, -2e-7, 3e-7], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(axis_angle_to_matrix, (small,)), "smooth and differentiable at 0"
    # look-at: the camera at C looking at the origin sees it on its axis, `up` upwards (−y) in the image.
    C = torch.tensor([100.0, -50.0, -400.0], dtype=torch.float64)
    pose = CameraTransform(look_at_rotation(C, (0.0, 0.0, 0.0), (0.0, -1.0, 0.0)), C)
    R_cw, T = pose.world_from_camera.T, -(pose.world_from_camera.T @ C)
    via_extrinsics = CameraTransform.from_extrinsics(R_cw, T)
    assert torch.allclose(via_extrinsics.position, C, atol=1e-12), "from_extrinsics inverts the pose"
    origin_cam = pose.points_to_camera(torch.zeros(3, dtype=torch.float64))
    assert float(origin_cam[:2].abs().max()) < 1e-12 and float(origin_cam[2]) > 0, "target on the optical axis"
    up_cam = pose.points_to_camera(torch.tensor([0.0, -10.0, 0.0], dtype=torch.float64))
    assert float(up_cam[1] / up_cam[2]) < 0, "world up appears above the axis (negative y)"


def test_copy_is_deepcopys_without_walking_the_module(monkeypatch):
    """`LensCamera.copy` gives what `copy.deepcopy` gives (the same numbers, free/frozen state, settings and
    buffers, none of them shared) without calling it (issue 32 §0: a calibration copies its camera hundreds of
    times)."""
    import copy as copy_module

    from renderer.cameras import lens_model

    cam = _random_camera(4).free("principal_point", "k1")
    cam.distortion_centre = "lens_axis"
    want = copy_module.deepcopy(cam)
    monkeypatch.setattr(lens_model.copy, "deepcopy", lambda *a: pytest.fail("deepcopy called"))
    got = cam.copy()
    assert type(got) is LensCamera and got.__dict__.keys() == want.__dict__.keys()
    for (n, p), (m, q) in zip(got.named_parameters(), want.named_parameters()):
        assert n == m and type(p) is type(q) and p.requires_grad == q.requires_grad and torch.equal(p, q), n
        assert p.data_ptr() != dict(cam.named_parameters())[n].data_ptr(), f"{n} shares the original's memory"
    for (n, b), (_, c) in zip(got.named_buffers(), want.named_buffers()):
        assert torch.equal(b, c) and b.data_ptr() != dict(cam.named_buffers())[n].data_ptr(), n
    for k, v in want.__dict__.items():
        if not isinstance(v, dict):
            assert got.__dict__[k] == v, k
        else:
            assert got.__dict__[k] is not cam.__dict__[k], f"{k} shared with the original"
    with torch.no_grad():
        got.rvec.add_(1.0)
        got.log_w_mm.add_(1.0)
    got.freeze("all")
    assert torch.equal(cam.rvec, want.rvec) and torch.equal(cam.log_w_mm, want.log_w_mm)
    assert cam.pp_scaled.requires_grad, "freezing the copy froze the original"
    uv_cam, _ = cam(torch.zeros(1, 3, dtype=torch.float64))
    uv_copy, _ = cam.copy()(torch.zeros(1, 3, dtype=torch.float64))
    assert torch.equal(uv_cam, uv_copy)
