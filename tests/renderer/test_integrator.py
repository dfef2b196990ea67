"""The Whitted integrator against closed forms: slab shift, mirror image, total internal reflection, shadows
through transparent objects, and the pixel convention of a whole render."""
from __future__ import annotations

import math

import pytest
import torch

from renderer.tracing.integrator import trace
from renderer.tracing.render import render
from renderer.scene.file import load_scene
from renderer.core.transforms import euler_xyz_deg

F64 = torch.float64
AMBIENT_ONLY = [{"type": "ambient", "intensity": [1, 1, 1]}]
GLASS = {"color": [1, 1, 1], "transmit": 1.0, "ior": 1.5}
WHITE = {"color": [1, 1, 1]}


def scene_of(objects, lights=AMBIENT_ONLY, width=8, height=8, camera=None, max_depth=5):
    """A scene from object dicts; the camera only matters for tests that render."""
    return load_scene({
        "image": {"width": width, "height": height, "max_depth": max_depth, "sampler": "center"},
        "camera": camera or {"type": "pinhole", "fov_deg": 40},
        "lights": lights,
        "objects": objects,
    })


def parallel_rays(xs, ys, z0=-1.0):
    """Rays along +z from a grid of points (x, y, z0): (N, 3) origins and directions, float64."""
    X, Y = torch.meshgrid(xs, ys, indexing="xy")
    o = torch.stack([X, Y, torch.full_like(X, z0)], -1).reshape(-1, 3)
    d = torch.tensor([0.0, 0.0, 1.0], dtype=F64).expand_as(o).contiguous()
    return o, d


@pytest.mark.parametrize("theta_deg", [25.0, 45.0])
def test_glass_slab_shifts_parallel_rays_by_the_textbook_amount(theta_deg):
    """A slab of thickness t and index n tilted by θ displaces a ray by t·sin(θ − θr)/cos θr, sin θ = n sin θr.

    Parallel rays pass the slab, then see a small white sphere; the sphere's image (the rays that reach it)
    moves by that displacement against the slab normal's sideways component, and keeps its area.
    """
    t, n = 1.0, 1.5
    sphere = {"name": "ball", "shape": {"type": "sphere", "center": [0, 0, 4], "radius": 0.05}, "material": WHITE}
    slab = {"name": "slab", "shape": {"type": "box", "center": [0, 0, 1.5], "size": [4, 4, t],
                                      "rotation_deg": [0, theta_deg, 0]}, "material": GLASS}
    step = 0.002
    xs = torch.arange(-0.45, 0.45 + step / 2, step, dtype=F64)
    ys = torch.arange(-0.08, 0.08 + step / 2, step, dtype=F64)
    o, d = parallel_rays(xs, ys)

    def image_of(objects):
        radiance, _ = trace(scene_of(objects), o, d)
        seen = radiance[:, 0] > 0.5
        return o[seen, :2].mean(0), int(seen.sum())

    (x0, y0), area0 = image_of([sphere])
    (x1, y1), area1 = image_of([sphere, slab])
    theta = math.radians(theta_deg)
    theta_r = math.asin(math.sin(theta) / n)
    shift = t * math.sin(theta - theta_r) / math.cos(theta_r)
    normal = euler_xyz_deg([0, theta_deg, 0])[:, 2]  # the slab normal; its x part says which way rays bend
    expected_x = -shift * math.copysign(1.0, float(normal[0]))
    assert abs(float(x0)) < 2e-4, f"without the slab the image is centred, got x = {float(x0):.5f}"
    assert abs(float(x1 - x0) - expected_x) < 5e-4, \
        f"slab shift {float(x1 - x0):.5f}, textbook t·sin(θ−θr)/cos θr = {expected_x:.5f}"
    assert abs(float(y1 - y0)) < 2e-4, "no shift across the tilt axis"
    assert abs(area1 - area0) <= 0.03 * area0, f"parallel rays stay parallel: image area {area1} vs {area0}"


def test_plane_mirror_shows_the_sphere_where_its_mirror_image_projects():
    """A sphere behind the camera is seen only in a mirror at z = 6, at the projection of its reflection."""
    center = [0.6, -0.4, -1.0]
    mirrored = [center[0], center[1], 2 * 6.0 - center[2]]
    scene = scene_of(
        [{"name": "mirror", "shape": {"type": "plane", "point": [0, 0, 6], "normal": [0, 0, -1]},
          "material": {"reflect": 1.0}},
         {"name": "ball", "shape": {"type": "sphere", "center": center, "radius": 0.3}, "material": WHITE}],
        width=96, height=72, camera={"type": "pinhole", "fov_deg": 12})
    image = render(scene, spp=1, sampler="center", dtype=F64).image[..., 0]
    rows, cols = torch.nonzero(image > 0.5, as_tuple=True)
    assert rows.numel() > 100, "the reflection covers a patch of pixels"
    centroid = torch.stack([cols.to(F64).mean(), rows.to(F64).mean()])
    expected = scene.camera.project(torch.tensor(mirrored, dtype=F64))
    err = float(torch.linalg.vector_norm(centroid - expected))
    assert err < 0.2, f"reflection centroid {centroid.tolist()} vs mirrored sphere at {expected.tolist()} px"


