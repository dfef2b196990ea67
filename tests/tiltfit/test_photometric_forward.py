"""The photometric fit's lens-sample path: the same dark fraction as the thin lens's own traced rays, from each
pixel's focus geometry alone (no ray traced per lens sample), with a Jacobian that asks for no rays either."""
from __future__ import annotations

import math
import os
import sys

import numpy as np
import pytest
import torch

sys.path.insert(0, os.path.dirname(__file__))
import test_photometric as tp  # noqa: E402  (the board, the lens and the camera helper)

from renderer import Lens, Sensor  # noqa: E402
from renderer.cameras import EOS_6D, ThinLensCamera, optics  # noqa: E402
from tiltfit.experiments import reproduce  # noqa: E402
from tiltfit.photometric import checker_dark_fraction, dark_fraction_samples, hammersley_disc_samples  # noqa: E402
from tiltfit.photometric.problem import _Problem, _View  # noqa: E402
from tiltfit.photometric.render import on_board  # noqa: E402


def _traced_dark_fraction(target, cam, uv_px, lens_uv, psf_var_px2):
    """The reference: every lens sample traced by `generate_rays` from the 2 x 2 sub-pixel centres and met with the
    board plane, the footprint from the chief rays of the pixel and its right and lower neighbours."""
    n, s = uv_px.shape[0], lens_uv.shape[0]
    sub = torch.tensor([[-0.25, -0.25], [0.25, -0.25], [-0.25, 0.25], [0.25, 0.25]], dtype=uv_px.dtype)
    uv_s = (uv_px[:, None, None, :] + sub[None, :, None, :]).expand(n, 4, s, 2)
    hit = on_board(cam.generate_rays(uv_s, lens_uv[None, None].expand(n, 4, s, 2))).reshape(n, 4 * s, 3)
    steps = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]], dtype=uv_px.dtype)
    chief = on_board(cam.generate_rays(uv_px[:, None, :] + steps, torch.full((n, 3, 2), 0.5, dtype=uv_px.dtype)))
    J = chief[:, 1:, :2] - chief[:, :1, :2]
    sigma = torch.sqrt((J ** 2).sum(1) * (1.0 / 48.0 + psf_var_px2))
    return checker_dark_fraction(hit[..., 0], hit[..., 1], sigma[:, None, 0], tp.BOARD,
                                 sigma_y=sigma[:, None, 1]).mean(-1)


def _tilted_view(theta_L_deg: float = 4.65, view: int = 1):
    """A tilted lens (blur about 9 px) looking at the test board, 342 x 228."""
    w_px, h_px = EOS_6D.binned(16).size_px
    lens = Lens.from_tilt(tp.W_MM, float(optics.focal_length(tp.W_MM, 700.0)), math.radians(theta_L_deg), tp.D_MM,
                          sensor=Sensor(w_px, h_px, EOS_6D.pixel_pitch * 16))
    R, T = reproduce.target_pose(tp.BOARD, *reproduce.TARGET_VIEWS[view])
    return lens, R, T


@pytest.mark.parametrize("theta_L_deg, psf_var", [(4.65, 0.0), (-5.0, 1.44)])
def test_lens_samples_match_the_traced_rays(theta_L_deg, psf_var):
    """`dark_fraction_samples` (focus points met with the board in closed form) against the same lens samples
    traced as rays by the camera: equal to rounding, on pixels that see edges and corners."""
    lens, R, T = _tilted_view(theta_L_deg)
    cam = ThinLensCamera.from_calibration(lens, torch.as_tensor(R, dtype=torch.float64),
                                          torch.as_tensor(T, dtype=torch.float64))
    rng = np.random.default_rng(1)
    uv = torch.tensor(np.stack([rng.uniform(0, lens.sensor.width_px, 2000),
                                rng.uniform(0, lens.sensor.height_px, 2000)], -1))
    samples = hammersley_disc_samples(64)
    with torch.no_grad():
        got = dark_fraction_samples(tp.BOARD, cam, uv, samples, psf_var)
        want = _traced_dark_fraction(tp.BOARD, cam, uv, samples, psf_var)
    edges = int(((want > 0.02) & (want < 0.98)).sum())
    assert edges > 100, f"only {edges} pixels see an edge"
    assert float((got - want).abs().max()) < 1e-12, f"off by {float((got - want).abs().max()):.3g}"


