"""Orthographic and inverted-perspective cameras: ray invariants, closed-form projection, rendered positions.

The rendered checks measure where a tiny bright sphere lands (intensity-weighted centroid, antialiased) on an
odd, non-square image and compare with the paper's eq. (4), (5).
"""
from __future__ import annotations

import pytest
import torch

from renderer import ImageSettings, Light, Material, Scene, SceneError, SceneObject
from renderer import render
from renderer.cameras import build_camera
from renderer.cameras.base import Screen
from renderer.cameras.inverted_perspective import InvertedPerspectiveCamera
from renderer.cameras.orthographic import OrthographicCamera
from renderer.shapes import build_shape
from renderer.core.transforms import CameraTransform

W, H = 41, 29  # odd and non-square, so a swapped or off-by-half pixel convention shows
SCREEN_SIZE = (0.82, 0.58)  # pitch 0.02 at q3 = 1
P3 = 4.0
ALPHAS = (0.0, 0.5, 1.0, 2.0)
# A tilted, moved pose: the closed forms must hold in the camera frame whatever the pose is.
POSE = dict(position=[0.3, -0.2, -1.0], look_at=[0.1, 0.0, 4.0], up=[0.1, -1.0, 0.05])


def inverted(alpha, pose=None, q3=1.0):
    cfg = dict(type="inverted_perspective", screen_size=[SCREEN_SIZE[0] * q3, SCREEN_SIZE[1] * q3],
               screen_distance=q3, alpha=alpha, pseudo_screen_distance=P3, **(pose or {}))
    return build_camera("camera", cfg, W, H)


def pinhole(pose=None):
    return build_camera("camera", dict(type="pinhole", screen_size=list(SCREEN_SIZE), **(pose or {})), W, H)


def orthographic(window, pose=None):
    return build_camera("camera", dict(type="orthographic", screen_size=list(window), **(pose or {})), W, H)


def some_pixels(dtype, shape=(3, 5)):
    g = torch.Generator().manual_seed(1)
    u = torch.rand(*shape, 2, generator=g, dtype=torch.float64) * torch.tensor([W + 1.0, H + 1.0]) - 1.0
    return u.to(dtype)


def all_cameras():
    return {
        "orthographic": orthographic((1.2, 0.9), POSE),
        "inverted_a0": inverted(0.0, POSE),
        "inverted_a0.5": inverted(0.5, POSE),
        "inverted_a1": inverted(1.0, POSE),
        "inverted_a2": inverted(2.0, POSE),
    }


# --- ray level -------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("name", list(all_cameras()))
def test_rays_are_unit_valid_and_batched(name, dtype):
    cam = all_cameras()[name]
    uv = some_pixels(dtype, (2, 3, 4))
    rays = cam.generate_rays(uv)
    assert rays.origin.shape == (2, 3, 4, 3), f"{name}: origin shape {tuple(rays.origin.shape)}"
    assert rays.direction.shape == (2, 3, 4, 3), f"{name}: direction shape {tuple(rays.direction.shape)}"
    assert rays.valid.shape == (2, 3, 4) and rays.valid.dtype == torch.bool, f"{name}: valid mask {rays.valid}"
    assert rays.weight.shape == (2, 3, 4), f"{name}: weight shape {tuple(rays.weight.shape)}"
    assert rays.origin.dtype == dtype and rays.direction.dtype == dtype, f"{name}: dtype does not follow input"
    assert bool(rays.valid.all()), f"{name}: every pixel of these cameras has a ray"
    norm = torch.linalg.vector_norm(rays.direction, dim=-1)
    tol = 1e-6 if dtype == torch.float32 else 1e-12
    assert torch.allclose(norm, torch.ones_like(norm), atol=tol), f"{name}: directions not unit, {norm}"
    assert bool(torch.isfinite(rays.origin).all() and torch.isfinite(rays.direction).all()), f"{name}: non-finite"
    flat = cam.generate_rays(uv.reshape(-1, 2))
    assert torch.equal(flat.direction.reshape(rays.direction.shape), rays.direction), f"{name}: batch changes rays"


