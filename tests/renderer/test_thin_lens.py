"""thin_lens and thin_lens_accumulation cameras: ray geometry, limits, closed-form blur of rendered spots."""
import math

import pytest
import torch

import renderer.cameras.accumulation  # noqa: F401  (registers thin_lens_accumulation)
import renderer.cameras.thin_lens  # noqa: F401  (registers thin_lens)
from renderer import CameraTransform, ImageSettings, Light, Material, Scene, SceneError, SceneObject
from renderer import render
from renderer.cameras import optics
from renderer.cameras import build_camera
from renderer.cameras.accumulation import AccumulationBufferCamera, render_accumulation
from renderer.cameras.base import Screen
from renderer.cameras.pinhole import PinholeCamera
from renderer.cameras import Lens
from renderer.cameras.thin_lens import ThinLensCamera, concentric_disk
from renderer.scene.materials import CheckerTexture
from renderer.shapes.plane import Plane
from renderer.shapes.sphere import Sphere

DEG = math.pi / 180
W, U, D = 50.0, 1000.0, 20.0  # scene units (mm): sensor distance, focus distance, aperture


def _lens(theta_F_deg=0.0, size=(36.0, 36.0), px=(9, 9), d=D, pp=None, transform=None, cls=ThinLensCamera):
    return cls(transform or CameraTransform.identity(), Lens(W, U, d, theta_F_deg * DEG, principal_point_px=pp), px, size)