def _fit_camera_of_two_views():
    """(lens, the photometric fit's float64 camera of the tilted view's first two target poses, no gradients)."""
    lens, _, _ = _tilted_view()
    poses = [reproduce.target_pose(tp.BOARD, *reproduce.TARGET_VIEWS[i]) for i in (0, 1)]
    start = {"w_mm": tp.W_MM, "U_mm": lens.U, "d_mm": tp.D_MM, "theta_F_deg": math.degrees(lens.theta_F),
             "views": [{"R": R, "T_mm": T} for R, T in poses]}
    camera = tp._camera(start, [np.zeros((lens.sensor.height_px, lens.sensor.width_px))],
                        lens.sensor.pixel_pitch).double()
    for p in camera.parameters():
        p.requires_grad_(False)
    return lens, camera


def test_lens_sample_jacobian_traces_no_rays(monkeypatch):
    """The fit's residuals and Jacobian on lens-sample pixels come from the 7 focus points a pixel: no ray is
    traced per lens sample (the old path traced 4 S rays a pixel under 11 forward-mode tangents, 99 % of the
    kernel-choice fit's time), and they match the traced rays' dark fraction."""
    lens, camera = _fit_camera_of_two_views()
    w_px, h_px = lens.sensor.width_px, lens.sensor.height_px
    rng = np.random.default_rng(2)
    uv = torch.tensor(np.stack([rng.integers(0, w_px, 400), rng.integers(0, h_px, 400)], -1), dtype=torch.float64)
    with torch.no_grad():
        traced = [_traced_dark_fraction(tp.BOARD, camera.view_camera(v), uv, hammersley_disc_samples(32), 0.25)
                  for v in range(2)]
    zeros = torch.zeros(400, dtype=torch.float64)
    data = [_View(uv, zeros, 0, zeros, torch.zeros(400, 2, dtype=torch.float64)) for _ in range(2)]
    problem = _Problem(camera, tp.BOARD, data, hammersley_disc_samples(32))

    def no_rays(*args, **kwargs):
        raise AssertionError("generate_rays called by the lens-sample path")

    monkeypatch.setattr(ThinLensCamera, "generate_rays", no_rays)
    x = {"lens": torch.zeros(4, dtype=torch.float64),
         "pose": torch.cat([camera.rvec.detach(), camera.T_scaled.detach()], 1),
         "levels": torch.tensor([[1.0, 0.0]] * 2, dtype=torch.float64), "psf": torch.tensor([0.5], dtype=torch.float64)}
    r, jac = problem.evaluate(x, True)
    assert set(jac) == set(x) and jac["pose"].shape == (800, 6) and bool(torch.isfinite(jac["psf"]).all()), \
        f"Jacobian blocks {({k: tuple(v.shape) for k, v in jac.items()})}"
    # Levels (1, 0) and no vignetting: the residual is 1 − D (observed 0).
    dark = 1.0 - torch.cat([r[:400], r[400:]])
    assert float((dark - torch.cat(traced)).abs().max()) < 1e-12, "the fit's dark fraction is the traced rays'"