@pytest.mark.parametrize("name", list(all_cameras()))
def test_project_inverts_rays(name):
    """Any point on a pixel's ray projects back to that pixel (float64)."""
    cam = all_cameras()[name]
    uv = some_pixels(torch.float64)
    rays = cam.generate_rays(uv)
    for t in (0.7, 3.0, 9.0):
        uv_back = cam.project(rays.origin + t * rays.direction)
        err = (uv_back - uv).abs().max()
        assert err < 1e-9, f"{name}: point at t={t} projects {float(err)} px away from its pixel"


@pytest.mark.parametrize("alpha", ALPHAS)
def test_project_is_equation_4_5(alpha):
    """project() in the camera frame is q_k = a_k q3 / (α (p3 − a3) + a3), mapped by the screen."""
    q3 = 1.5
    cam = inverted(alpha, q3=q3)  # default pose: camera frame = scene frame
    a = torch.tensor([[0.4, -0.3, 3.0], [-0.2, 0.1, 5.5], [0.3, 0.3, P3]], dtype=torch.float64)
    q = a[:, :2] * q3 / (alpha * (P3 - a[:, 2:]) + a[:, 2:])
    expected = q / torch.tensor([SCREEN_SIZE[0] * q3 / W, SCREEN_SIZE[1] * q3 / H]) + torch.tensor(
        [(W - 1) / 2, (H - 1) / 2])
    assert torch.allclose(cam.project(a), expected, atol=1e-12), f"alpha={alpha}: project differs from eq. (4)(5)"


def test_alpha0_rays_equal_pinhole():
    for dtype, tol in ((torch.float64, 1e-12), (torch.float32, 1e-6)):
        uv = some_pixels(dtype)
        a, b = inverted(0.0, POSE).generate_rays(uv), pinhole(POSE).generate_rays(uv)
        assert torch.allclose(a.origin, b.origin, atol=tol), f"{dtype}: α=0 origins differ from the pinhole's"
        assert torch.allclose(a.direction, b.direction, atol=tol), f"{dtype}: α=0 directions differ from the pinhole's"
    p = torch.tensor([[0.5, 0.2, 3.0], [-1.0, 0.4, 7.0]], dtype=torch.float64)
    assert torch.allclose(inverted(0.0, POSE).project(p), pinhole(POSE).project(p), atol=1e-10), "α=0 project"


def test_alpha1_rays_equal_orthographic():
    window = (SCREEN_SIZE[0] * P3, SCREEN_SIZE[1] * P3)  # screen_size · p3 / q3 with q3 = 1
    for dtype, tol in ((torch.float64, 1e-12), (torch.float32, 1e-6)):
        uv = some_pixels(dtype)
        a, b = inverted(1.0, POSE).generate_rays(uv), orthographic(window, POSE).generate_rays(uv)
        assert torch.allclose(a.origin, b.origin, atol=tol), f"{dtype}: α=1 origins differ from orthographic"
        assert torch.allclose(a.direction, b.direction, atol=tol), f"{dtype}: α=1 directions differ from orthographic"


def test_orthographic_sees_along_z_with_its_window():
    cam = orthographic((0.82, 0.58))
    corners = torch.tensor([[-0.5, -0.5], [W - 0.5, H - 0.5]], dtype=torch.float64)
    rays = cam.generate_rays(corners)
    expected = torch.tensor([[-0.41, -0.29, 0.0], [0.41, 0.29, 0.0]], dtype=torch.float64)
    assert torch.allclose(rays.origin, expected, atol=1e-12), f"pixel corners should span the window: {rays.origin}"
    assert torch.equal(rays.direction, torch.tensor([[0.0, 0, 1]] * 2, dtype=torch.float64)), "rays along +z"
    p = torch.tensor([[0.2, -0.1, 1.0], [0.2, -0.1, 50.0]], dtype=torch.float64)
    uv = cam.project(p)
    assert torch.allclose(uv[0], uv[1], atol=1e-12), f"depth must not change the orthographic image: {uv}"


def test_pseudo_screen_points_do_not_move_with_alpha():
    a = torch.tensor([[0.35, -0.3, P3], [-0.9, 0.6, P3]], dtype=torch.float64)
    ref = inverted(0.0).project(a)
    for alpha in ALPHAS[1:] + (3.5, -0.5):
        assert torch.allclose(inverted(alpha).project(a), ref, atol=1e-12), f"α={alpha}: pseudo-screen point moved"


