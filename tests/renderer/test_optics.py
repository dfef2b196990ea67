"""renderer.cameras.optics: exact Scheimpflug/hinge relations, the paper's approximations, closed-form blur."""
import math

import pytest
import torch

from renderer.cameras import optics

DEG = math.pi / 180
# The paper's stage-1 estimate (NOTES.md §2): w, U in mm.
W_PAPER, U_PAPER = 55.39, 618.4


def _lens_conjugate(p, f, theta_L):
    """Conjugate of point p (..., 3) through a thin lens of focal length f at the origin, normal (0, −sin, cos).

    Independent of renderer.cameras.optics: 1/s_o + 1/s_i = 1/f with distances along the lens normal, the conjugate
    on the line p–O on the other side (works both ways: scene -> sensor side and sensor -> scene side).
    """
    n = torch.tensor([0.0, -math.sin(theta_L), math.cos(theta_L)], dtype=p.dtype)
    s_o = (p @ n).abs()
    s_i = f * s_o / (s_o - f)
    return -p * (s_i / s_o)[..., None]


def _aperture_projection(p, w, U, d, theta_F, n=4096):
    """Boundary of the blur spot by brute force: aperture circle projected from p's conjugate onto the sensor,
    returned in upright image-plane coordinates (n, 2)."""
    theta_L = float(optics.theta_L_from_theta_F(theta_F, w, U))
    f = float(optics.focal_length(w, U, theta_L))
    p_img = _lens_conjugate(p, f, theta_L)
    phi = torch.linspace(0, 2 * math.pi, n, dtype=p.dtype)
    r = d / 2
    s = torch.stack([r * phi.cos(), r * phi.sin() * math.cos(theta_L), r * phi.sin() * math.sin(theta_L)], -1)
    lam = (-w - p_img[2]) / (s[:, 2] - p_img[2])
    on_sensor = p_img + lam[:, None] * (s - p_img)
    return -on_sensor[:, :2]


# --- Scheimpflug, hinge rule and the paper's (1) ---------------------------------------------------------

def test_notes_numbers():
    f = optics.focal_length(W_PAPER, U_PAPER)
    assert abs(1 / f - (1 / W_PAPER + 1 / U_PAPER)) < 1e-15, "untilted focal length must obey 1/f = 1/w + 1/U"
    U_tilted = optics.focus_distance_tilted(W_PAPER, f, 5 * DEG)
    assert abs(float(U_tilted) - 648.4) < 0.05, f"hinge rule: U should move 618.4 -> 648.4 mm, got {float(U_tilted)}"
    theta_F = optics.theta_F_from_theta_L(5 * DEG, W_PAPER, U_tilted)
    assert abs(float(theta_F) / DEG - 48.03) < 0.005, f"exact theta_F should be 48.03 deg, got {float(theta_F) / DEG}"
    theta_F_f = optics.theta_F_from_theta_L_f(5 * DEG, W_PAPER, f)
    assert abs(float(theta_F_f - theta_F)) < 1e-12, "theta_F from (w, f) must equal theta_F from (w, U(f))"
    back = optics.theta_L_paper(theta_F, f, U_tilted)
    assert abs(float(back) / DEG - 4.62) < 0.005, f"paper's (1) should map 48.03 deg to 4.62 deg: {float(back) / DEG}"
    assert abs(float(optics.theta_L_from_theta_F(theta_F, W_PAPER, U_tilted)) - 5 * DEG) < 1e-14, "exact inverse"
    assert abs(float(optics.theta_L_from_theta_F_f(theta_F, W_PAPER, f)) - 5 * DEG) < 1e-14, "exact inverse (f)"


def test_round_trips_random():
    g = torch.Generator().manual_seed(1)
    w = 20 + 80 * torch.rand(200, generator=g, dtype=torch.float64)
    U = w * (1.5 + 50 * torch.rand(200, generator=g, dtype=torch.float64))
    theta_L = (torch.rand(200, generator=g, dtype=torch.float64) - 0.5) * 40 * DEG
    theta_F = optics.theta_F_from_theta_L(theta_L, w, U)
    assert torch.allclose(optics.theta_L_from_theta_F(theta_F, w, U), theta_L, atol=1e-13, rtol=0), "θL -> θF -> θL"
    f = optics.focal_length(w, U, theta_L)
    assert torch.allclose(optics.focus_distance_tilted(w, f, theta_L), U, rtol=1e-12), "f <-> U (hinge rule)"
    assert torch.allclose(optics.theta_F_from_theta_L_f(theta_L, w, f), theta_F, atol=1e-12, rtol=0), "θF via f"
    assert torch.allclose(optics.theta_L_from_theta_F_f(theta_F, w, f), theta_L, atol=1e-12, rtol=0), "θL via f"
    assert bool((torch.sign(theta_F) == torch.sign(theta_L)).all()), "θL has the sign of θF"


