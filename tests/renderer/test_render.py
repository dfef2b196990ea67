"""The render loop and the scene's fast paths: every optimisation against a straightforward reference.

Culling (ray packets against bounding spheres, convex objects skipped by their own shadow rays), the chunk
size, the packet size and torch.compile change only how rays are traced, never the image: each is compared
with the plain path (every ray against every object, one chunk, eager). Plus closed forms for the shading
and the sampler's two evaluation orders.
"""
from __future__ import annotations

import math
import warnings

import pytest
import torch

import renderer.scene.model as scene_module
from renderer import render
from renderer.tracing.integrator import trace
from renderer.tracing.render import tile_order
from renderer.tracing.sampling import SAMPLERS, Sampler
from renderer.scene.model import TraceOptions
from renderer.scene.file import load_scene

PLAIN = TraceOptions(culling=False)


def _object(name, shape, **material):
    return {"name": name, "shape": shape, "material": material}


def every_shape_scene(width=48, height=36, spp=2, max_depth=2, **image):
    """Every analytic shape type, opaque, mirror and glass materials, a checker, a point and an ambient light."""
    checker = {"type": "checker", "size": 0.5, "colors": [[0.9, 0.9, 0.8], [0.2, 0.3, 0.6]]}
    cube = [[1, 0, 0, 1.3], [-1, 0, 0, -0.7], [0, 1, 0, 0.3], [0, -1, 0, 0.3], [0, 0, 1, 4.3], [0, 0, -1, -3.7]]
    objects = [
        _object("floor", {"type": "plane", "point": [0, 0.8, 0], "normal": [0, -1, 0]}, texture=checker),
        _object("wall", {"type": "rectangle", "center": [0, 0, 6], "size": [8, 5]}, color=[0.7, 0.7, 0.9]),
        _object("ball", {"type": "sphere", "center": [-1.2, 0.2, 4], "radius": 0.5}, color=[0.9, 0.3, 0.2],
                specular=0.4, shininess=30),
        _object("box", {"type": "box", "center": [0, 0.3, 3.5], "size": [0.6, 0.6, 0.6],
                        "rotation_deg": [20, 30, 0]}, color=[0.3, 0.8, 0.4], reflect=0.3),
        _object("glass", {"type": "box", "center": [0.2, -0.5, 2.5], "size": [0.5, 0.5, 0.5]},
                color=[0.8, 0.9, 1.0], transmit=0.7, ior=1.4),
        _object("can", {"type": "cylinder", "center": [1.2, 0.8, 4.5], "axis": [0, -1, 0], "radius": 0.3,
                        "height": 0.9}, color=[0.9, 0.8, 0.3]),
        _object("cone", {"type": "cone", "center": [-0.2, 0.8, 5], "axis": [0, -1, 0], "radius": 0.4,
                         "height": 0.8}, color=[0.6, 0.4, 0.9]),
        _object("cube", {"type": "polyhedron", "halfspaces": cube}, color=[0.5, 0.5, 0.5]),
    ]
    cfg = {
        "image": {"width": width, "height": height, "spp": spp, "max_depth": max_depth,
                  "background": [0.1, 0.1, 0.2], **image},
        "camera": {"type": "pinhole", "fov_deg": 60, "position": [0, -0.3, 0], "look_at": [0, 0, 4]},
        "lights": [{"type": "point", "position": [-2, -3, 1], "intensity": [30, 30, 30]},
                   {"type": "ambient", "intensity": [0.05, 0.05, 0.05]}],
        "objects": objects,
    }
    return load_scene(cfg)


def assert_same_image(actual, expected, what, atol=1e-5):
    diff = (actual - expected).abs()
    assert torch.allclose(actual, expected, rtol=1e-5, atol=atol), (
        f"{what}: max |diff| {float(diff.max()):.3g} at {divmod(int(diff.amax(-1).argmax()), actual.shape[1])}")


@pytest.fixture(scope="module")
def scene():
    return every_shape_scene()


@pytest.fixture(scope="module")
def reference(scene):
    """The plain path: no culling, the whole image in one chunk, eager."""
    return render(scene, culling=False, chunk_rays=1 << 30)


def test_culling_gives_the_reference_image(scene, reference):
    result = render(scene, culling=True)
    assert_same_image(result.image, reference.image, "culling on vs off")
    assert torch.equal(result.coverage, reference.coverage), "coverage changed with culling"


@pytest.mark.parametrize("chunk_rays", [1, 100, 2048])
def test_chunked_rendering_equals_one_shot(scene, reference, chunk_rays):
    result = render(scene, culling=False, chunk_rays=chunk_rays)
    assert_same_image(result.image, reference.image, f"chunk_rays={chunk_rays} vs one chunk")


@pytest.mark.parametrize("packet_size", [1, 8, 256])
def test_packet_size_does_not_change_the_image(scene, reference, packet_size):
    scene_p = every_shape_scene()
    scene_p.options = TraceOptions(packet_size=packet_size)
    assert_same_image(render(scene_p).image, reference.image, f"packet_size={packet_size}")


