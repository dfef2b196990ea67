"""Closed-form Jacobians of the calibration camera against autograd (float64): the axis-angle rotation, the
distortion coefficients, the three blur closed forms, and `LensCamera.jacobian` for every distortion model and
blur model, tilted and not."""
import math

import pytest
import torch
from torch.func import functional_call, jacrev

from renderer.cameras import optics
from renderer.cameras import LensCamera
from renderer.cameras.distortion import (MODEL_TERMS, COEFFICIENT_NAMES, distort, distort_coefficient_jacobian,
                                         distort_jacobian, distort_with_jacobians)
from renderer.core.transforms import axis_angle_to_matrix, rotated_point_jacobian

F64 = torch.float64
TOL = 1e-9  # relative to the largest derivative; the closed forms agree with autograd to ~1e-15


def _rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).abs().max() / b.abs().max().clamp(min=1e-300))


@pytest.mark.parametrize("rvec", [[0.3, -0.2, 0.5], [1e-5, 2e-5, -1e-5], [0.0, 0.0, 0.0], [0.0, 3.0, 0.1]])
def test_rotated_point_jacobian_matches_autograd(rvec):
    r = torch.tensor(rvec, dtype=F64)
    X = torch.tensor([[120.0, -40.0, 3.0], [-5.0, 80.0, 0.0]], dtype=F64)
    auto = torch.stack([jacrev(lambda v: axis_angle_to_matrix(v) @ x)(r) for x in X])
    ours = rotated_point_jacobian(r, X @ axis_angle_to_matrix(r).T)
    assert _rel_err(ours, auto) < TOL, f"∂(R X)/∂r at r = {rvec}: {_rel_err(ours, auto):.2e}"


@pytest.mark.parametrize("lead", [((3, 1), (3, 5)), ((3, 1), (1, 5)), ((1, 1), (3, 5)), ((2, 3, 1), (2, 1, 5))],
                         ids=["per-view", "rows-shared", "rotation-shared", "two-batch-dims"])
def test_rotated_point_jacobian_rows_broadcast(lead):
    """With `rows`, ∂f/∂r = rows · ∂(R X)/∂r for every broadcast of the rotations' and the rows' batch dimensions
    (one rotation a view over its points, or rows shared by all views)."""
    gen = torch.Generator().manual_seed(3)
    r_lead, x_lead = lead
    r = 0.4 * torch.randn(*r_lead, 3, generator=gen, dtype=F64)
    p = 100.0 * torch.randn(*x_lead, 3, generator=gen, dtype=F64)
    rows = torch.randn(*x_lead, 2, 3, generator=gen, dtype=F64)
    want = rows @ rotated_point_jacobian(r, p)
    ours = rotated_point_jacobian(r, p, rows)
    assert ours.shape == want.shape, f"shape {tuple(ours.shape)}, expected {tuple(want.shape)}"
    assert _rel_err(ours, want) < TOL, f"rows · ∂(R X)/∂r: {_rel_err(ours, want):.2e}"


def test_rotated_point_jacobian_needs_no_broadcast_shapes(monkeypatch):
    """The per-view product's broadcast check is made by hand: `torch.broadcast_shapes` imports sympy on its first
    call, which every `tiltfit calibrate` would pay (its Jacobian calls this first)."""
    def refuse(*shapes):
        raise AssertionError("torch.broadcast_shapes called")

    monkeypatch.setattr(torch, "broadcast_shapes", refuse)
    gen = torch.Generator().manual_seed(4)
    r = 0.4 * torch.randn(3, 1, 3, generator=gen, dtype=F64)
    p = 100.0 * torch.randn(3, 5, 3, generator=gen, dtype=F64)
    rows = torch.randn(3, 5, 2, 3, generator=gen, dtype=F64)
    ours = rotated_point_jacobian(r, p, rows)
    assert _rel_err(ours, rows @ rotated_point_jacobian(r, p)) < TOL, "rows · ∂(R X)/∂r"


def test_distort_coefficient_jacobian_matches_autograd():
    gen = torch.Generator().manual_seed(1)
    xy = 0.4 * torch.randn(30, 2, generator=gen, dtype=F64)
    k = 0.1 * torch.randn(8, generator=gen, dtype=F64)
    auto = jacrev(lambda c: distort(xy, c))(k)
    ours = distort_coefficient_jacobian(xy, k)
    assert ours.shape == (30, 2, 8), f"shape {tuple(ours.shape)}"
    assert _rel_err(ours, auto) < TOL, f"∂D/∂k: {_rel_err(ours, auto):.2e}"