@pytest.mark.parametrize("k1, centre", [(0.0, "sensor"), (-0.05, "sensor"), (-0.05, "lens_axis")])
def test_focus_geometry_of_the_fit_equals_the_cameras(k1, centre):
    """The fit's focus geometry (`_Problem._focus`: combined from three ideal points; with distortion each point's
    ideal position by Newton once and its derivative by the implicit function, in closed form about the principal
    point, by one Newton step in forward mode about the lens axis) and its chained derivatives equal the camera's
    own `focus_geometry` and forward mode at every point, with and without distortion (the sigma's
    held-intrinsics step moves k1 between calls)."""
    lens, camera = _fit_camera_of_two_views()
    w_px, h_px = lens.sensor.width_px, lens.sensor.height_px
    zeros = torch.zeros(10, dtype=torch.float64)
    problem = _Problem(camera, tp.BOARD, [_View(torch.zeros(10, 2), zeros, 0, zeros)], hammersley_disc_samples(16))
    camera.distortion_centre = centre
    with torch.no_grad():
        camera.dist_k1 += k1
    rng = np.random.default_rng(3)
    pts = torch.tensor(rng.uniform(0, w_px, (50, 7, 2)))
    from renderer.cameras import LENS_PARAMETERS
    geo = torch.cat([torch.stack([getattr(camera, n).detach() for n in LENS_PARAMETERS]),
                     camera.rvec.detach()[1], camera.T_scaled.detach()[1]])
    q, c, a, chain = problem._focus(1, geo, True)(pts)

    def direct(g):
        return problem._call(1, g, lambda cam: cam.focus_geometry(pts)[:3])

    want = direct(geo)
    dq, dc, da = torch.func.jacfwd(direct)(geo)
    scale = float(want[0].abs().max())
    assert float((q - want[0]).abs().max()) < 1e-12 * scale, \
        f"focus points off by {float((q - want[0]).abs().max()):.3g}"
    assert torch.equal(c, want[1]) and torch.equal(a, want[2]), "the lens centre and axes are the camera's"
    gq, gc, ga = torch.tensor(rng.normal(size=(50, 7, 4))), torch.tensor(rng.normal(size=(50, 3))), \
        torch.tensor(rng.normal(size=(50, 2, 3)))
    got = chain(gq, gc, ga)
    ref = torch.einsum("nsk,nskp->np", gq, dq) + gc @ dc + torch.einsum("nij,ijp->np", ga, da)
    assert float((got - ref).abs().max()) < 1e-10 * float(ref.abs().max()), \
        f"chained derivatives off by {float((got - ref).abs().max()):.3g} of {float(ref.abs().max()):.3g}"
    if k1:
        assert float((problem._focus(1, geo, False)(pts)[0] - direct(geo)[0]).abs().max()) < 1e-12 * scale, \
            "without derivatives, the same focus points"


@pytest.mark.parametrize("centre", ["sensor", "lens_axis"])
def test_undistorted_pixels_by_one_newton_step_have_the_newton_derivatives(centre):
    """`Camera.undistort_pixels_from` (one Newton step from the root) gives `undistort_pixels`'s values to rounding
    and its forward-mode derivatives by the lens and pose; `undistort_pixels_jacobian` (about the principal point,
    by the focal lengths and principal point, chained here) gives the same derivatives in closed form, and is
    refused for a distortion about the lens axis. Pixels whose inverse does not exist stay put, without
    derivatives."""
    lens, camera = _fit_camera_of_two_views()
    w_px, h_px = lens.sensor.width_px, lens.sensor.height_px
    camera.distortion_centre = centre
    with torch.no_grad():
        camera.dist_k1 += -0.3   # strong barrel: the outer pixels have no inverse
    problem = _Problem(camera, tp.BOARD, [], hammersley_disc_samples(4))
    from renderer.cameras import LENS_PARAMETERS
    geo = torch.cat([torch.stack([getattr(camera, n).detach() for n in LENS_PARAMETERS]),
                     camera.rvec.detach()[1], camera.T_scaled.detach()[1]])
    rng = np.random.default_rng(5)
    pts = torch.tensor(np.concatenate([rng.uniform(0, w_px, (40, 2)), [[-4 * w_px, -4 * h_px]]]))

    def newton(g):
        return problem._call(1, g, lambda cam: cam.undistort_pixels(pts)[0])

    with torch.no_grad():
        ideal, valid = problem._call(1, geo, lambda cam: cam.undistort_pixels(pts))
    assert bool(valid[:-1].all()) and not bool(valid[-1]), f"valid {valid.tolist()}"

    def step(g):
        return problem._call(1, g, lambda cam: cam.undistort_pixels_from(pts, ideal, valid))

    want, got = torch.func.jacfwd(newton)(geo), torch.func.jacfwd(step)(geo)
    assert float((step(geo) - ideal).abs().max()) < 1e-9, "one step from the root stays at the root"
    assert float((got - want).abs().max()) < 1e-9 * float(want.abs().max()), \
        f"one step's derivatives off by {float((got - want).abs().max()):.3g} of {float(want.abs().max()):.3g}"
    assert float(want[:, 0].abs().max()) > 1e-3 and not bool(got[-1].any()), \
        "w moves the ideal points; not the lost one"
    if centre == "lens_axis":
        with pytest.raises(ValueError, match="lens axis"):
            problem._call(1, geo, lambda cam: cam.undistort_pixels_jacobian(pts, ideal, valid))
        return

    def intrinsics(g):
        return problem._call(1, g, lambda cam: torch.stack([torch.as_tensor(t).to(g) for t in
                                                            (*cam.focal_px, *cam.screen.center_px)]))

    closed = problem._call(1, geo, lambda cam: cam.undistort_pixels_jacobian(pts, ideal, valid)) @ \
        torch.func.jacrev(intrinsics)(geo)
    assert float((closed - want).abs().max()) < 1e-9 * float(want.abs().max()), \
        f"closed-form derivatives off by {float((closed - want).abs().max()):.3g} of {float(want.abs().max()):.3g}"