def _random_rays(n, seed, spread=0.6):
    g = torch.Generator().manual_seed(seed)
    o = torch.randn(n, 3, generator=g) * spread + torch.tensor([0.0, -0.3, 0.0])
    target = torch.randn(n, 3, generator=g) * 1.5 + torch.tensor([0.0, 0.0, 4.0])
    d = target - o
    return o, d / d.norm(dim=-1, keepdim=True)


@pytest.mark.parametrize("n", [1, 63, 1000])
def test_intersect_matches_every_shape_tested(scene, n):
    """Incoherent rays (culling gains nothing, so bounds are loose) and sizes off the packet size."""
    o, d = _random_rays(n, seed=n)
    hit = scene.intersect(o, d)
    plain = scene.intersect(o, d, options=PLAIN)
    best = torch.full((n,), math.inf)
    for obj in scene.objects:
        best = torch.minimum(best, obj.shape.intersect(o, d, scene.ray_epsilon)[0])
    assert torch.equal(hit.t, best), "nearest hit differs from the minimum over shapes"
    assert torch.equal(hit.object_id, plain.object_id) and torch.equal(hit.aux, plain.aux), "object/aux differ"


def test_intersect_respects_the_object_mask(scene):
    o, d = _random_rays(500, seed=1)
    mask = [i % 2 == 0 for i in range(len(scene.objects))]
    hit = scene.intersect(o, d, mask)
    assert all(mask[k] for k in hit.object_id[hit.found].tolist()), "a masked-out object was hit"
    assert torch.equal(hit.t, scene.intersect(o, d, mask, options=PLAIN).t), "mask changes culled result"


def test_transmittance_matches_every_shape_tested(scene):
    o, d = _random_rays(777, seed=3)
    t_max = torch.rand(777, generator=torch.Generator().manual_seed(4)) * 6
    expected = torch.ones(777, 3)
    table = scene.materials(o)
    for k, obj in enumerate(scene.objects):
        t, _ = obj.shape.intersect(o, d, scene.ray_epsilon)
        expected = torch.where((t < t_max)[:, None], expected * table.shadow_transmittance[k], expected)
    trans = scene.transmittance(o, d, t_max)
    assert trans.shape == (777, 3), f"transmittance shape {tuple(trans.shape)}"
    assert torch.allclose(trans, expected), "transmittance differs from the product over shapes"
    assert torch.allclose(scene.transmittance(o, d, t_max, options=PLAIN), expected), "plain path differs"


@pytest.mark.parametrize("intersector", ["torch", "auto"])
def test_shadow_rays_leaving_a_closed_box_from_inside_still_meet_it(intersector):
    """The convex self-skip applies only to points reached from outside: a camera inside a closed box lit
    from outside sees only the ambient term (ours, and the default, Embree where it runs)."""
    cfg = {
        "image": {"width": 16, "height": 12, "spp": 1, "max_depth": 0, "sampler": "center"},
        "camera": {"type": "pinhole", "fov_deg": 90},
        "lights": [{"type": "point", "position": [0, 0, 5], "intensity": [100, 100, 100]},
                   {"type": "ambient", "intensity": [0.25, 0.25, 0.25]}],
        "objects": [_object("room", {"type": "box", "center": [0, 0, 0], "size": [2, 2, 2]}, color=[0.8, 0.8, 0.8])],
    }
    image = render(load_scene(cfg), intersector=intersector).image
    assert torch.allclose(image, torch.full_like(image, 0.25 * 0.8)), (
        f"{intersector}: inside of the box is lit: max {float(image.max())}, expected ambient 0.2 everywhere")


def test_lambert_closed_form():
    """Centre pixel on a sphere facing the light: radiance = kd·albedo/π · I·cos/r², cos = 1, with r the
    distance from the shadow ray's origin (the hit point moved off the surface by the ray epsilon)."""
    kd, albedo, intensity = 0.7, (0.5, 0.6, 0.8), 40.0
    cfg = {
        "image": {"width": 9, "height": 7, "spp": 1, "max_depth": 0, "sampler": "center"},
        "camera": {"type": "pinhole", "fov_deg": 10},
        "lights": [{"type": "point", "position": [0, 0, 0], "intensity": [intensity] * 3}],
        "objects": [_object("ball", {"type": "sphere", "center": [0, 0, 5], "radius": 1}, color=list(albedo),
                            diffuse=kd)],
    }
    sc = load_scene(cfg)
    image = render(sc, dtype=torch.float64).image
    r = 4.0 - sc.ray_epsilon
    expected = torch.tensor(albedo, dtype=torch.float64) * kd / math.pi * intensity / r**2
    assert torch.allclose(image[3, 4], expected, rtol=1e-9), f"centre pixel {image[3, 4].tolist()} vs {expected.tolist()}"