@pytest.mark.parametrize("alpha", [0.5, 2.0, 3.0])
def test_all_rays_meet_at_the_apex(alpha):
    """For α ≠ 1 every ray passes through (0, 0, α p3 / (α − 1)) in the camera frame (paper notes)."""
    cam = inverted(alpha)
    rays = cam.rays_in_camera(some_pixels(torch.float64), torch.zeros(3, 5, 2, dtype=torch.float64))
    apex_z = alpha * P3 / (alpha - 1)
    t = (apex_z - rays.origin[..., 2]) / rays.direction[..., 2]
    at_apex = rays.origin + t[..., None] * rays.direction
    assert torch.allclose(at_apex[..., :2], torch.zeros_like(at_apex[..., :2]), atol=1e-12), \
        f"α={alpha}: rays miss the apex by {float(at_apex[..., :2].abs().max())}"


def test_singular_depth_gives_inf_not_nan():
    alpha = 2.0
    cam = inverted(alpha)
    z_apex = alpha * P3 / (alpha - 1)  # 8.0, exactly representable: the denominator of (4) is exactly 0
    a = torch.tensor([[0.3, 0.2, z_apex], [0.0, 0.0, z_apex], [0.3, 0.2, 6.0]], dtype=torch.float64,
                     requires_grad=True)
    uv = cam.project(a)
    assert not bool(uv.isnan().any()), f"NaN in the projection at the singular depth: {uv}"
    assert bool(uv[:2].isinf().all()), f"points at the singular depth should be +inf, got {uv[:2]}"
    assert bool(uv[2].isfinite().all()), f"a regular point should stay finite, got {uv[2]}"
    uv[2].sum().backward()
    assert not bool(a.grad.isnan().any()), f"NaN gradient next to the singular point: {a.grad}"


def test_float32_projection_matches_float64():
    cam = inverted(2.0, POSE)
    p = torch.tensor([[0.5, 0.2, 3.0], [-1.0, 0.4, 5.0]], dtype=torch.float64)
    d = (cam.project(p.float()).double() - cam.project(p)).abs().max()
    assert d < 1e-3, f"float32 projection is {float(d)} px off the float64 one"


# --- configuration ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("cfg, message", [
    (dict(type="inverted_perspective", screen_size=[1, 1], pseudo_screen_distance=4), "camera.alpha: missing"),
    (dict(type="inverted_perspective", screen_size=[1, 1], alpha=1), "camera.pseudo_screen_distance: missing"),
    (dict(type="inverted_perspective", screen_size=[1, 1], alpha=1, pseudo_screen_distance=0),
     "camera.pseudo_screen_distance: expected a positive distance, got 0"),
    (dict(type="inverted_perspective", screen_size=[1, 1], alpha="big", pseudo_screen_distance=4),
     "camera.alpha: expected a number, got 'big'"),
    (dict(type="orthographic"), "camera.screen_size: missing"),
    (dict(type="orthographic", fov_deg=40), "camera.fov_deg: unknown key"),
    (dict(type="orthographic", screen_size=[1, -1]), "camera.screen_size: expected positive sizes"),
])
def test_bad_config_names_the_field(cfg, message):
    with pytest.raises(SceneError) as err:
        build_camera("camera", cfg, W, H)
    assert message in str(err.value), f"message {str(err.value)!r} should contain {message!r}"


def test_built_types():
    assert isinstance(inverted(1.0), InvertedPerspectiveCamera), "inverted_perspective builds its class"
    cam = build_camera("camera", dict(type="inverted_perspective", fov_deg=60, alpha=2, pseudo_screen_distance=3),
                       W, H)
    assert cam.alpha == 2.0 and cam.pseudo_screen_distance == 3.0, "alpha and p3 are read from the file"
    assert isinstance(orthographic((1, 1)), OrthographicCamera), "orthographic builds its class"
    direct = OrthographicCamera(CameraTransform.identity(), Screen(W, H, (1.0, 1.0), 5.0))
    assert torch.equal(direct.generate_rays(torch.zeros(2)).direction, torch.tensor([0.0, 0.0, 1.0])), \
        "an orthographic camera built in code looks along +z"


# --- rendered positions ----------------------------------------------------------------------------------------