def test_distortion_and_its_jacobians_at_once_are_the_same_numbers():
    """`distort_with_jacobians` (the Jacobian's one pass: r² and the radial factor shared) gives exactly the numbers
    of `distort`, `distort_jacobian` and `distort_coefficient_jacobian`, for any subset of the coefficients' columns
    in their order, and no coefficient columns where none are asked for."""
    gen = torch.Generator().manual_seed(7)
    xy = 0.4 * torch.randn(3, 30, 2, generator=gen, dtype=F64)
    k = 0.1 * torch.randn(8, generator=gen, dtype=F64)
    full = distort_coefficient_jacobian(xy, k)
    for names in (COEFFICIENT_NAMES, ("k1",), ("k2", "p2", "k4"), MODEL_TERMS["rational5"]):
        xd, J_xy, J_k = distort_with_jacobians(xy, k, names)
        assert torch.equal(xd, distort(xy, k)) and torch.equal(J_xy, distort_jacobian(xy, k)), "x_d and ∂x_d/∂xy"
        cols = [COEFFICIENT_NAMES.index(n) for n in names]
        assert torch.equal(J_k, full[..., cols]), f"∂x_d/∂k of {names}"
        assert torch.equal(distort_coefficient_jacobian(xy, k, names), J_k), f"the named columns of {names}"
    assert distort_with_jacobians(xy, k, ())[2] is None, "no coefficient columns asked for"


@pytest.fixture(scope="module")
def points_cam():
    """Points in front of the camera on both sides of a plane of focus near 640 mm."""
    gen = torch.Generator().manual_seed(2)
    p = torch.randn(200, 3, generator=gen, dtype=F64) * torch.tensor([150.0, 120.0, 120.0], dtype=F64)
    return p + torch.tensor([0.0, 0.0, 640.0], dtype=F64)


@pytest.mark.parametrize("blur_model", optics.BLUR_MODELS)
@pytest.mark.parametrize("theta_F", [0.0, 0.8, -0.4])
def test_blur_diameter_jacobian_matches_autograd(points_cam, blur_model, theta_F):
    lens = torch.tensor([55.4, 640.0, 18.8, theta_F], dtype=F64)

    def b(p, v):
        return optics.blur_diameter(p, v[0], v[1], v[2], v[3], blur_model)

    value, ours = optics.blur_diameter_jacobian(points_cam, *lens, blur_model=blur_model)
    jp, jl = torch.func.vmap(jacrev(b, argnums=(0, 1)), in_dims=(0, None))(points_cam, lens)
    auto = torch.cat([jp, jl], -1)
    assert torch.allclose(value, b(points_cam, lens), rtol=1e-13, atol=0), "the value is blur_diameter's"
    assert ours.shape == (200, 7), f"columns {optics.BLUR_JACOBIAN_ARGS}, got shape {tuple(ours.shape)}"
    assert _rel_err(ours, auto) < TOL, f"{blur_model}, θF {theta_F}: {_rel_err(ours, auto):.2e}"


def test_blur_diameter_jacobian_matches_finite_differences(points_cam):
    """An independent check of the ellipse's chain rule (autograd shares the forward formula)."""
    args = [55.4, 640.0, 18.8, 0.6]
    _, J = optics.blur_diameter_jacobian(points_cam, *args)
    for i in range(7):
        h = 1e-6 * (abs(args[i - 3]) if i >= 3 else 1.0)
        plus, minus = points_cam.clone(), points_cam.clone()
        a_plus, a_minus = list(args), list(args)
        if i < 3:
            plus[:, i] += h
            minus[:, i] -= h
        else:
            a_plus[i - 3] += h
            a_minus[i - 3] -= h
        fd = (optics.blur_diameter(plus, *a_plus) - optics.blur_diameter(minus, *a_minus)) / (2 * h)
        assert _rel_err(J[:, i], fd) < 1e-6, f"∂b/∂{optics.BLUR_JACOBIAN_ARGS[i]}: {_rel_err(J[:, i], fd):.2e}"


