"""The aperture in closed form: disc areas cut by lines, the thin lens's focus points, and the target renderer
that integrates the checker over the disc exactly (`tiltfit.photometric.aperture`, `render_target_disc`)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import renderer
from renderer.cameras import EOS_6D, Lens
from renderer.cameras import ThinLensCamera
from tiltfit.experiments import reproduce
from tiltfit.photometric.aperture import checker_dark_fraction_disc, disc_halfplane_fraction, disc_wedge_fraction, lines_cut
from tiltfit.photometric import render_target_disc
from tiltfit.photometric.render import on_board, pixel_blur_px
from tiltfit.target.layout import Target

BOARD = Target(tuple(50.0 * i for i in range(7)), tuple(50.0 * j for j in range(5)), (0, 0), 25.0)
f64 = dict(dtype=torch.float64)


def _unit(angle):
    a = torch.as_tensor(angle, **f64)
    return torch.cos(a), torch.sin(a)


# ------------------------------------------------------------------------------------------ disc areas

def test_halfplane_fraction_is_the_circular_segment():
    h = torch.linspace(-1.5, 1.5, 61, **f64)
    F = disc_halfplane_fraction(h)
    assert float(disc_halfplane_fraction(torch.tensor(0.0, **f64))) == pytest.approx(0.5, abs=1e-15)
    assert torch.allclose(F + disc_halfplane_fraction(-h), torch.ones_like(h), atol=1e-14), "F(h) + F(−h) = 1"
    assert bool((F[h >= 1] == 1).all() and (F[h <= -1] == 0).all()), "lines outside the disc"
    # Its slope is the chord length over the disc's area: dF/dh = 2 √(1 − h²) / π.
    hs = torch.tensor([-0.9, -0.3, 0.2, 0.7], **f64, requires_grad=True)
    (g,) = torch.autograd.grad(disc_halfplane_fraction(hs).sum(), hs)
    want = 2 * torch.sqrt(1 - hs.detach() ** 2) / math.pi
    assert torch.allclose(g, want, rtol=1e-12), f"dF/dh {g} vs {want}"


def test_wedge_through_the_centre_is_its_angle():
    for phi in (0.3, 1.0, math.pi / 2, 2.5):
        # Lines through the centre whose positive sides meet in a wedge of angle φ.
        n1 = _unit(math.pi / 2)                 # y > 0
        n2 = _unit(phi - math.pi / 2)           # the side of the ray at angle φ towards angle 0
        got = float(disc_wedge_fraction(*n1, torch.tensor(0.0, **f64), *n2, torch.tensor(0.0, **f64)))
        assert got == pytest.approx(phi / (2 * math.pi), abs=1e-12), f"wedge of {phi} rad: {got}"


def test_wedge_adds_up_to_the_halfplane():
    rng = np.random.default_rng(3)
    for _ in range(40):
        a1, a2 = rng.uniform(0, 2 * math.pi, 2)
        h1, h2 = (torch.tensor(x, **f64) for x in rng.uniform(-0.95, 0.95, 2))
        n1, n2 = _unit(a1), _unit(a2)
        both = disc_wedge_fraction(*n1, h1, *n2, h2)
        other = disc_wedge_fraction(*n1, h1, -n2[0], -n2[1], -h2)
        assert float(both + other) == pytest.approx(float(disc_halfplane_fraction(h1)), abs=1e-12), \
            f"wedges on both sides of line 2 sum to line 1's segment (angles {a1:.3f}, {a2:.3f})"
        assert 0 <= float(both) <= min(float(disc_halfplane_fraction(h1)), float(disc_halfplane_fraction(h2))) + 1e-12


def test_wedge_of_nearly_parallel_lines_against_monte_carlo():
    gen = torch.Generator().manual_seed(2)
    pts = torch.rand(300_000, 2, generator=gen, **f64) * 2 - 1
    pts = pts[(pts ** 2).sum(1) < 1]
    for a1, a2, h1, h2 in ((0.7, 0.7 + 1e-5, 0.3, -0.2), (0.7, 0.7 + math.pi + 1e-6, 0.3, 0.2),
                           (0.7, 0.7, 0.3, -0.2), (1.0, 1.0 + 1e-3, -0.1, 0.05)):
        n1, n2 = _unit(a1), _unit(a2)
        got = float(disc_wedge_fraction(*n1, torch.tensor(h1, **f64), *n2, torch.tensor(h2, **f64)))
        inside = ((pts[:, 0] * n1[0] + pts[:, 1] * n1[1] + h1 > 0) & (pts[:, 0] * n2[0] + pts[:, 1] * n2[1] + h2 > 0))
        mc = float(inside.double().mean())
        sd = math.sqrt(max(mc * (1 - mc), 1e-4) / pts.shape[0])
        assert abs(got - mc) < 4 * sd + 1e-6, f"angles {a1}, {a2}: wedge {got:.5f} vs Monte Carlo {mc:.5f}"


def test_wedge_gradient_where_the_lines_cross_at_the_centre():
    h = torch.zeros(2, **f64)
    n1, n2 = _unit(0.3), _unit(1.7)
    f = lambda hh: disc_wedge_fraction(*n1, hh[0], *n2, hh[1])  # noqa: E731
    g = torch.func.jacfwd(f)(h)
    eps = 1e-6
    fd = torch.stack([(f(h + eps * e) - f(h - eps * e)) / (2 * eps) for e in torch.eye(2, **f64)])
    assert torch.isfinite(g).all() and torch.allclose(g, fd, atol=1e-6), f"gradient {g} vs differences {fd}"


def test_wedge_against_monte_carlo():
    gen = torch.Generator().manual_seed(1)
    pts = torch.rand(300_000, 2, generator=gen, **f64) * 2 - 1
    pts = pts[(pts ** 2).sum(1) < 1]
    for a1, h1, a2, h2 in ((0.4, 0.3, 2.0, -0.5), (1.1, -0.7, 1.5, 0.6), (3.0, 0.9, 4.5, 0.2)):
        n1, n2 = _unit(a1), _unit(a2)
        got = float(disc_wedge_fraction(*n1, torch.tensor(h1, **f64), *n2, torch.tensor(h2, **f64)))
        inside = ((pts[:, 0] * n1[0] + pts[:, 1] * n1[1] + h1 > 0) & (pts[:, 0] * n2[0] + pts[:, 1] * n2[1] + h2 > 0))
        mc = float(inside.double().mean())
        sd = math.sqrt(mc * (1 - mc) / pts.shape[0])
        assert abs(got - mc) < 4 * sd + 1e-6, f"wedge {got:.5f} vs Monte Carlo {mc:.5f} ± {sd:.5f}"


# ------------------------------------------------------------------------------------------ the thin lens

def _camera(theta_F_deg=40.0, U=700.0, d=30.0, downscale=16):
    R, T = reproduce.target_pose(BOARD, 30.0, 5.0, 600.0)
    lens = Lens(55.0, U, d, math.radians(theta_F_deg), EOS_6D.binned(downscale))
    cam = ThinLensCamera.from_calibration(lens, torch.tensor(R, **f64), torch.tensor(T, **f64))
    return cam, (*lens.sensor.size_px, lens.sensor.pixel_pitch, R, T)


@pytest.mark.parametrize("theta_F_deg", [40.0, 0.0, -80.0])
def test_every_ray_of_a_pixel_passes_through_its_focus_point(theta_F_deg):
    """At θF = −80° the plane of focus crosses the lens plane inside the field: some pixels focus behind the
    lens (s < 0), and their rays still share one point, the virtual focus."""
    cam, (w_px, h_px, *_) = _camera(theta_F_deg)
    uv = torch.tensor([[3.0, 4.0], [w_px / 2, h_px / 2], [w_px - 2.0, h_px - 5.0], [10.0, h_px - 1.0]], **f64)
    lens = torch.rand(uv.shape[0], 16, 2, generator=torch.Generator().manual_seed(0), **f64)
    rays = cam.generate_rays(uv[:, None, :].expand(-1, 16, 2), lens)
    q_h, centre, axes, valid = cam.focus_geometry(uv)
    q = q_h[:, :3] / q_h[:, 3:]
    # Distance of q from each ray's line, relative to q's distance from the ray's origin.
    rel = q[:, None, :] - rays.origin
    off = torch.linalg.cross(rel, rays.direction, dim=-1).norm(dim=-1) / rel.norm(dim=-1)
    assert float(off.max()) < 1e-9, f"rays miss their focus point by {float(off.max()):.2e} (relative)"
    # The rays leave the disc centre + a·axes[0] + b·axes[1], a² + b² ≤ 1, of radius d/2.
    ab = torch.linalg.lstsq(axes.T, (rays.origin - centre).reshape(-1, 3).T).solution.T
    assert torch.allclose(axes.T @ ab.T, (rays.origin - centre).reshape(-1, 3).T, atol=1e-9), "origins on the disc plane"
    assert float((ab ** 2).sum(-1).max()) <= 1 + 1e-9, "origins inside the disc"
    assert torch.allclose(axes.norm(dim=-1), torch.full((2,), 15.0, **f64)) and abs(float(axes[0] @ axes[1])) < 1e-9
    if theta_F_deg == -80.0:
        assert bool((q_h[:, 3] < 0).any()) and bool((q_h[:, 3] > 0).any()), "focus on both sides of the lens"
    assert bool(valid.all())


@pytest.mark.parametrize("theta_F_deg, U, d, dark", [(40.0, 700.0, 30.0, (0, 0)), (-30.0, 900.0, 40.0, (1, 0)),
                                                     (0.0, 1e5, 20.0, (0, 0))])
def test_closed_form_equals_the_mean_over_traced_lens_samples(theta_F_deg, U, d, dark):
    """One sensor point: the closed form against 60 000 random lens samples traced by the camera and looked up
    on the hard-edged checker (a different integrator), within 4 Monte Carlo σ."""
    cam, (w_px, h_px, *_) = _camera(theta_F_deg, U, d)
    # Points along a line across the board's middle; the test takes those in blurred edges and corners.
    line = torch.stack([torch.linspace(0.3 * w_px, 0.7 * w_px, 400, **f64),
                        torch.linspace(0.35 * h_px, 0.6 * h_px, 400, **f64)], -1)
    board = Target(BOARD.x_edges, BOARD.y_edges, dark, 25.0)
    q_h, centre, axes, _ = cam.focus_geometry(line)
    darkness = checker_dark_fraction_disc(q_h, centre, axes, board, near=7)
    blurred = torch.nonzero((darkness > 0.03) & (darkness < 0.97)).squeeze(1)
    assert blurred.numel() >= 20, f"only {blurred.numel()} of 400 points see a blurred edge"
    pick = blurred[torch.linspace(0, blurred.numel() - 1, 8).round().long()]
    uv, got = line[pick], darkness[pick]
    n = 60_000
    lens = torch.rand(n, 2, generator=torch.Generator().manual_seed(5), **f64)
    xe, ye = np.asarray(BOARD.x_edges), np.asarray(BOARD.y_edges)
    for k in range(uv.shape[0]):
        rays = cam.generate_rays(uv[k].expand(n, 2), lens)
        t = -rays.origin[:, 2] / rays.direction[:, 2]
        X, Y = (rays.origin + t[:, None] * rays.direction)[:, :2].T.numpy()
        col, row = np.searchsorted(xe, X) - 1, np.searchsorted(ye, Y) - 1
        on = (col >= 0) & (col < len(xe) - 1) & (row >= 0) & (row < len(ye) - 1)
        hit_dark = on & ((col + row) % 2 == (dark[0] + dark[1]) % 2)
        mc, sd = hit_dark.mean(), math.sqrt(max(hit_dark.mean() * (1 - hit_dark.mean()), 1e-4) / n)
        assert abs(float(got[k]) - mc) < 4 * sd, f"point {k}: closed form {float(got[k]):.4f} vs samples {mc:.4f} ± {sd:.4f}"


def test_render_target_disc_gradcheck():
    sensor = EOS_6D.binned(16)
    R, T = reproduce.target_pose(BOARD, 30.0, 5.0, 600.0)
    import cv2

    rvec = torch.tensor(cv2.Rodrigues(R)[0].reshape(3), **f64, requires_grad=True)
    T_mm = torch.tensor(T, **f64, requires_grad=True)
    g = dict(w=55.0, inv_U=1.4, d=30.0, theta_F=math.radians(40), white=0.8, black=0.06, vig=0.05)
    scalars = [torch.tensor(v, **f64, requires_grad=True) for v in g.values()]
    uv = torch.tensor([[171.0, 114.0], [150.3, 100.7], [190.2, 130.1], [130.0, 120.0], [205.5, 95.5]], **f64)

    def model(w, inv_U, d, theta_F, white, black, vig, rvec, T_mm):
        cam = ThinLensCamera.from_calibration(Lens(w, 1000.0 / inv_U, d, theta_F, sensor),
                                              renderer.axis_angle_to_matrix(rvec), T_mm)
        return render_target_disc(BOARD, cam, uv, 2, white, black, vig, subpixels=2)

    inputs = (*scalars, rvec, T_mm)
    value = model(*inputs)
    assert float(value.detach().min()) < 0.7 and float(value.detach().max()) > 0.1, "pixels see edges"
    assert torch.autograd.gradcheck(model, inputs, eps=1e-6, atol=1e-7, rtol=1e-4), "closed-form gradients"


def test_lines_cut_counts_the_edges_a_disc_spans():
    cam, (w_px, h_px, *_) = _camera(0.0, 3000.0, 30.0)   # focused far behind the board
    uv = torch.tensor([[w_px / 2, h_px / 2]], **f64)
    q_h, centre, axes, _ = cam.focus_geometry(uv)
    one = lines_cut(q_h, centre, axes, BOARD)
    # The same camera with a 6x wider aperture spans more edges; near = that count is exact, fewer is not.
    wide, _ = _camera(0.0, 3000.0, 180.0)
    qw, cw, aw, _ = wide.focus_geometry(uv)
    many = lines_cut(qw, cw, aw, BOARD)
    assert one <= 1 < many, f"edges cut: {one} at d = 30 mm, {many} at 180 mm"
    exact = checker_dark_fraction_disc(qw, cw, aw, BOARD, near=7)
    assert float(checker_dark_fraction_disc(qw, cw, aw, BOARD, near=many)) == pytest.approx(float(exact), abs=1e-12)
    assert abs(float(checker_dark_fraction_disc(qw, cw, aw, BOARD, near=1)) - float(exact)) > 1e-3, \
        "one line per family cannot be exact where the disc spans several"


def test_pixel_blur_is_the_blur_disc_of_paper_4():
    """`pixel_blur_px` against paper (4), w d |1/z_f − 1/z| / p, with z the depth of
    the board point the chief ray meets and z_f the depth where it meets the plane of focus z = U + y tan θF
    (camera frame; the paper takes y at the board point instead, a few percent off here)."""
    theta_F, U, d, w = math.radians(40.0), 700.0, 30.0, 55.0
    cam, (w_px, h_px, pitch, R, T) = _camera(40.0, U, d)
    uv = torch.tensor([[w_px * 0.3, h_px * 0.4], [w_px / 2, h_px / 2], [w_px * 0.7, h_px * 0.6]], **f64)
    got = pixel_blur_px(cam, uv)
    p = on_board(cam.generate_rays(uv)) @ torch.tensor(R, **f64).T + torch.tensor(T, **f64)
    slope = p[:, 1] / p[:, 2]                              # chief ray: y = slope · z
    z_f = U / (1 - slope * math.tan(theta_F))
    want = w * d * (1 / z_f - 1 / p[:, 2]).abs() / pitch
    assert torch.allclose(got, want, rtol=1e-9), f"blur {got.tolist()} vs paper (4) {want.tolist()}"
    assert float(want.max()) > 2.0, "the points are out of focus"
