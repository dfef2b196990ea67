"""Gradients with respect to camera and lens parameters, checked against finite differences (float64).

The thin lens's w, U, d, θF and the pose may be tensors; gradients then reach them through every ray and,
on a scene without visibility edges in view (a textured, tilted plane under a point light), through the
tracer's intersection, bilinear texture lookup and shading. Visibility edges (silhouettes, shadow
boundaries) have no gradient: see docs/conventions.md.
"""
from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from renderer import CameraTransform, load_scene, write_image
from renderer.cameras import Lens
from renderer.cameras.thin_lens import ThinLensCamera
from renderer.tracing.integrator import trace

W_PX, H_PX, PITCH = 9, 7, 0.5  # a tiny sensor: 4.5 x 3.5 scene units at distance w
SCENES = Path(__file__).resolve().parents[2] / "renderer" / "scenes"


def _skew(v):
    z = torch.zeros_like(v[0])
    return torch.stack([torch.stack([z, -v[2], v[1]]), torch.stack([v[2], z, -v[0]]),
                        torch.stack([-v[1], v[0], z])])


def _camera(w, U, d, theta_F, rvec, position):
    R = torch.linalg.matrix_exp(_skew(rvec))
    return ThinLensCamera(CameraTransform(R, position), Lens(w, U, d, theta_F), (W_PX, H_PX),
                          (W_PX * PITCH, H_PX * PITCH))


def _samples(n=12, seed=3):
    g = torch.Generator().manual_seed(seed)
    uv = torch.rand(n, 2, generator=g, dtype=torch.float64) * torch.tensor([W_PX - 1.0, H_PX - 1.0],
                                                                              dtype=torch.float64)
    lens = 0.15 + 0.7 * torch.rand(n, 2, generator=g, dtype=torch.float64)  # off the lens centre
    return uv, lens


def _params():
    vals = dict(w=50.0, U=600.0, d=20.0, theta_F=math.radians(30.0))
    ps = [torch.tensor(v, dtype=torch.float64, requires_grad=True) for v in vals.values()]
    ps.append(torch.tensor([0.02, -0.01, 0.03], dtype=torch.float64, requires_grad=True))
    ps.append(torch.tensor([5.0, -3.0, 0.0], dtype=torch.float64, requires_grad=True))
    return ps


def test_thin_lens_rays_gradcheck():
    uv, lens = _samples()

    def rays(*p):
        r = _camera(*p).generate_rays(uv, lens)
        return r.origin, r.direction

    assert torch.autograd.gradcheck(rays, tuple(_params()), eps=1e-6, atol=1e-7), "ray gradients"


def test_tilt_follows_a_replaced_focus_distance():
    """θL is derived from (θF, w, U) on every call: replacing U by a tensor moves θL (no stale float)."""
    cam = _camera(*[p.detach() for p in _params()])
    before = float(cam.lens.theta_L)
    cam.lens = cam.lens.with_(U=torch.tensor(300.0, dtype=torch.float64))
    expected = math.atan(50.0 * math.tan(math.radians(30.0)) / (300.0 + 50.0))
    assert float(cam.lens.theta_L) == pytest.approx(expected, abs=1e-12), "tan θL = w tan θF / (U + w)"
    assert abs(float(cam.lens.theta_L) - before) > 1e-3, "θL moved with U"


@pytest.fixture(scope="module")
def textured_plane(tmp_path_factory):
    """A tilted rectangle (smooth random image texture) filling the view, lit by a point light."""
    folder = tmp_path_factory.mktemp("tex")
    rng = np.random.default_rng(0)
    tex = rng.uniform(0.2, 0.9, (6, 6, 3)).astype(np.float32)
    write_image(str(folder / "tex.exr"), tex)
    cfg = {
        "image": {"width": W_PX, "height": H_PX},
        "camera": {"type": "pinhole", "screen_distance": 1.0, "screen_size": [1.0, 1.0]},
        "lights": [{"type": "point", "position": [80.0, -120.0, 100.0], "intensity": [4e4, 4e4, 4e4]}],
        "objects": [{"name": "board",
                     "shape": {"type": "rectangle", "center": [0.0, 0.0, 600.0], "size": [900.0, 900.0],
                               "rotation_deg": [25.0, 10.0, 0.0]},
                     "material": {"texture": {"type": "image", "file": "tex.exr", "size": [150.0, 150.0]}}}],
    }
    return load_scene(cfg, base_dir=str(folder))