@pytest.mark.parametrize("theta_L_deg", [-12.0, -5.0, 3.0, 5.0, 20.0])
def test_plane_of_focus_contains_scheimpflug_and_hinge_lines(theta_L_deg):
    w, f = 55.39, 50.0
    theta_L = theta_L_deg * DEG
    U = optics.focus_distance_tilted(w, f, theta_L)
    theta_F = optics.theta_F_from_theta_L(theta_L, w, U)
    y_s = optics.scheimpflug_line_y(w, theta_L)
    assert abs(float(y_s * math.tan(theta_L)) + w) < 1e-9, "Scheimpflug line must lie in the lens plane"
    assert abs(float(optics.focus_depth(y_s, U, theta_F)) + w) < 1e-9, "plane of focus contains the Scheimpflug line"
    y_h = optics.hinge_line_y(f, theta_L)
    assert abs(float(optics.focus_depth(y_h, U, theta_F))) < 1e-9, "plane of focus must contain the hinge line (z = 0)"
    lens_normal = torch.tensor([0.0, -math.sin(theta_L), math.cos(theta_L)], dtype=torch.float64)
    hinge = torch.tensor([0.0, float(y_h), 0.0], dtype=torch.float64)
    assert abs(float(hinge @ lens_normal) - f) < 1e-9, "hinge line must lie in the front focal plane"


def test_plane_of_focus_is_conjugate_of_sensor():
    """Physics check independent of the Scheimpflug formula: thin-lens images of sensor points."""
    w, f, theta_L = 55.39, 50.836, 5 * DEG
    U = optics.focus_distance_tilted(w, f, theta_L)
    theta_F = optics.theta_F_from_theta_L(theta_L, w, U)
    g = torch.Generator().manual_seed(2)
    sensor = torch.cat([(torch.rand(50, 2, generator=g, dtype=torch.float64) - 0.5) * 30,
                        torch.full((50, 1), -w, dtype=torch.float64)], -1)
    obj = _lens_conjugate(sensor, f, theta_L)
    residual = obj[:, 2] - optics.focus_depth(obj[:, 1], U, theta_F)
    assert float(residual.abs().max()) < 1e-8, f"sensor conjugates must lie on Π_F: {residual.abs().max()}"


def test_paper_eq1_is_biased_but_exact_for_f_equal_w():
    theta_F, U, w = 30 * DEG, 600.0, 55.0
    assert abs(float(optics.theta_L_paper(theta_F, w, U) - optics.theta_L_from_theta_F(theta_F, w, U))) < 1e-15, \
        "eq. (1) with w in place of f is the exact relation"
    f = float(optics.focal_length(w, U))
    assert float(optics.theta_L_paper(theta_F, f, U)) < float(optics.theta_L_from_theta_F(theta_F, w, U)), \
        "with f < w eq. (1) underestimates θL"


# --- Blur --------------------------------------------------------------------------------------------------

def test_blur_untilted_all_forms_agree_with_eq2():
    w, U, d = 50.0, 1000.0, 20.0
    p = torch.tensor([[0.0, 0.0, 500.0], [30.0, -80.0, 700.0], [-40.0, 60.0, 2500.0], [5.0, 5.0, 1000.0]],
                     dtype=torch.float64)
    b2 = w * d * (1 / U - 1 / p[:, 2]).abs()
    for name, b in [("paper", optics.blur_diameter_paper(p[:, 1], p[:, 2], w, U, d)),
                    ("first_order", optics.blur_diameter_first_order(p, w, U, d)),
                    ("exact", optics.blur_diameter_exact(p, w, U, d)),
                    ("width x", optics.blur_width(p, w, U, d, 0.0, torch.tensor([1.0, 0.0]))),
                    ("width y", optics.blur_width(p, w, U, d, 0.0, torch.tensor([0.0, 1.0])))]:
        assert torch.allclose(b, b2, rtol=1e-12, atol=1e-14), f"{name} must equal eq. (2) for θF = 0: {b} vs {b2}"
    center, _ = optics.blur_ellipse(p, w, U, d)
    assert torch.allclose(center, w * p[:, :2] / p[:, 2:], atol=1e-12), "untilted spots centre on the pinhole image"