# Sphere centres (camera = scene frame): two nearer than the pseudo-screen, one beyond it, one on it. Chosen so
# that for all α in ALPHAS the images stay inside the frame and more than 7 px apart along x or y.
CENTERS = [(0.5, 0.3, 3.0), (-0.6, 0.35, 5.0), (-0.3, -0.35, 3.5), (0.45, -0.45, P3)]
ON_PSEUDO_SCREEN = 3
RADIUS = 0.1
WINDOW = 4  # half-size of the centroid window, px


def dots_scene(camera, spp=36):
    objects = [SceneObject(f"dot{k}", build_shape("shape", dict(type="sphere", center=list(c), radius=RADIUS)),
                           Material(color=(1.0, 1.0, 1.0))) for k, c in enumerate(CENTERS)]
    return Scene(objects, [Light("ambient", (1.0, 1.0, 1.0))], camera,
                 ImageSettings(W, H, spp=spp, max_depth=0, sampler="stratified"))


def centroids(image: torch.Tensor, predicted: torch.Tensor) -> torch.Tensor:
    """Intensity-weighted centroid (x, y) in a window around each predicted pixel position."""
    lum = image.to(torch.float64).sum(-1)
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    out = []
    for x0, y0 in predicted.tolist():
        win = ((xs - round(x0)).abs() <= WINDOW) & ((ys - round(y0)).abs() <= WINDOW)
        w = torch.where(win, lum, torch.zeros_like(lum))
        out.append(torch.stack([(w * xs).sum() / w.sum(), (w * ys).sum() / w.sum()]))
    return torch.stack(out)


@pytest.fixture(scope="module")
def rendered():
    images = {f"inverted_a{a}": render(dots_scene(inverted(a)), dtype=torch.float64).image for a in ALPHAS}
    images["pinhole"] = render(dots_scene(pinhole()), dtype=torch.float64).image
    images["orthographic"] = render(dots_scene(orthographic((SCREEN_SIZE[0] * P3, SCREEN_SIZE[1] * P3))),
                                    dtype=torch.float64).image
    return images


@pytest.mark.parametrize("alpha", ALPHAS)
def test_rendered_dots_land_where_equation_4_5_says(rendered, alpha):
    a = torch.tensor(CENTERS, dtype=torch.float64)
    den = alpha * (P3 - a[:, 2:]) + a[:, 2:]
    q = a[:, :2] / den  # q3 = 1
    predicted = q / torch.tensor([SCREEN_SIZE[0] / W, SCREEN_SIZE[1] / H]) + torch.tensor([(W - 1) / 2, (H - 1) / 2])
    # No other dot (image radius < 2 px) may reach into a dot's window.
    gaps = (predicted[:, None] - predicted[None]).abs().amax(-1) + 1e3 * torch.eye(len(CENTERS), dtype=torch.float64)
    assert float(gaps.min()) > WINDOW + 3, f"test set-up: dots too close to measure ({float(gaps.min())} px)"
    image = rendered[f"inverted_a{alpha}"]
    found = centroids(image, predicted)
    err = (found - predicted).abs().max()
    assert err < 0.25, f"α={alpha}: rendered dots at {found.tolist()}, eq. (4)(5) says {predicted.tolist()}"


def test_rendered_alpha0_equals_pinhole(rendered):
    d = (rendered["inverted_a0.0"] - rendered["pinhole"]).abs().max()
    assert d < 1e-6, f"α=0 image differs from the pinhole image by {float(d)}"
    assert float(rendered["pinhole"].sum()) > 10, "the pinhole image should show the dots"


def test_rendered_alpha1_equals_orthographic(rendered):
    d = (rendered["inverted_a1.0"] - rendered["orthographic"]).abs().max()
    assert d < 1e-6, f"α=1 image differs from the orthographic image by {float(d)}"


def test_rendered_pseudo_screen_dot_does_not_move(rendered):
    cam = inverted(0.0)
    predicted = cam.project(torch.tensor([CENTERS[ON_PSEUDO_SCREEN]], dtype=torch.float64))
    found = torch.cat([centroids(rendered[f"inverted_a{a}"], predicted) for a in ALPHAS])
    spread = (found - found.mean(0)).abs().max()
    assert spread < 0.25, f"the dot on the pseudo-screen moved with α: {found.tolist()}"
