"""The fast paths give the reference paths' hits and images.

- `Shape.intersect_soa` on (3, N) rows against each shape's `intersect_reference` (the former (N, 3) code):
  same hit/miss, t to float64 rounding, same face index (aux); `need_aux=False` the same t.
- `normal_rows` / `uv_rows` against `surface`.
- `renderer.tracing.direct.trace_direct` (direct light on rows) against the general integrator (fast_paths=False):
  the same image to float32 rounding, with ambient light, a background, a tilted lens and layers' object
  masks; scenes it cannot render exactly do not take it.
"""
import os
from dataclasses import replace

import pytest
import torch

from renderer import render
from renderer.tracing.direct import applies
from renderer.tracing.integrator import trace
from renderer.shapes import Box, Cone, Cylinder, Plane, Rectangle, Sphere
from renderer.scene.file import load_scene

SCENE = os.path.join(os.path.dirname(__file__), "..", "..", "benchmarks", "scenes", "speed_thin_lens.json")
SHAPES = {
    "sphere": lambda: Sphere((0.3, -0.2, 1.0), 1.3),
    "box aligned": lambda: Box((0.2, -0.1, 1.5), (2.0, 1.0, 1.5)),
    "box turned": lambda: Box((1.0, 2.0, 3.0), (2.0, 4.0, 6.0), (30.0, -20.0, 50.0)),
    "rectangle": lambda: Rectangle((0.0, 0.0, 2.0), (4.0, 2.0), (10.0, 20.0, 30.0)),
    "rectangle aligned": lambda: Rectangle((0.5, 0.0, 2.0), (3.0, 2.0)),
    "plane": lambda: Plane((0.0, 1.0, 0.0), (0.2, -1.0, 0.1)),
    "cylinder": lambda: Cylinder((1.0, 0.0, 1.0), (1.0, 2.0, 2.0), 0.7, 2.5),
    "cylinder along z": lambda: Cylinder((0.5, 0.5, 1.0), (0.0, 0.0, 1.0), 1.0, 2.0),
    "cone": lambda: Cone((0.0, 1.0, 1.0), (0.0, -1.0, 1.0), 1.2, 2.0),
}