def test_float32_matches_float64(scene):
    img32 = render(scene, sampler="center", spp=1).image.double()
    img64 = render(scene, sampler="center", spp=1, dtype=torch.float64).image
    close = ((img32 - img64).abs().amax(-1) < 1e-3).double().mean()
    assert close > 0.99, f"only {float(close):.3f} of pixels agree between float32 and float64"


def test_trace_accepts_any_batch_size(scene):
    o, d = _random_rays(37, seed=5)
    rad, found = trace(scene, o, d)
    rad_plain, found_plain = trace(scene, o, d, options=PLAIN)
    assert torch.allclose(rad, rad_plain, atol=1e-6) and torch.equal(found, found_plain), "trace differs"


@pytest.mark.parametrize("name", SAMPLERS)
@pytest.mark.parametrize("spp", [1, 4, 6])
def test_sampler_evaluation_orders_agree(name, spp):
    s = Sampler(name, spp, seed=3)
    pixel = torch.tensor([0, 5, 17, 123456])
    per_pixel = s.pixel_samples(pixel)
    flat = s.samples(pixel.repeat_interleave(spp), torch.arange(spp).repeat(pixel.shape[0]))
    columns = torch.stack(s.pixel_columns(pixel), -1)
    assert torch.equal(per_pixel.reshape(-1, 4), flat), f"{name}: pixel_samples != samples"
    assert torch.equal(columns, per_pixel), f"{name}: pixel_columns != pixel_samples"


def test_tile_order_is_a_permutation_on_an_odd_image():
    order = tile_order(13, 7, tile=4)
    assert torch.equal(order.sort().values, torch.arange(13 * 7)), "tile order is not a permutation"
    assert order[:4].tolist() == [0, 1, 2, 3] and order[4] == 13, f"first tile starts {order[:6].tolist()}"


def test_compile_falls_back_to_eager_with_a_warning(monkeypatch):
    def broken(*args, **kwargs):
        raise RuntimeError("no compiler")

    monkeypatch.setattr(torch, "compile", broken)
    monkeypatch.setattr(scene_module, "_COMPILED", {})

    def double(x):
        return 2 * x

    x = torch.arange(5.0)
    with pytest.warns(RuntimeWarning, match="no compiler"):
        assert torch.equal(scene_module.compiled_call(True, double, x), 2 * x), "fallback result wrong"


@pytest.mark.slow
def test_worker_processes_give_the_same_image(scene, reference):
    result = render(scene, chunk_rays=1000, workers=2)
    assert_same_image(result.image, reference.image, "2 worker processes vs one process")
    assert torch.equal(result.coverage, reference.coverage), "coverage changed with workers"


def test_shape_parameters_do_not_break_a_compiled_graph():
    """Under torch.compile a shape's parameters are read into the graph as they are: `Shape._param`'s cache
    check (a tensor's version counter, data-dependent to the compiler) broke the graph at each call (32 of the
    45 frames compiled for the two-shape scene below; 14 without), so the first compilation took longer."""
    box = every_shape_scene().objects[3].shape  # rotated: its local frame and half sizes are parameters
    o, d = _random_rays(64, seed=3)
    o, d = o.T.contiguous(), d.T.contiguous()
    eager = box.intersect_soa(o, d, 1e-4, need_aux=False)[0]  # first, as a render would: the cache is filled
    compiled = torch.compile(lambda o, d: box.intersect_soa(o, d, 1e-4, need_aux=False)[0], fullgraph=True,
                             backend="eager")  # fullgraph: a graph break raises
    assert torch.equal(compiled(o, d), eager), "same hits as eager"


@pytest.mark.slow
@pytest.mark.xdist_group("inductor")  # with test_fused.py's compiling tests: Inductor's set-up once a run
def test_compiled_tracing_gives_the_eager_image():
    """torch.compile (fused per-shape kernels) against eager on two shape types: float rounding only
    (a ray grazing a silhouette may flip, so a few pixels may differ)."""
    cfg = {
        "image": {"width": 40, "height": 30, "spp": 2, "max_depth": 0},
        "camera": {"type": "pinhole", "fov_deg": 50},
        "lights": [{"type": "point", "position": [-2, -3, 0], "intensity": [30, 30, 30]}],
        "objects": [_object("wall", {"type": "rectangle", "center": [0, 0, 6], "size": [8, 6]}),
                    _object("ball", {"type": "sphere", "center": [0.3, 0, 4], "radius": 0.8}, color=[0.9, 0.4, 0.2])],
    }
    sc = load_scene(cfg)
    eager = render(sc, compile=False, intersector="torch").image  # our own intersection code in both
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # a fallback to eager would hide what is tested
        compiled = render(sc, compile=True, intersector="torch").image
    off = ((compiled - eager).abs().amax(-1) > 1e-4).double().mean()
    assert off < 0.01, f"{float(off):.3f} of pixels differ between compiled and eager"
    assert torch.allclose(compiled.mean(), eager.mean(), rtol=1e-3), "mean brightness differs"