def test_total_internal_reflection_past_the_critical_angle():
    """Rays start inside glass (n = 1.5, critical angle 41.81°) and meet its top face at angle φ.

    Below the critical angle they leave through the top and see the red detector above; past it they are
    reflected entirely, the steep one (60°) then leaving through the side face towards the green detector.
    """
    critical = math.degrees(math.asin(1 / 1.5))
    scene = scene_of([
        {"name": "glass", "shape": {"type": "box", "center": [0, 0, 0.5], "size": [2, 20, 1]}, "material": GLASS},
        {"name": "above", "shape": {"type": "plane", "point": [0, 0, 1.5], "normal": [0, 0, -1]},
         "material": {"color": [1, 0, 0]}},
        {"name": "side", "shape": {"type": "plane", "point": [8, 0, 0], "normal": [-1, 0, 0]},
         "material": {"color": [0, 1, 0]}},
    ], max_depth=8)
    phis = torch.tensor([30.0, critical - 0.3, critical + 0.3, 60.0], dtype=F64)
    d = torch.stack([torch.sin(torch.deg2rad(phis)), torch.zeros_like(phis), torch.cos(torch.deg2rad(phis))], -1)
    o = torch.tensor([0.0, 0.0, 0.5], dtype=F64).expand_as(d).contiguous()
    radiance, _ = trace(scene, o, d)
    red, green = radiance[:, 0], radiance[:, 1]
    assert bool((red[:2] > 0.99).all()), f"below {critical:.2f}° the rays leave through the top: red {red[:2]}"
    assert bool((red[2:] < 1e-6).all()), f"past the critical angle nothing leaves the top: red {red[2:]}"
    assert float(green[3]) > 0.99, f"the totally reflected 60° ray keeps all its energy, got {float(green[3])}"


def test_transparent_object_casts_a_lighter_tinted_shadow():
    """Shadow rays through a transparent blocker carry transmit · colour; an opaque one blocks everything."""
    floor = {"name": "floor", "shape": {"type": "plane", "point": [0, 0, 5], "normal": [0, 0, -1]},
             "material": WHITE}
    light = [{"type": "point", "position": [-10, 0, 0], "intensity": [100, 100, 100]}]

    def blocker(material):
        # Halfway between the light and the floor point (0, 0, 5), away from the viewing ray x = 0.
        return [{"name": "blocker", "shape": {"type": "sphere", "center": [-5, 0, 2.5], "radius": 0.5},
                 "material": material}]

    o = torch.zeros(1, 3, dtype=F64)
    d = torch.tensor([[0.0, 0.0, 1.0]], dtype=F64)
    lit = trace(scene_of([floor], light), o, d)[0][0]
    opaque = trace(scene_of([floor] + blocker({}), light), o, d)[0][0]
    tint = [1.0, 0.5, 0.25]
    clear = trace(scene_of([floor] + blocker({"color": tint, "transmit": 0.6, "ior": 1.3}), light), o, d)[0][0]
    assert float(lit.min()) > 0.05, f"the floor point is lit without a blocker: {lit.tolist()}"
    assert float(opaque.max()) < 1e-9, f"an opaque blocker casts a full shadow: {opaque.tolist()}"
    assert bool((clear > opaque).all() & (clear < lit).all()), "the transparent blocker's shadow is lighter"
    expected = lit * 0.6 * torch.tensor(tint, dtype=F64)
    # rtol: the shadow-ray offset scales with the scene size, which the blocker changes.
    assert torch.allclose(clear, expected, rtol=1e-5), f"shadow {clear.tolist()} vs transmit·colour·lit {expected}"


def test_pixel_convention_on_an_odd_non_square_image():
    """On a 17×11 render, pixel (0, 0) is the centre of the top-left pixel and ((W−1)/2, (H−1)/2) the axis.

    Screen 1.7 × 1.1 at distance 1: pixel pitch 0.1. Tiny spheres at distance 10 along the rays through
    pixel centres (0, 0), (8, 5) and (16, 10) each light exactly one pixel: image[row, col], y down.
    """
    W, H = 17, 11
    targets = {(0, 0): [0, 1, 0], (8, 5): [1, 0, 0], (16, 10): [0, 0, 1]}
    objects = []
    for (x, y), color in targets.items():
        center = [(x - (W - 1) / 2) * 0.1 * 10, (y - (H - 1) / 2) * 0.1 * 10, 10.0]
        objects.append({"name": f"px{x}_{y}", "shape": {"type": "sphere", "center": center, "radius": 0.2},
                        "material": {"color": color}})
    scene = scene_of(objects, width=W, height=H,
                     camera={"type": "pinhole", "screen_distance": 1.0, "screen_size": [1.7, 1.1]})
    image = render(scene, spp=1, sampler="center", dtype=F64).image
    assert tuple(image.shape) == (H, W, 3), f"image is (H, W, 3), got {tuple(image.shape)}"
    expected = torch.zeros(H, W, 3, dtype=F64)
    for (x, y), color in targets.items():
        expected[y, x] = torch.tensor(color, dtype=F64)
    lit = [(int(r), int(c)) for r, c in torch.nonzero(image.amax(-1) > 0.5).tolist()]
    assert sorted(lit) == [(0, 0), (5, 8), (10, 16)], f"lit pixels (row, col): {lit}"
    assert torch.allclose(image, expected, atol=1e-9), "each sphere lights its own pixel in its own colour"
    for obj, (x, y) in zip(objects, targets):
        uv = scene.camera.project(torch.tensor(obj["shape"]["center"], dtype=F64))
        assert torch.allclose(uv, torch.tensor([x, y], dtype=F64), atol=1e-9), f"project gives {uv.tolist()}"