@pytest.mark.parametrize("theta_F_deg", [30.0, -40.0, 60.0])
def test_blur_ellipse_matches_brute_force_projection(theta_F_deg):
    w, U, d = 50.0, 1000.0, 20.0
    theta_F = theta_F_deg * DEG
    for p in ([0.0, 100.0, 600.0], [50.0, -150.0, 1500.0], [-80.0, 200.0, 3000.0]):
        p = torch.tensor(p, dtype=torch.float64)
        boundary = _aperture_projection(p, w, U, d, theta_F)
        center, shape = optics.blur_ellipse(p, w, U, d, theta_F)
        e = boundary - center
        level = (e @ torch.linalg.inv(shape) * e).sum(-1)
        assert float((level - 1).abs().max()) < 1e-9, f"spot boundary must be the ellipse, p={p.tolist()}"
        for n in ([1.0, 0.0], [0.0, 1.0], [0.6, 0.8]):
            n = torch.tensor(n, dtype=torch.float64)
            extent = float((boundary @ n).max() - (boundary @ n).min())
            width = float(optics.blur_width(p, w, U, d, theta_F, n))
            assert abs(width / extent - 1) < 1e-6, f"width along {n.tolist()}: {width} vs brute force {extent}"
        area = math.pi * math.sqrt(float(torch.linalg.det(shape)))
        dia = float(optics.blur_diameter_exact(p, w, U, d, theta_F))
        assert abs(math.pi * dia**2 / 4 / area - 1) < 1e-12, "equivalent-area diameter"


def test_first_order_and_paper_forms_tilted():
    w, U, theta_F = 50.0, 1000.0, 45 * DEG
    p = torch.tensor([[0.0, 150.0, 900.0], [20.0, -200.0, 1400.0], [0.0, 300.0, 2500.0]], dtype=torch.float64)
    exact_x = optics.blur_width(p, w, U, 1e-4, theta_F, torch.tensor([1.0, 0.0]))
    first = optics.blur_diameter_first_order(p, w, U, 1e-4, theta_F)
    assert torch.allclose(exact_x, first, rtol=1e-6), "first-order form is the exact x-width as d -> 0"
    theta_L = optics.theta_L_from_theta_F(theta_F, w, U)
    exact_y = optics.blur_width(p, w, U, 1e-4, theta_F, torch.tensor([0.0, 1.0]))
    fore = torch.cos(theta_L) - p[:, 1] / p[:, 2] * torch.sin(theta_L)
    assert torch.allclose(exact_y, first * fore, rtol=1e-6), "y-width = first-order × aperture foreshortening"
    paper = optics.blur_diameter_paper(p[:, 1], p[:, 2], w, U, 1e-4, theta_F)
    ratio = first / paper
    expected = optics.focus_depth(p[:, 1], U, theta_F) / U
    assert torch.allclose(ratio, expected, rtol=1e-12), "paper's (4) differs by the factor (U + y tan θF) / U"


def test_blur_vanishes_on_plane_of_focus_and_is_finite_without_focus():
    w, U, d, theta_F = 50.0, 1000.0, 20.0, 50 * DEG
    y = torch.tensor([-300.0, 0.0, 250.0], dtype=torch.float64)
    p = torch.stack([torch.zeros(3, dtype=torch.float64), y, optics.focus_depth(y, U, theta_F)], -1)
    assert float(optics.blur_diameter_exact(p, w, U, d, theta_F).max()) < 1e-9, "points on Π_F are sharp"
    # Points on a chief ray that never meets Π_F in front of the lens (y/z > 1/tan θF): finite blur that
    # never reaches 0; it falls towards w d |1/z_f| (1/z_f < 0) as the point recedes.
    z = torch.tensor([1000.0, 2000.0, 4000.0, 1e7], dtype=torch.float64)
    p = torch.stack([torch.zeros(4, dtype=torch.float64), 1.2 * z / math.tan(theta_F), z], -1)
    for b in (optics.blur_diameter_first_order(p, w, U, d, theta_F), optics.blur_diameter_exact(p, w, U, d, theta_F)):
        inv_z_f = (1 - 1.2) / U
        assert bool(torch.isfinite(b).all()) and bool((b.diff() < 0).all()), f"finite, decreasing with depth: {b}"
        assert float(b.min()) > 0.9 * w * d * abs(inv_z_f), f"never sharp: {b} vs limit {w * d * abs(inv_z_f)}"