def _random_samples(n, cam, seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    uv = torch.rand(n, 2, generator=g, dtype=dtype) * torch.tensor([cam.width, cam.height], dtype=dtype) - 0.5
    return uv, torch.rand(n, 2, generator=g, dtype=dtype)


def _focus_point(cam, uv):
    """Independent: the chief ray (x_s, y_s, w)·t meets z = U + y tan θF at t = U / (w − y_s tan θF)."""
    c = cam.screen.to_plane(uv)
    t = U / (W - c[:, 1] * math.tan(cam.lens.theta_F))
    return c * t[:, None], t


# --- configuration -------------------------------------------------------------------------------------------

def test_config_keys_conversions_and_errors():
    base = {"type": "thin_lens", "w": 55.39, "d": 18.81, "sensor_size": [36.0, 24.0]}
    cam = build_camera("camera", {**base, "U": 648.4, "theta_L_deg": 5.0}, 30, 20)
    assert abs(cam.lens.theta_F / DEG - 48.03) < 0.01, f"theta_L_deg converts exactly to theta_F: {cam.lens.theta_F / DEG}"
    cam_f = build_camera("camera", {**base, "f": float(optics.focal_length(55.39, 618.4)), "theta_L_deg": 5.0}, 30, 20)
    assert abs(cam_f.lens.U - 648.4) < 0.05, f"f + theta_L place U by the hinge rule: {cam_f.lens.U}"
    cam_F = build_camera("camera", {**base, "U": 618.4, "theta_F_deg": 30.0, "principal_point_px": [14.0, 9.0]}, 30, 20)
    assert abs(cam_F.lens.theta_L - float(optics.theta_L_from_theta_F(30 * DEG, 55.39, 618.4))) < 1e-15
    assert cam_F.screen.center_px == (14.0, 9.0) and cam_F.screen.distance == 55.39, "sensor at distance w"
    assert build_camera("camera", {**base, "U": 618.4}, 30, 20).lens.theta_F == 0.0, "theta_F_deg defaults to 0"
    bad = [({**base, "U": 600, "theta_F_deg": 10, "theta_L_deg": 2}, "not both"),
           ({**base}, "exactly one of U"),
           ({**base, "U": 600, "f": 50}, "exactly one of U"),
           ({**base, "U": 600, "d": -1}, "camera.d"),
           ({**base, "U": -5}, "camera.U"),
           ({**base, "U": 600, "theta_F_deg": 90}, "camera.theta_F_deg"),
           ({**base, "f": 60}, "camera.f"),
           ({**base, "U": 600, "focus": 3}, "camera.focus")]
    for cfg, where in bad:
        with pytest.raises(SceneError, match=where):
            build_camera("camera", cfg, 30, 20)


def test_concentric_disk_is_uniform_on_the_disc():
    n = 64
    u = (torch.arange(n, dtype=torch.float64) + 0.5) / n
    uv = torch.stack(torch.meshgrid(u, u, indexing="ij"), -1).reshape(-1, 2)
    s = concentric_disk(uv)
    r2 = (s * s).sum(-1)
    assert float(r2.max()) <= 1 + 1e-12, "samples inside the unit disc"
    assert abs(float(r2.mean()) - 0.5) < 1e-3, f"area-preserving: E[r²] = 1/2, got {float(r2.mean())}"
    assert torch.equal(concentric_disk(torch.tensor([[0.5, 0.5]])), torch.zeros(1, 2)), "centre maps to centre"
    assert bool(torch.isfinite(concentric_disk(torch.tensor([[0.5, 0.3], [0.3, 0.5], [0.0, 0.0]]))).all())


# --- limits ----------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_zero_aperture_is_exactly_the_pinhole(dtype):
    pose = CameraTransform.look_at((10.0, -20.0, 5.0), (30.0, 40.0, 900.0), (0.0, -1.0, 0.0))
    screen = Screen(7, 5, (36.0, 24.0), W, (3.3, 1.7))  # odd, non-square, off-centre principal point
    lens = ThinLensCamera(pose, Lens(W, U, 0.0, 40 * DEG, principal_point_px=(3.3, 1.7)), (7, 5), (36.0, 24.0))
    pin = PinholeCamera(pose, screen)
    uv, lens_uv = _random_samples(200, lens, dtype=dtype)
    a, b = lens.generate_rays(uv, lens_uv), pin.generate_rays(uv, lens_uv)
    assert torch.equal(a.origin, b.origin) and torch.equal(a.direction, b.direction), "d = 0 must be the pinhole"
    p_world = b.origin + 700 * b.direction
    assert torch.allclose(lens.project(p_world), uv, atol=1e-3 if dtype == torch.float32 else 1e-9), \
        "project() inverts the chief ray"


def test_untilted_is_the_plain_thin_lens():
    cam = _lens(0.0, px=(7, 5), size=(36.0, 24.0))
    uv, lens_uv = _random_samples(500, cam)
    rays = cam.rays_in_camera(uv, lens_uv)
    # The textbook thin lens (pbrt's PerspectiveCamera): lens point on the disc z = 0, aim at the focus point.
    s = concentric_disk(lens_uv) * D / 2
    s = torch.cat([s, torch.zeros_like(s[:, :1])], -1)
    p_focus = cam.screen.to_plane(uv) * (U / W)
    d = p_focus - s
    assert torch.allclose(rays.origin, s, atol=1e-15), "origins on the untilted lens disc"
    assert torch.allclose(rays.direction, d / d.norm(dim=-1, keepdim=True), atol=1e-14), "θF = 0 is the thin lens"


# --- ray geometry ------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("theta_F_deg", [0.0, 30.0, -60.0, 75.0])
def test_all_lens_samples_pass_through_the_focus_point(theta_F_deg):
    cam = _lens(theta_F_deg, px=(31, 23))
    uv, lens_uv = _random_samples(4000, cam, seed=1)
    rays = cam.rays_in_camera(uv, lens_uv)
    p_f, t = _focus_point(cam, uv)
    # The focus point must lie on each ray's line, in front of the origin (real) or behind it (virtual).
    along = ((p_f - rays.origin) * rays.direction).sum(-1)
    miss = (p_f - rays.origin - along[:, None] * rays.direction).norm(dim=-1) / p_f.norm(dim=-1)
    assert float(miss.max()) < 1e-12, f"rays of a pixel must meet at its focus point: {float(miss.max())}"
    assert bool((torch.sign(along) == torch.sign(t)).all()), "eq. (5) for P_f in front, eq. (6) behind"
    if theta_F_deg == 75.0:
        assert bool((t < 0).any()) and bool((t > 0).any()), "the test must cover pixels without finite focus"
    lens_normal = torch.tensor([0.0, -math.sin(cam.lens.theta_L), math.cos(cam.lens.theta_L)], dtype=torch.float64)
    assert float((rays.origin @ lens_normal).abs().max()) < 1e-12, "origins lie in the tilted lens plane"
    assert float(rays.origin.norm(dim=-1).max()) <= D / 2 + 1e-12, "origins lie on the aperture disc"
    assert bool((rays.direction @ lens_normal > 0).all()), "rays leave the lens forwards"


def test_rays_are_the_thin_lens_refraction():
    """Physics: ray from the sensor point P through S, refracted by a tilted thin lens of focal length f."""
    cam = _lens(50.0, px=(15, 11))
    uv, lens_uv = _random_samples(1000, cam, seed=2)
    rays = cam.rays_in_camera(uv, lens_uv)
    n = torch.tensor([0.0, -math.sin(cam.lens.theta_L), math.cos(cam.lens.theta_L)], dtype=torch.float64)
    f = float(optics.focal_length(W, U, cam.lens.theta_L))
    p_sensor = -cam.screen.to_plane(uv)  # the image is inverted behind the lens
    s = rays.origin
    v = s - p_sensor
    out = v / (v @ n)[:, None] - s / f  # thin-lens vector refraction (normal component kept at 1)
    out = out / out.norm(dim=-1, keepdim=True)
    assert torch.allclose(rays.direction, out, atol=1e-13), "camera rays must follow thin-lens refraction"


def test_pixels_without_finite_focus_give_finite_diverging_rays():
    theta_F = 75.0
    cam = _lens(theta_F, px=(9, 9))
    y_inf = W / math.tan(theta_F * DEG)  # chief ray parallel to the plane of focus
    cy = cam.screen.center_px[1]
    pitch = cam.screen.pitch[1]
    lens_uv = torch.stack(torch.meshgrid(*(torch.linspace(0.02, 0.98, 12, dtype=torch.float64),) * 2,
                                         indexing="ij"), -1).reshape(-1, 2)
    spread = {}
    for name, y_s in (("parallel", y_inf), ("virtual", y_inf + 4.0)):
        uv = torch.tensor([[4.0, cy + y_s / pitch]], dtype=torch.float64).expand(len(lens_uv), 2)
        rays = cam.rays_in_camera(uv, lens_uv)
        assert bool(torch.isfinite(rays.direction).all() and torch.isfinite(rays.origin).all()), name
        spread[name] = []
        for z in (1000.0, 2000.0, 4000.0):
            p = rays.origin + ((z - rays.origin[:, 2]) / rays.direction[:, 2])[:, None] * rays.direction
            spread[name].append(float(p[:, :2].std(0).norm()))
    uv = torch.tensor([[4.0, cy + y_inf / pitch]], dtype=torch.float64)
    chief = cam.screen.to_plane(uv)
    par = cam.rays_in_camera(uv.expand(len(lens_uv), 2), lens_uv)
    assert torch.allclose(par.direction, (chief / chief.norm()).expand_as(par.direction), atol=1e-9), \
        "D = 0: every ray is parallel to the chief ray"
    s = spread["parallel"]
    assert max(s) - min(s) < 1e-6 * max(s), f"D = 0: rays parallel to the chief ray, constant spread {s}"
    s = spread["virtual"]
    assert s[0] < s[1] < s[2], f"D < 0: the spot grows with distance {s}"
    assert abs((s[2] - s[1]) / (s[1] - s[0]) - 2.0) < 1e-6, f"and grows linearly (virtual point source) {s}"
    # Any |θF| < 90°: every pixel renders, nothing NaN.
    for deg in (-89.99, 89.99):
        cam = _lens(deg, px=(21, 17))
        uv, lens_uv = _random_samples(2000, cam, seed=3, dtype=torch.float32)
        rays = cam.rays_in_camera(uv, lens_uv)
        assert bool(torch.isfinite(rays.direction).all()) and bool(rays.valid.all()), f"θF = {deg}"


# --- accumulation buffer ------------------------------------------------------------------------------------------

def test_accumulation_rays_equal_distributed_rays_where_valid():
    for deg in (0.0, 30.0, 75.0):
        drt, acc = _lens(deg, px=(31, 23)), _lens(deg, px=(31, 23), cls=AccumulationBufferCamera)
        uv, lens_uv = _random_samples(3000, drt, seed=4)
        a, b = drt.rays_in_camera(uv, lens_uv), acc.rays_in_camera(uv, lens_uv)
        _, t = _focus_point(drt, uv)
        assert torch.equal(b.valid, t > 0), "accumulation is valid exactly where the focus point is in front"
        v = b.valid
        assert torch.allclose(a.origin[v], b.origin[v], atol=0) and torch.allclose(
            a.direction[v], b.direction[v], atol=1e-13), f"same rays where both are valid (θF = {deg})"
        assert bool(torch.isfinite(b.direction).all()), "invalid rays stay finite"
        assert acc.frustum_corners()[1] == (deg != 75.0), "the frustum exists only if every corner is in focus"


def _scene(cam, objects, lights=None, spp=4, sampler="sobol"):
    lights = lights or [Light("ambient", (1.0, 1.0, 1.0))]
    return Scene(objects, lights, cam, ImageSettings(cam.width, cam.height, spp, 1, (0.0, 0.0, 0.0), sampler))


def _tilted_floor(cam, theta_F):
    """A checkered plane lying exactly in the plane of focus z = U + y tan θF."""
    normal = (0.0, -math.sin(theta_F), math.cos(theta_F))
    tex = CheckerTexture(40.0, ((0.9, 0.9, 0.9), (0.1, 0.2, 0.6)))
    return SceneObject("floor", Plane((0.0, 0.0, U), normal), Material(color=(1, 1, 1), texture=tex))


def test_plane_of_focus_renders_sharp_and_accumulation_reports_unfocusable_pixels():
    theta_F = 75.0  # chief rays of rows below y_s = w / tan θF = 13.4 mm never meet the plane in front
    px = (20, 18)
    drt = _lens(theta_F, px=px, size=(40.0, 36.0))
    acc = _lens(theta_F, px=px, size=(40.0, 36.0), cls=AccumulationBufferCamera)
    pin = PinholeCamera(CameraTransform.identity(), drt.screen)
    objs = [_tilted_floor(drt, theta_F * DEG)]
    a = render(_scene(drt, objs), dtype=torch.float64)
    b = render(_scene(acc, objs), dtype=torch.float64)
    p = render(_scene(pin, objs), dtype=torch.float64)
    # Rows whose chief ray meets the plane of focus in front of the lens see the plane, sharp: the same
    # image as the pinhole (up to checker cells split by rounding).
    y_s = drt.screen.to_plane(torch.stack([torch.zeros(px[1]), torch.arange(px[1], dtype=torch.float64)], -1))[:, 1]
    D_lo = W - (y_s + drt.screen.pitch[1] / 2) * math.tan(theta_F * DEG)  # D at each row's lower edge
    D_hi = W - (y_s - drt.screen.pitch[1] / 2) * math.tan(theta_F * DEG)
    front, behind = D_lo > 0, D_hi < 0
    assert bool(front.any()) and bool(behind.any()), "the test needs rows on both sides"
    close = (a.image[front] - p.image[front]).abs().max(-1).values < 1e-6
    sharp = float(close.double().mean())
    assert sharp > 0.97, f"objects on the plane of focus are sharp: {sharp:.3f} of pixels equal the pinhole's"
    assert bool((a.coverage == 1).all()), "distributed ray tracing renders every pixel"
    assert bool((b.coverage[front] == 1).all()) and bool((b.coverage[behind] == 0).all()), \
        "accumulation buffer: no coverage where the focus point is behind the lens"
    assert torch.allclose(a.image[front], b.image[front], atol=1e-9), "both methods agree where both are valid"
    # One shared lens point per pass (the original method): same coverage, and the same sharp image as a
    # pinhole with the same pixel samples.
    lens_uv = torch.tensor([[0.2, 0.3], [0.7, 0.6], [0.5, 0.9]], dtype=torch.float64)
    c = render_accumulation(_scene(acc, objs, spp=1), lens_uv, spp=1, dtype=torch.float64)
    p1 = render(_scene(pin, objs, spp=1), dtype=torch.float64)
    assert bool((c.coverage[front] == 1).all()) and bool((c.coverage[behind] == 0).all()), "per-pass coverage"
    close = (c.image[front] - p1.image[front]).abs().max(-1).values < 1e-6
    assert float(close.double().mean()) > 0.97, f"per-pass image sharp on Π_F: {float(close.double().mean())}"


# --- blur spots: rendered vs closed form ----------------------------------------------------------------------------

PITCH = 0.04  # mm per pixel; spots of 10-40 px


def _rendered_spot(p, theta_F, spp=256, rho_px=1.5):
    """Render a tiny ambient-lit sphere at camera point p on a window centred on its predicted spot.

    Returns the measured (width_x, width_y) in pixels: 4 × the per-axis standard deviation, after removing
    the sphere's own image (a disc of radius a: variance a²/4) and the pixel box (variance 1/12) in quadrature.
    """
    p = torch.tensor(p, dtype=torch.float64)
    center, shape = optics.blur_ellipse(p, W, U, D, theta_F)
    n = int(1.4 * 2 * math.sqrt(float(shape.diagonal().max())) / PITCH) + 8
    pp = ((n - 1) / 2 - float(center[0]) / PITCH, (n - 1) / 2 - float(center[1]) / PITCH)
    cam = ThinLensCamera(CameraTransform.identity(), Lens(W, U, D, theta_F, principal_point_px=pp), (n, n), (n * PITCH, n * PITCH))
    rho = rho_px * PITCH * float(p.norm()) / W
    obj = SceneObject("dot", Sphere(p.tolist(), rho), Material(color=(1.0, 1.0, 1.0)))
    img = render(_scene(cam, [obj], spp=spp), dtype=torch.float64).image[..., 0]
    ys, xs = torch.meshgrid(torch.arange(n, dtype=torch.float64), torch.arange(n, dtype=torch.float64), indexing="ij")
    m = img.sum()
    mx, my = (img * xs).sum() / m, (img * ys).sum() / m
    a = W * math.tan(math.asin(rho / float(p.norm()))) / PITCH
    own = a * a / 4 + 1 / 12
    var_x = float((img * (xs - mx) ** 2).sum() / m) - own
    var_y = float((img * (ys - my) ** 2).sum() / m) - own
    centroid_err = math.hypot(float(mx) - (n - 1) / 2, float(my) - (n - 1) / 2)
    return 4 * math.sqrt(var_x), 4 * math.sqrt(var_y), centroid_err


@pytest.mark.parametrize("z", [500.0, 650.0, 2000.0, 4000.0])
def test_rendered_blur_matches_eq2_untilted(z):
    measured_x, measured_y, centroid_err = _rendered_spot([0.0, 0.0, z], 0.0)
    b = float(optics.blur_diameter_paper(0.0, z, W, U, D)) / PITCH
    for axis, m in (("x", measured_x), ("y", measured_y)):
        assert abs(m / b - 1) < 0.03, f"z = {z}: rendered {axis} diameter {m:.2f} px vs eq. (2) {b:.2f} px"
    assert centroid_err < 0.3, f"spot centred on the chief-ray image, off by {centroid_err:.2f} px"


@pytest.mark.parametrize("p", [[0.0, 150.0, 600.0], [40.0, 250.0, 900.0], [0.0, 200.0, 2400.0],
                               [-50.0, -150.0, 3000.0]])
def test_rendered_blur_matches_exact_ellipse_tilted(p):
    theta_F = 45 * DEG
    side = p[2] - float(optics.focus_depth(p[1], U, theta_F))
    measured_x, measured_y, centroid_err = _rendered_spot(p, theta_F)
    pt = torch.tensor(p, dtype=torch.float64)
    for axis, m, n in (("x", measured_x, [1.0, 0.0]), ("y", measured_y, [0.0, 1.0])):
        b = float(optics.blur_width(pt, W, U, D, theta_F, torch.tensor(n, dtype=torch.float64))) / PITCH
        where = "behind" if side > 0 else "before"
        assert abs(m / b - 1) < 0.05, f"p = {p} ({where} Π_F): {axis} {m:.2f} vs {b:.2f} px"
    assert centroid_err < 0.3, f"spot centred on the ellipse centre, off by {centroid_err:.2f} px"
    paper = float(optics.blur_diameter_paper(p[1], p[2], W, U, D, theta_F)) / PITCH
    assert abs(measured_x / paper - 1) > 0.05, f"the paper's eq. (4) misses this spot by more than 5% ({paper:.2f} px)"


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("theta_F_deg", [0.0, 25.0])
def test_in_place_rays_equal_the_general_formulas_bit_for_bit(dtype, theta_F_deg):
    """`rays_in_camera` writes rays of plain-number cameras in place (`_rays_in_place`); inputs that need a
    gradient take the general formulas. Both must give the same bits, on an odd, non-square image with an
    off-centre principal point, including the lens centre and the square's corners (the concentric map's
    0/0 and its octant edges)."""
    cam = _lens(theta_F_deg, size=(36.0, 24.0), px=(13, 7), pp=(5.0, 2.5))
    uv, lens = _random_samples(4001, cam, seed=3, dtype=dtype)
    lens[:5] = torch.tensor([[0.5, 0.5], [0.0, 0.0], [0.0, 1.0], [0.75, 0.75], [0.5, 0.0]], dtype=dtype)
    fast = cam.rays_in_camera(uv, lens)
    general = cam.rays_in_camera(uv.clone().requires_grad_(True), lens)
    for name in ("origin", "direction", "weight", "valid"):
        a, b = getattr(fast, name), getattr(general, name).detach()
        assert a.dtype == b.dtype and torch.equal(a, b), f"{name}: max |diff| {float((a.double() - b.double()).abs().max()):.3g}"
    assert torch.allclose(fast.direction.norm(dim=-1), torch.ones(4001, dtype=dtype)), "directions not unit"


def test_in_place_rays_keep_every_kind_of_derivative():
    """The in-place rays and the branch-free selects of the concentric map are for plain inputs only: a
    principal point that needs a gradient, forward-mode AD (torch.func.jacfwd) through the pixels or the lens
    samples, and mismatched shapes all take the general formulas, with the same derivatives as reverse mode."""
    cam = _lens(20.0, size=(36.0, 24.0), px=(13, 7), pp=(5.0, 2.5))
    uv, lens = _random_samples(64, cam, seed=5)
    # A differentiable principal point on a plain-number lens: reverse mode reaches it.
    pp = torch.tensor([5.0, 2.5], dtype=torch.float64, requires_grad=True)
    cam_pp = _lens(20.0, size=(36.0, 24.0), px=(13, 7), pp=pp)
    cam_pp.generate_rays(uv, lens).direction.sum().backward()
    assert pp.grad is not None and float(pp.grad.abs().sum()) > 0, "no gradient reached the principal point"
    # Forward mode through the pixels and the lens samples equals reverse mode, and is not zero.
    for argnum, name in ((0, "pixels"), (1, "lens samples")):
        f = lambda a, b: cam.generate_rays(a, b).direction  # noqa: E731
        fwd = torch.func.jacfwd(f, argnums=argnum)(uv[:8], lens[:8])
        rev = torch.func.jacrev(f, argnums=argnum)(uv[:8], lens[:8])
        assert float(rev.abs().max()) > 0.01, f"{name}: the reverse-mode Jacobian should not vanish"
        assert torch.allclose(fwd, rev, atol=1e-12), f"{name}: forward mode {float((fwd - rev).abs().max()):.3g} off"
    jf = torch.func.jacfwd(concentric_disk)(lens[:8])
    jr = torch.func.jacrev(concentric_disk)(lens[:8])
    assert float(jr.abs().max()) > 0.5 and torch.allclose(jf, jr, atol=1e-12), "concentric map: forward mode"
    # Lens samples of another shape than the pixels: the general formulas' broadcasting error, not (4, 3) rays.
    with pytest.raises(RuntimeError):
        cam.generate_rays(uv[:4], lens[:50])


@pytest.mark.parametrize("phi_deg", [0.0, 35.0, 90.0, -120.0])
def test_a_turned_tilt_axis_focuses_on_its_plane(phi_deg):
    """Tilt axis turned by φ (a tilt-shift lens's rotation): every ray of a pixel leaves the lens disc in the plane
    z = y_φ tan θL and passes through the point where the pixel's chief ray meets z = U + y_φ tan θF,
    y_φ = y cos φ − x sin φ (closed forms written here, not the camera's)."""
    phi, theta_F = math.radians(phi_deg), math.radians(30.0)
    lens = Lens(W, U, D, theta_F, phi=phi)
    cam = ThinLensCamera(CameraTransform.identity(), lens, (11, 7), (36.0, 24.0))
    g = torch.Generator().manual_seed(5)
    uv = torch.rand(40, 2, generator=g, dtype=torch.float64) * torch.tensor([11.0, 7.0]) - 0.5
    lens_uv = torch.rand(40, 2, generator=g, dtype=torch.float64)
    rays = cam.generate_rays(uv, lens_uv)
    chief = cam.generate_rays(uv, torch.full_like(lens_uv, 0.5)).direction
    c, s = math.cos(phi), math.sin(phi)
    y_phi = lambda p: p[:, 1] * c - p[:, 0] * s  # noqa: E731
    t = U / (chief[:, 2] - y_phi(chief) * math.tan(theta_F))
    focus = chief * t[:, None]
    o = rays.origin
    tan_L = W * math.tan(theta_F) / (U + W)  # exact Scheimpflug
    assert torch.allclose(o[:, 2], y_phi(o) * tan_L, atol=1e-9), "lens points lie in the tilted lens plane"
    assert float(o[:, :2].norm(dim=-1).max()) > 0.3 * D, "samples spread over the disc"
    to_focus = focus - o
    cross = torch.linalg.cross(to_focus, rays.direction)
    assert float((cross.norm(dim=-1) / to_focus.norm(dim=-1)).max()) < 1e-9, "each ray passes through the focus"


def test_a_replaced_lens_moves_the_rays():
    """The camera keeps no copy of its lens: w, the principal point and the distortion are read from `lens` on every
    call, so a lens set after construction (`cam.lens = cam.lens.with_(...)`) gives the rays and the projection
    of a camera built with it."""
    lens = Lens(W, U, D, 20 * DEG, principal_point_px=(4.0, 3.5))
    moved = lens.with_(w=1.3 * W, principal_point_px=(5.25, 2.0), distortion=(-0.2, 0.03))
    cam = ThinLensCamera(CameraTransform.identity(), lens, (9, 7), (36.0, 24.0))
    cam.lens = moved
    fresh = ThinLensCamera(CameraTransform.identity(), moved, (9, 7), (36.0, 24.0))
    uv, lens_uv = _random_samples(50, cam)
    a, b = cam.generate_rays(uv, lens_uv), fresh.generate_rays(uv, lens_uv)
    assert torch.equal(a.origin, b.origin) and torch.equal(a.direction, b.direction), "rays at the new w"
    assert cam.screen.distance == 1.3 * W and cam.screen.center_px == (5.25, 2.0), "the screen follows the lens"
    p = torch.tensor([[30.0, -20.0, 900.0]], dtype=torch.float64)
    assert torch.equal(cam.project(p), fresh.project(p)), "the projection too, with the new distortion"