def _rays(n, seed):
    """Rays from around the shapes (some inside them) towards them, plus axis-parallel ones."""
    g = torch.Generator().manual_seed(seed)
    o = torch.randn(n, 3, generator=g, dtype=torch.float64) * 2.0
    target = torch.randn(n, 3, generator=g, dtype=torch.float64) + torch.tensor([0.5, 0.5, 2.0], dtype=torch.float64)
    d = target - o
    axis = torch.eye(3, dtype=torch.float64).repeat(n // 30 + 1, 1)[: n // 10]
    d[: axis.shape[0]] = axis * torch.sign(torch.randn(axis.shape[0], 1, generator=g, dtype=torch.float64))
    return o, d / d.norm(dim=-1, keepdim=True)


@pytest.mark.parametrize("name", sorted(SHAPES))
def test_rows_intersection_matches_the_reference(name):
    shape = SHAPES[name]()
    o, d = _rays(3000, seed=len(name))
    t_ref, aux_ref = shape.intersect_reference(o, d, 1e-6)
    t, aux = shape.intersect_soa(o.T.contiguous(), d.T.contiguous(), 1e-6)
    t_only, _ = shape.intersect_soa(o.T.contiguous(), d.T.contiguous(), 1e-6, need_aux=False)
    hit_ref, hit = torch.isfinite(t_ref), torch.isfinite(t)
    assert 100 < int(hit_ref.sum()) < 2900, f"{name}: the rays should both hit and miss, {int(hit_ref.sum())} hits"
    assert torch.equal(hit, hit_ref), f"{name}: {int((hit != hit_ref).sum())} rays differ in hit/miss"
    assert torch.allclose(t[hit], t_ref[hit], rtol=1e-12, atol=1e-12), f"{name}: t differs"
    assert torch.equal(t_only, t), f"{name}: need_aux=False changes t"
    assert torch.equal(aux, aux_ref), f"{name}: {int((aux != aux_ref).sum())} face indices differ"
    # The public `intersect` is the rows code (bit for bit), whatever the layout it is given.
    t_pub, aux_pub = shape.intersect(o, d, 1e-6)
    assert torch.equal(t_pub, t) and torch.equal(aux_pub, aux), f"{name}: intersect is not intersect_soa"


@pytest.mark.parametrize("name", sorted(SHAPES))
def test_rows_normals_and_uv_match_surface(name):
    shape = SHAPES[name]()
    o, d = _rays(2000, seed=7)
    t, aux = shape.intersect(o, d, 1e-6)
    hit = torch.isfinite(t)
    p = o[hit] + t[hit, None] * d[hit]
    n_ref, uv_ref = shape.surface(p, aux[hit])
    n = shape.normal_rows(p.T.contiguous(), aux[hit])
    assert torch.allclose(n.T, n_ref, atol=1e-12), f"{name}: normal_rows differs from surface"
    assert torch.allclose(shape.normal_at(p, aux[hit]), n_ref, atol=1e-12), f"{name}: normal_at differs"
    if hasattr(shape, "uv_rows"):
        uv = shape.uv_rows(p.T.contiguous(), aux[hit])
        assert torch.allclose(uv.T, uv_ref, atol=1e-12), f"{name}: uv_rows differs from surface"


def test_checker_palette_index_is_evaluate_on_rows():
    """The checker's row form (what the fast paths gather colours with) picks the colour `evaluate` gives, on
    both sides of cell borders and of the origin (negative cells), in float32 and float64."""
    from renderer.scene.materials import CheckerTexture, ImageTexture

    tex = CheckerTexture(0.25, ((0.9, 0.1, 0.2), (0.1, 0.8, 0.3)))
    for dtype in (torch.float32, torch.float64):
        g = torch.Generator().manual_seed(5)
        uv = (torch.rand(4000, 2, generator=g, dtype=torch.float64) * 8 - 4).to(dtype)
        uv[:8] = torch.tensor([[0.0, 0.0], [-0.0, 0.25], [0.25, -0.25], [-1e-7, 0.1], [0.2499999, 0.0],
                               [-0.25, -0.25], [3.75, -3.75], [1e-9, -1e-9]], dtype=dtype)
        index = tex.palette_index(uv[:, 0].contiguous(), uv[:, 1].contiguous())
        assert index.dtype == torch.long and set(index.unique().tolist()) == {0, 1}, f"{dtype}: indices {index.unique()}"
        got = torch.tensor(tex.palette, dtype=dtype)[index]
        assert torch.equal(got, tex.evaluate(uv)), f"{dtype}: {int((got != tex.evaluate(uv)).any(-1).sum())} points differ"
    assert ImageTexture("x.png", (1.0, 1.0)).palette is None, "an image texture has no palette (shaded by evaluate)"


CASES = {
    "defaults": [],
    "tilted, ambient, background": ["camera.theta_F_deg=25", "image.background=[0.2,0.3,0.4]",
                                    'lights=[{"type":"point","position":[-1.5,-1.5,-1.0],"intensity":[70,70,70]},'
                                    '{"type":"point","position":[2.0,-1.0,1.0],"intensity":[20,10,5]},'
                                    '{"type":"ambient","intensity":[0.1,0.1,0.1]}]'],
    "float64, no culling": [],
    "cylinder and cone": ['objects.sphere_left.shape={"type":"cylinder","center":[-1.2,0.6,4],"axis":[0.2,-1,0.3],'
                          '"radius":0.4,"height":0.8}',
                          'objects.sphere_right.shape={"type":"cone","center":[1.2,0.6,4],"axis":[0,-1,-0.4],'
                          '"radius":0.4,"height":0.8}'],
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_direct_fast_path_renders_the_general_image(case):
    scene = load_scene(SCENE, ["image.width=48", "image.height=40", *CASES[case]])
    dtype = torch.float64 if "float64" in case else torch.float32
    culling = "no culling" not in case
    assert applies(scene, scene.options, scene.materials(torch.zeros(1))), "the speed scene should take the fast path"
    # Our own intersection code in both (the default `auto` may hand float32 rays to Embree).
    fast = render(scene, spp=4, dtype=dtype, culling=culling, intersector="torch").image
    scene.options = replace(scene.options, fast_paths=False)
    general = render(scene, spp=4, dtype=dtype, culling=culling, intersector="torch").image
    tol = 1e-12 if dtype == torch.float64 else 2e-6
    diff = float((fast - general).abs().max())
    assert diff <= tol * max(1.0, float(general.abs().max())), f"{case}: max |fast - general| = {diff:.3g}"
    assert float(general.mean()) > 0.05, "the image should not be black"


def test_direct_fast_path_honours_the_object_mask():
    """Layers trace their first ray against their own objects only: the mask gives the general result."""
    scene = load_scene(SCENE, ["image.width=16", "image.height=16"])
    scene.options = replace(scene.options, intersector="torch")  # our own shadow rays in both
    g = torch.Generator().manual_seed(3)
    o = torch.zeros(500, 3)
    d = torch.randn(500, 3, generator=g) * 0.3 + torch.tensor([0.0, 0.0, 1.0])
    d = d / d.norm(dim=-1, keepdim=True)
    mask = [i % 2 == 1 for i in range(len(scene.objects))]
    rad, found = trace(scene, o, d, mask)
    general = replace(scene.options, fast_paths=False)
    rad_ref, found_ref = trace(scene, o, d, mask, options=general)
    assert torch.equal(found, found_ref), "found differs under a mask"
    assert torch.allclose(rad, rad_ref, atol=1e-6), f"radiance differs by {float((rad - rad_ref).abs().max()):.3g}"
    assert 50 < int(found.sum()) < 480, f"the mask should hide some hits, found {int(found.sum())}"


@pytest.mark.parametrize("override", ["objects.sphere_top.material.reflect=0.5",
                                      "objects.cube_bottom.material.specular=0.5",
                                      'objects.sphere_top.shape={"type":"polyhedron","halfspaces":[[-1,0,0,0],'
                                      '[0,-1,0,0],[0,0,-1,-4],[1,1,1,6]]}'])
def test_scenes_the_fast_path_cannot_render_exactly_do_not_take_it(override):
    scene = load_scene(SCENE, ["image.width=8", "image.height=8", override])
    assert not applies(scene, scene.options, scene.materials(torch.zeros(1))), f"{override} should not apply"


def test_compiled_tracing_does_not_take_the_eager_fast_path():
    scene = load_scene(SCENE, ["image.width=8", "image.height=8"])
    table = scene.materials(torch.zeros(1))
    assert applies(scene, scene.options, table), "the speed scene takes the fast path eagerly"
    assert not applies(scene, replace(scene.options, compile=True), table), "compile=True keeps the general path"


def test_render_restores_torch_threads():
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        scene = load_scene(SCENE, ["image.width=8", "image.height=8"])
        render(scene, spp=1)
        assert torch.get_num_threads() == 2, "render() should restore the caller's thread count"
    finally:
        torch.set_num_threads(before)