def test_dtype_device_and_broadcast():
    p = torch.rand(4, 1, 3, dtype=torch.float32) * 100 + torch.tensor([0.0, 0.0, 500.0])
    theta_F = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float32)
    c, A = optics.blur_ellipse(p, 50.0, 1000.0, 20.0, theta_F)
    assert c.shape == (4, 3, 2) and A.shape == (4, 3, 2, 2), f"batch broadcast: {c.shape}, {A.shape}"
    assert c.dtype == torch.float32 and A.dtype == torch.float32, "dtype follows the inputs"
    assert optics.theta_F_from_theta_L(0.1, 50, 1000).dtype == torch.float64, "numbers give float64"
    assert optics.blur_diameter_exact(p, 50.0, 1000.0, 20.0, theta_F).shape == (4, 3)


def test_gradcheck():
    def t(*v):
        return torch.tensor(v, dtype=torch.float64, requires_grad=True)

    w, U, f, d = t(55.0), t(620.0), t(50.0), t(18.0)
    theta = t(0.05, -0.1)
    p = torch.tensor([[10.0, 120.0, 500.0], [-30.0, -90.0, 1500.0]], dtype=torch.float64, requires_grad=True)
    checks = {
        "theta_F_from_theta_L": (optics.theta_F_from_theta_L, (theta, w, U)),
        "theta_L_from_theta_F": (optics.theta_L_from_theta_F, (theta, w, U)),
        "theta_F_from_theta_L_f": (optics.theta_F_from_theta_L_f, (theta, w, f)),
        "theta_L_from_theta_F_f": (optics.theta_L_from_theta_F_f, (theta, w, f)),
        "focus_distance_tilted": (optics.focus_distance_tilted, (w, f, theta)),
        "focal_length": (optics.focal_length, (w, U, theta)),
        "theta_L_paper": (optics.theta_L_paper, (theta, f, U)),
        "scheimpflug_line_y": (optics.scheimpflug_line_y, (w, theta)),
        "hinge_line_y": (optics.hinge_line_y, (f, theta)),
        "focus_depth": (optics.focus_depth, (p[:, 1], U, theta)),
        "blur_diameter_paper": (optics.blur_diameter_paper, (p[:, 1], p[:, 2], w, U, d, theta)),
        "blur_diameter_first_order": (optics.blur_diameter_first_order, (p, w, U, d, theta)),
        "blur_ellipse": (optics.blur_ellipse, (p, w, U, d, theta)),
        "blur_width": (lambda *a: optics.blur_width(*a, torch.tensor([0.6, 0.8], dtype=torch.float64)),
                       (p, w, U, d, theta)),
        "blur_diameter_exact": (optics.blur_diameter_exact, (p, w, U, d, theta)),
    }
    for name, (fn, args) in checks.items():
        assert torch.autograd.gradcheck(fn, args), f"gradcheck failed for {name}"


def test_gradients_finite_in_focus():
    """Fits see points on the plane of focus: gradients there must be finite (no 0 · inf)."""
    U = torch.tensor(1000.0, dtype=torch.float64, requires_grad=True)
    theta_F = torch.tensor(0.3, dtype=torch.float64, requires_grad=True)
    y = torch.tensor([-100.0, 0.0, 200.0], dtype=torch.float64)
    p = torch.stack([torch.zeros(3, dtype=torch.float64), y, (1000.0 + y * math.tan(0.3))], -1)
    for name, fn in (("exact", optics.blur_diameter_exact), ("first_order", optics.blur_diameter_first_order),
                     ("width", lambda *a: optics.blur_width(*a, torch.tensor([0.0, 1.0], dtype=torch.float64)))):
        b = fn(p, 50.0, U, 20.0, theta_F)
        gU, gF = torch.autograd.grad(b.sum(), (U, theta_F))
        assert float(b.detach().abs().max()) < 1e-9, f"{name}: points on the plane of focus are sharp"
        assert bool(torch.isfinite(gU) & torch.isfinite(gF)), f"{name}: finite gradients, got {gU}, {gF}"