def test_closed_form_reverse_pass_holds_only_the_lines_that_cut():
    """The closed form keeps for its reverse pass only what the lines that cut a disc need (`aperture._CutLines`):
    on 20,000 sub-points (28 % of them cut by an x edge) the tensors saved for the gradient hold fewer than 100
    numbers a point (measured 56; the dense form of 8c1f30a saved 399 a point, 30-odd tensors over all 12 lines),
    and the gradient equals the dense form's to rounding."""
    from tiltfit.photometric import aperture
    from tiltfit.photometric.render import sub_points

    lens, R, T = _tilted_view()
    cam = ThinLensCamera.from_calibration(lens, torch.as_tensor(R, dtype=torch.float64),
                                          torch.as_tensor(T, dtype=torch.float64))
    rng = np.random.default_rng(4)
    uv = torch.tensor(np.stack([rng.uniform(60, 280, 1250), rng.uniform(40, 190, 1250)], -1))
    with torch.no_grad():
        q, c, a, _ = cam.focus_geometry(sub_points(uv, 4))
    qq = q.clone().requires_grad_()
    saved = []

    def pack(t):
        saved.append(t.numel())
        return t

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        dark = aperture.checker_dark_fraction_disc(qq, c, a, tp.BOARD, near=7)
    cut = int(((aperture._edge_lines(q, c, a, torch.tensor(tp.BOARD.x_edges, dtype=torch.float64), 0)[2].abs() < 1)
               .sum()))
    assert 0.2 * q.shape[0] * q.shape[1] < cut, f"only {cut} lines cut the discs of {q.shape[0] * q.shape[1]} points"
    assert sum(saved) < 100 * q.shape[0] * q.shape[1], f"{sum(saved)} numbers saved for {q.numel() // 4} points"
    grad = torch.autograd.grad(dark.sum(), qq)[0]
    # The dense form: every line's segment with its gradient (as `disc_halfplane_fraction` and the pairs by
    # `disc_wedge_fraction`, summed as the module docstring writes D).
    qd = q.clone().requires_grad_()
    xe, ye = (torch.tensor(e, dtype=torch.float64) for e in (tp.BOARD.x_edges, tp.BOARD.y_edges))
    nx, ny, hx = aperture._edge_lines(qd, c, a, xe, 0)
    mx, my, hy = aperture._edge_lines(qd, c, a, ye, 1)
    Fx, Fy = aperture.disc_halfplane_fraction(hx), aperture.disc_halfplane_fraction(hy)
    kix, kbx = aperture._checker_coefficients(len(xe) - 1, torch.float64, None)
    kiy, kby = aperture._checker_coefficients(len(ye) - 1, torch.float64, None)
    W = aperture.disc_wedge_fraction(nx[..., :, None], ny[..., :, None], hx[..., :, None], mx[..., None, :],
                                     my[..., None, :], hy[..., None, :])
    both = (hx.abs() < 1)[..., :, None] & (hy.abs() < 1)[..., None, :]
    E = torch.where(both, W, Fx[..., :, None] * Fy[..., None, :])

    def expect(cx, cy):
        return torch.einsum("...ij,i,j->...", E, cx, cy)

    parity = 1.0 if (tp.BOARD.dark_cell[0] + tp.BOARD.dark_cell[1]) % 2 == 0 else -1.0
    dense = 0.5 * (expect(kix, kiy) + parity * expect(kbx, kby))
    assert float((dense.detach() - dark.detach()).abs().max()) < 1e-12, "the dense form's dark fraction"
    want = torch.autograd.grad(dense.sum(), qd)[0]
    assert float((grad - want).abs().max()) <= 1e-9 * float(want.abs().max()), \
        f"gradient off by {float((grad - want).abs().max()):.3g} of {float(want.abs().max()):.3g}"