def _camera(distortion_model: str, blur_model: str, theta_F: float, seed: int, phi: float = 0.0,
            centre: str = "sensor") -> LensCamera:
    gen = torch.Generator().manual_seed(seed)
    u = lambda *s: 2 * torch.rand(*s, generator=gen, dtype=F64) - 1  # noqa: E731
    V = 3
    rvec = 0.3 * u(V, 3)
    T = torch.stack([40 * u(V), 30 * u(V), 560 + 80 * u(V)], -1)
    terms = MODEL_TERMS[distortion_model]
    coeff = [0.05 * float(u(1)) if name in terms else 0.0 for name in COEFFICIENT_NAMES]
    cam = LensCamera(V, (1368, 912), 0.026, 55.0, 620.0, 18.0, theta_F, rvec=rvec, T_mm=T, blur_model=blur_model,
                     principal_point_px=(690.0, 449.0), distortion=coeff, phi=phi, distortion_centre=centre)
    with torch.no_grad():
        cam.blur_offset_px.fill_(0.2)
    return cam


CASES = [(m, b, th, 0.0, "sensor") for m in MODEL_TERMS for b, th in (("ellipse", 0.0), ("ellipse", 0.7), ("first_order", -0.5),
                                                           ("paper", 0.4))]
# The tilt axis turned by φ (Lens.phi): the blur rows go through the turned frame, and ∂/∂φ is a new row.
CASES += [("k1k2", "ellipse", 0.7, 0.9, "sensor"), ("opencv5", "first_order", -0.5, -2.1, "sensor"),
          ("none", "paper", 0.4, 1.3, "sensor")]
# The distortion about the tilted lens's axis: its frame turns with θL (w, 1/U, θF) and φ.
CASES += [("k1k2", "ellipse", 0.7, 0.9, "lens_axis"), ("rational", "first_order", -0.5, 0.0, "lens_axis"),
          ("opencv5", "ellipse", 0.0, 0.0, "lens_axis"), ("opencv5", "paper", 0.4, -2.1, "lens_axis")]


@pytest.mark.parametrize("distortion_model,blur_model,theta_F,phi,centre", CASES)
def test_lens_camera_jacobian_matches_autograd(distortion_model, blur_model, theta_F, phi, centre):
    cam = _camera(distortion_model, blur_model, theta_F, seed=len(distortion_model) + int(10 * theta_F) + 20, phi=phi,
                  centre=centre)
    X = torch.stack(torch.meshgrid(torch.linspace(-100, 100, 5, dtype=F64), torch.linspace(-60, 60, 4, dtype=F64),
                                   indexing="xy"), -1).reshape(-1, 2)
    X = torch.cat([X, torch.zeros(X.shape[0], 1, dtype=F64)], -1)
    params = {n: p.detach() for n, p in cam.named_parameters()}

    def model(pr):
        uv, b = functional_call(cam, pr, (X,))
        return torch.cat([uv, b[..., None]], -1)

    uv, b, ours = cam.jacobian(X)
    expected = model(params)
    assert torch.allclose(uv, expected[..., :2], rtol=0, atol=1e-9), "uv is forward's"
    assert torch.allclose(b, expected[..., 2], rtol=0, atol=1e-12), "b is forward's"
    auto = jacrev(model)(params)
    V, N = cam.n_views, X.shape[0]
    assert set(ours) == set(auto), f"every stored parameter: {sorted(set(auto) ^ set(ours))}"
    for name, a in auto.items():
        if name in ("rvec", "T_scaled"):
            a = torch.stack([a[v, :, :, v, :] for v in range(V)])      # a view's rows and its own pose
        else:
            a = a.reshape(V, N, 3, -1)
        assert ours[name].shape == a.shape, f"{name}: shape {tuple(ours[name].shape)} vs {tuple(a.shape)}"
        scale = max(float(a.abs().max()), 1e-300)
        err = float((ours[name] - a).abs().max()) / scale
        assert err < TOL or float(a.abs().max()) == 0 and float(ours[name].abs().max()) == 0, \
            f"∂(u, v, b)/∂{name} ({distortion_model}, {blur_model}, θF {theta_F}, φ {phi}, {centre}): relative error " \
            f"{err:.2e}"


def test_lens_camera_jacobian_without_blur_or_distortion_has_zero_rows():
    cam = _camera("opencv5", "ellipse", 0.3, seed=5)
    X = torch.tensor([[0.0, 0.0, 0.0], [50.0, 20.0, 0.0]], dtype=F64)
    uv, b, jac = cam.jacobian(X, with_blur=False, with_distortion=False)
    assert float(b.abs().max()) == 0 and float(jac["d_scaled"].abs().max()) == 0, "no blur: zero blur rows"
    assert float(jac["dist_k1"].abs().max()) == 0, "no distortion: zero distortion columns"
    assert not math.isclose(float(jac["log_w_mm"].abs().max()), 0.0), "the focal length still moves the corners"