def test_tracer_gradcheck_on_a_textured_plane(textured_plane):
    uv, lens = _samples(n=10, seed=5)

    def radiance(*p):
        r = _camera(*p).generate_rays(uv, lens)
        rgb, found = trace(textured_plane, r.origin, r.direction)
        assert bool(found.all()), "every ray hits the plane (no visibility edge in view)"
        return rgb

    params = tuple(_params())
    out = radiance(*params)
    assert float(out.detach().min()) > 0, "lit and textured: no black sample"
    assert torch.autograd.gradcheck(radiance, params, eps=1e-6, atol=1e-7, rtol=1e-4), \
        "tracer gradients with respect to w, U, d, θF, rotation and position"
    # Each parameter really moves the image (a zero gradient would pass gradcheck trivially).
    grads = torch.autograd.grad(out.sum(), params)
    for name, g in zip(("w", "U", "d", "theta_F", "rvec", "position"), grads):
        assert float(g.abs().max()) > 1e-9, f"d radiance / d {name} is not zero"


def _box_halfspaces(center, half):
    return [[*(s * e for e in axis), s * c + h] for axis, c, h in zip(np.eye(3).tolist(), center, half)
            for s in (1.0, -1.0)]


def _every_shape_scene():
    """fig6 (sphere, cone, cylinder, boxes, a rectangle; mirror and glass) seen wider, plus a mesh, a polyhedron,
    a CSG difference and a plane around it, with background left above (rays that miss everything)."""
    cfg = json.loads((SCENES / "fig6.json").read_text())
    cfg["camera"]["screen_size"] = [2.4, 2.4]
    tetra_normals, p = [[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], np.array([3.8, 0.0, 4.5])
    cfg["objects"] += [
        {"name": "mesh", "shape": {"type": "mesh", "file": "icosahedron.obj", "center": [-3.8, 0.0, 4.5],
                                   "size": [1.2, 1.2, 1.2]}, "material": {"color": [0.7, 0.5, 0.3]}},
        {"name": "tetra", "shape": {"type": "polyhedron",
                                    "halfspaces": [[*n, 0.6 + float(np.dot(n, p))] for n in tetra_normals]},
         "material": {"color": [0.3, 0.6, 0.6], "reflect": 0.5}},
        {"name": "csg", "shape": {"type": "csg", "op": "difference", "children": [
            {"type": "polyhedron", "halfspaces": _box_halfspaces([0.0, -3.8, 4.5], [0.6, 0.6, 0.6])},
            {"type": "polyhedron", "halfspaces": _box_halfspaces([0.0, -3.8, 4.5], [0.3, 0.3, 1.0])}]},
         "material": {"color": [0.9, 0.4, 0.6]}},
        {"name": "floor", "shape": {"type": "plane", "point": [0, 4.5, 0], "normal": [0, -1, 0]},
         "material": {"color": [0.5, 0.5, 0.5]}},
    ]
    return load_scene(cfg, base_dir=str(SCENES))


@pytest.mark.parametrize("fast_paths", [True, False], ids=["fast-paths", "general"])
def test_ray_gradients_are_finite_and_right_on_every_shape_kind(fast_paths):
    """d radiance / d (origin, direction) over random rays: misses, grazing rays and hits of every shape kind.

    A masked miss gets a zero gradient, and √ at a negative or zero discriminant (sphere, cylinder, cone,
    refraction's total internal reflection) has an infinite or NaN slope: 0·∞ = NaN reached every ray's
    gradient through the sum, so any camera or pose gradient on such a scene was NaN (3,895 of 4,000 rays on
    fig6 before `shapes.base.root`). Finite differences check the values on a subset (random rays are far from
    silhouettes and shadow edges at eps = 1e-6).
    """
    scene = _every_shape_scene()
    scene.options = replace(scene.options, fast_paths=fast_paths, intersector="torch")
    cam = scene.camera
    g = torch.Generator().manual_seed(11)
    n = 3000
    uv = torch.rand(n, 2, generator=g) * torch.tensor([cam.width - 1.0, cam.height - 1.0])
    rays = cam.generate_rays(uv, torch.rand(n, 2, generator=g))
    o = rays.origin.detach().double().requires_grad_(True)
    d = rays.direction.detach().double().requires_grad_(True)
    rgb, found = trace(scene, o, d)
    kinds = {type(scene.objects[int(k)].shape).__name__ for k in scene.intersect(o.detach(), d.detach()).object_id[found]}
    assert {"Sphere", "Cylinder", "Cone", "Box", "Mesh", "Polyhedron", "CSG", "Plane"} <= kinds, kinds
    assert bool((~found).any()), "some rays miss everything"
    go, gd = torch.autograd.grad(rgb.sum(), (o, d))
    assert bool(torch.isfinite(go).all()) and bool(torch.isfinite(gd).all()), \
        f"NaN/inf gradients on {int((~torch.isfinite(go).all(1)).sum())} of {n} rays"
    assert float(gd.abs().sum(1).gt(0).float().mean()) > 0.5, "most rays' radiance moves with the direction"

    sub = torch.arange(0, n, n // 40)

    def radiance(o_s, d_s):
        return trace(scene, o_s, d_s / d_s.norm(dim=1, keepdim=True))[0]

    analytical, numerical = _ray_jacobians(radiance, o.detach()[sub], d.detach()[sub], eps=1e-6)
    # gradcheck's test, on every entry of the (120, 240) Jacobians (a ray's gradient reaching another ray's
    # inputs included): |analytical - numerical| <= atol + rtol |numerical|.
    off = (analytical - numerical).abs() - (1e-6 + 1e-4 * numerical.abs())
    assert bool((off <= 0).all()), (f"ray gradients against finite differences: {int((off > 0).sum())} of "
                                    f"{off.numel()} entries off, worst by {float(off.max()):.3g}")


def _ray_jacobians(radiance, o, d, eps):
    """(analytical, numerical) Jacobians, each (3n, 6n), of radiance(o, d) -> (n, 3) with respect to the
    inputs (o, d), (n, 3) each, flattened in that order: formed as torch.autograd.gradcheck forms them (central
    differences of each input element by eps; one vector-Jacobian product per output element), but each set
    of evaluations traced at once, as copies of the n rays side by side in one batch. That the tracer traces
    each ray alone (the batch's other rays change nothing) is checked here: an unchanged copy in the batch must
    give the n rays' own radiance. On this test's rays both Jacobians equal gradcheck's bit for bit; gradcheck
    traced the n rays 12n + 6n times one batch after another (30 CPU s for n = 40; this takes under one)."""
    n = o.shape[0]
    x = torch.cat([o.reshape(-1), d.reshape(-1)])
    m, k = x.numel(), 3 * n

    def batched(rows):  # (c, 6n) -> (c, 3n): c copies of the n rays in one trace
        c = rows.shape[0]
        return radiance(rows[:, :k].reshape(c * n, 3), rows[:, k:].reshape(c * n, 3)).reshape(c, k)

    with torch.no_grad():
        step = torch.zeros(m, m, dtype=x.dtype).fill_diagonal_(eps)
        out = batched(torch.cat([x + step, x - step, x[None]]))
        alone = radiance(o, d).reshape(k)
        assert torch.allclose(out[-1], alone, rtol=1e-12, atol=1e-12), \
            f"a ray's radiance changed with the rest of its batch by {float((out[-1] - alone).abs().max()):.3g}"
        numerical = ((out[:m] - out[m:2 * m]) / (2 * eps)).T
    rows = x.repeat(k, 1).requires_grad_(True)
    picked = batched(rows).diagonal()  # output element j of copy j
    analytical = torch.autograd.grad(picked.sum(), rows)[0]  # row j: output j's gradient, from copy j alone
    return analytical, numerical
