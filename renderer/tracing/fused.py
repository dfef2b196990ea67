"""Opt-in compiled direct-light path for Embree renders: `render(..., intersector="mitsuba", compile=True)`.

The eager fast path (`renderer.tracing.direct`) runs a few hundred small torch operations per batch of rays, each a
pass over memory. Here the per-ray work between the two Embree calls is written as functions of separate
1-D component tensors (x, y, z each (N,)), so that torch.compile (Inductor) emits one fused loop over the
rays per stage; compiled on (3, N) rows instead, Inductor recomputed the per-ray values once per row and
gained nothing. A batch of pixels is traced as three compiled stages and two Embree calls:

    samples -> camera rays (stage 1) -> Embree nearest -> shading (stage 2) -> Embree shadow rays
            -> radiance and pixel means (stage 3)

Batches (`CHUNK_RAYS` rays by default) are padded to a power of two of pixels (the last pixel repeated), so
a render compiles each stage for at most a few sizes (`torch.compile(dynamic=False)`).

Applies (`applies`) where `renderer.tracing.direct` would (direct light only: Lambert, point and ambient lights),
with the thin-lens camera with plain-number parameters and no distortion, no layers, every shape a sphere,
box, rectangle or plane traced by Embree, textures only ones with a palette (checkers) on rectangles, CPU
float32. Same formulas as `renderer.tracing.direct.shade_hits` / `add_light` and `ThinLensCamera._rays_in_place`;
images agree with the eager path to float rounding (Inductor may contract or reorder float operations), and
a ray grazing an edge may then change its hit (tests/renderer/test_fused.py).
"""
from __future__ import annotations

import math

import torch

from typing import NamedTuple

from renderer.cameras.thin_lens import concentric_disk_xy, direction_rows, disc_rows, focus_weight_rows
from renderer.tracing.direct import applies as direct_applies
from renderer.scene.model import Scene, TraceOptions

_KINDS = {"sphere", "box", "rectangle", "plane"}
# Rays a batch by default: with the stages fused, per-call costs (Python, torch.compile's guards, Dr.Jit) are a
# larger share, so larger batches pay; 2^20 was faster still but leaves two workers only two jobs each on the
# speed scene (`render.MAX_JOB_RAYS`; docs/speed.md, "Defaults and where they come from").
CHUNK_RAYS = 1 << 19


def applies(scene: Scene, options: TraceOptions, device, dtype) -> bool:
    """Whether `render_pixels` computes this scene's image (see the module docstring)."""
    return options.compile and options.intersector == "mitsuba" and scene_fits(scene, device, dtype)


def scene_fits(scene: Scene, device, dtype) -> bool:
    """Whether the scene is one the per-component stages here shade (see the module docstring), for a
    render on `device` in `dtype`."""
    if not camera_fits(scene, device, dtype) or not all(o.shape.type_name in _KINDS for o in scene.objects):
        return False
    table = scene.materials(torch.zeros(0, dtype=dtype, device=device))
    if not direct_applies(scene, TraceOptions(), table):
        return False
    return all(scene.objects[k].shape.type_name == "rectangle" and tex.palette is not None
               for k, tex in table.textures.items())


def camera_fits(scene: Scene, device, dtype) -> bool:
    """Whether `_camera_rays` makes the scene's camera rays (and `renderer.tracing.jit_direct`'s): a render on
    the CPU in float32, no layers, the thin lens with plain-number parameters, its tilt about the camera x axis,
    no distortion, nothing in the scene needing gradients."""
    from renderer.cameras.thin_lens import ThinLensCamera

    cam = scene.camera
    if (torch.device(device).type != "cpu" or dtype != torch.float32 or scene.layers
            or type(cam) is not ThinLensCamera):
        return False
    if cam.distortion is not None and not cam.distortion.is_identity:
        return False
    lens, screen = cam.lens, cam.screen
    numbers = (lens.w, lens.U, lens.d, lens.theta_F, lens.phi, *screen.center_px, *screen.pitch)
    if any(isinstance(v, torch.Tensor) for v in numbers):  # Python numbers only (constants of the kernels)
        return False
    if lens.phi != 0:  # its compiled rays take the tilt about x only
        return False
    return not scene.requires_grad()


class _Tables:
    """Per-object values as 1-D float32 tables gathered by object id in the compiled shading, and the scene's
    constants as Python numbers (baked into the compiled code)."""

    def __init__(self, scene: Scene, table):
        from renderer.tracing.direct import NormalTables

        like = torch.zeros(0, dtype=torch.float32)
        nt = NormalTables(scene, table, like)
        self.faces, self.center, self.inv_r = nt.faces, nt.center, nt.inv_r
        f32 = dict(dtype=torch.float32)
        colors = [torch.zeros(3, 1, **f32), table.color.T.to(**f32)]
        # (object, texture, first palette slot, origin (3 floats), rows of local_from_world, half) per textured
        # rectangle
        self.textured = []
        for k in sorted(table.textures):
            shape, tex = scene.objects[k].shape, table.textures[k]
            first = sum(c.shape[1] for c in colors)
            colors.append(torch.tensor(tex.palette, **f32).T)
            R = shape.local_from_world.tolist() if not shape.axis_aligned else None
            self.textured.append((k, tex, first, [float(v) for v in shape.origin], R, [float(v) for v in shape.half]))
        self.colors = torch.cat(colors, 1).contiguous().unbind(0)
        self.kd = torch.cat([torch.zeros(1, **f32), table.diffuse.to(**f32)])
        self.eps = float(scene.ray_epsilon)
        self.lights = [(light.type, [float(v) for v in light.intensity],
                        None if light.type == "ambient" else [float(v) for v in light.position])
                       for light in scene.lights]
        self.background = [float(v) for v in scene.image.background]


class _CameraConstants(NamedTuple):
    """The thin-lens camera's numbers as `_camera_rays` takes them (Python numbers, baked into the compiled code)."""
    cx: float               # principal point, pixels
    cy: float
    pitch_x: float          # pixel pitch, scene units
    pitch_y: float
    w: float                # lens centre to sensor
    half_d: float           # aperture radius
    cos_theta_L: float      # lens tilt, float32-rounded trigonometry
    sin_theta_L: float
    tan_theta_F: float
    U: float                # focus distance
    R: list | None          # world_from_camera rows, None for the identity
    position: list          # camera centre, world frame


def _camera_rays(sampler, pixel, width: int, cam: _CameraConstants):
    """Stage 1: world rays (ox, oy, oz, dx, dy, dz), each (n·spp,) float32, for the samples of the pixels
    `pixel` (n,): `Sampler.pixel_block`, `sampling.camera_samples` then the thin lens's rays (`renderer.cameras.
    thin_lens`' row functions, as `ThinLensCamera._rays_in_place` computes them)."""
    block = sampler.pixel_block(pixel)
    xs = (block[0] + ((pixel % width).to(torch.float64) - 0.5)[:, None]).to(torch.float32).reshape(-1)
    ys = (block[1] + ((pixel // width).to(torch.float64) - 0.5)[:, None]).to(torch.float32).reshape(-1)
    # The thin lens's own concentric map (its selects are torch.where while compiling, one fused loop here).
    lx, ly = concentric_disk_xy(block[2:].to(torch.float32).reshape(2, -1).T)
    x, y, z = (xs - cam.cx) * cam.pitch_x, (ys - cam.cy) * cam.pitch_y, cam.w
    o0, o1, o2 = disc_rows(lx, ly, cam.half_d, cam.cos_theta_L, cam.sin_theta_L)
    weight = focus_weight_rows(y, z, cam.tan_theta_F, cam.U)
    d0, d1, d2 = direction_rows(x, y, z, o0, o1, o2, weight)
    inv = (d0 * d0 + d1 * d1 + d2 * d2).rsqrt().clamp_max(1e12)
    d0, d1, d2 = d0 * inv, d1 * inv, d2 * inv
    R, t = cam.R, cam.position
    if R is None:
        return o0 + t[0], o1 + t[1], o2 + t[2], d0, d1, d2
    o = [R[i][0] * o0 + R[i][1] * o1 + R[i][2] * o2 + t[i] for i in range(3)]
    d = [R[i][0] * d0 + R[i][1] * d1 + R[i][2] * d2 for i in range(3)]
    return (*o, *d)


def _shade(o, d, t, obj, aux, faces, center, inv_r, colors, kd, tb: _Tables):
    """Stage 2: `direct.shade_hits` on 1-D components. Returns found (N,), the shadow rays' origin (3 × (N,))
    and per point light its direction (3 × (N,)) and reach (N,), and the radiance terms: ambient (3 × (N,),
    None without ambient light) and per point light the unshadowed radiance (3 × (N,))."""
    found = obj >= 0
    safe = obj.clamp_min(0)
    tt = torch.where(found, t, 0)
    p = [o[i] + tt * d[i] for i in range(3)]
    face = aux.clamp(0, 5) + 6 * safe
    n = [faces[i][face] + (p[i] - center[i][safe]) * inv_r[safe] for i in range(3)]
    slot = obj + 1
    index = slot
    for k, tex, first, origin, R, half in tb.textured:  # the rectangle's `uv_rows`, then the texture's index
        q = [p[i] - origin[i] for i in range(3)]
        if R is None:
            u, v = q[0], q[1]
        else:
            u, v = (R[j][0] * q[0] + R[j][1] * q[1] + R[j][2] * q[2] for j in range(2))
        index = index + (obj == k) * (tex.palette_index(u + half[0], v + half[1]) + (first - (k + 1)))
    albedo = [colors[i][index] for i in range(3)]
    entering = n[0] * d[0] + n[1] * d[1] + n[2] * d[2] < 0
    sign = entering.to(t.dtype) * 2 - 1
    nf = [n[i] * sign for i in range(3)]
    kds = kd[slot]
    origin = [p[i] + nf[i] * tb.eps for i in range(3)]
    ambient = None  # no zero rows written and read back where the scene has no ambient light
    shadow, unshadowed = [], []
    for kind, intensity, position in tb.lights:
        if kind == "ambient":
            ambient = [intensity[i] * albedo[i] + (0 if ambient is None else ambient[i]) for i in range(3)]
            continue
        to = [position[i] - origin[i] for i in range(3)]
        dist = (to[0] * to[0] + to[1] * to[1] + to[2] * to[2]).sqrt()
        inv = 1 / dist.clamp_min(1e-12)
        l = [to[i] * inv for i in range(3)]
        cos = (nf[0] * l[0] + nf[1] * l[1] + nf[2] * l[2]).clamp_min(0)
        reach = torch.where((cos > 0) & found, dist, 0)
        scale = kds * cos / (math.pi * (reach * reach).clamp_min(1e-30))
        shadow.append((*l, reach))
        unshadowed.append([albedo[i] * scale * intensity[i] for i in range(3)])
    return found, origin, shadow, ambient, unshadowed


def _pixel_means(found, ambient, unshadowed, vis, background, spp: int):
    """Stage 3: `direct.add_light` and the mean of each pixel's spp consecutive samples: (n, 3)."""
    rad = None if ambient is None else list(ambient)
    for term, v in zip(unshadowed, vis):
        rad = [term[i] * v + (0 if rad is None else rad[i]) for i in range(3)]
    if rad is None:  # no lights: black
        rad = [torch.zeros(found.shape, dtype=torch.float32, device=found.device) for _ in range(3)]
    if any(background):
        rad = [rad[i] + background[i] * (~found).to(rad[i].dtype) for i in range(3)]
    return torch.stack([r.view(-1, spp).sum(1) for r in rad], 1) / spp


class _Rows(tuple):
    """Three (N,) components standing in for the (3, N) rows `MitsubaIntersector` reads (it only indexes
    them and asks their device and dtype), so the compiled stages' outputs go to Embree without stacking."""

    device = property(lambda self: self[0].device)
    dtype = property(lambda self: self[0].dtype)


_COMPILED: dict = {}


def _compiled(fn):
    if fn not in _COMPILED:
        _COMPILED[fn] = torch.compile(fn, dynamic=False)
    return _COMPILED[fn]


def _camera_constants(cam) -> _CameraConstants:
    """The thin lens's numbers as `_camera_rays` takes them (read on every batch: a camera changed between
    renders is seen; torch.compile then recompiles for its new constants). Trigonometry in float32 as the
    eager path rounds it."""
    f32 = lambda v: float(torch.tensor(float(v), dtype=torch.float32))  # noqa: E731
    trig = lambda fn, angle: f32(fn(torch.tensor(float(angle), dtype=torch.float32)))  # noqa: E731
    R = cam.transform.world_from_camera.to(torch.float64)
    eye = bool((R == torch.eye(3, dtype=R.dtype)).all())
    lens, screen = cam.lens, cam.screen
    return _CameraConstants(*screen.center_px, *screen.pitch, lens.w, lens.d / 2, trig(torch.cos, lens.theta_L),
                            trig(torch.sin, lens.theta_L), trig(torch.tan, lens.theta_F), lens.U,
                            None if eye else R.tolist(), [float(v) for v in cam.transform.position])


def _state(scene: Scene):
    """The scene's `_Tables` (`Scene.derived`: rebuilt after a move, and for other lights or background) and
    camera constants."""
    key = (tuple(scene.image.background),
           tuple((l.type, tuple(l.intensity), tuple(getattr(l, "position", None) or ())) for l in scene.lights))
    tables = scene.derived(("fused.tables", key),
                           lambda: _Tables(scene, scene.materials(torch.zeros(0, dtype=torch.float32))))
    return tables, _camera_constants(scene.camera)


def _padded(pixel: torch.Tensor) -> torch.Tensor:
    """The pixels (n,) padded by their last one to a power of two (at least 64): few sizes to compile."""
    n = pixel.shape[0]
    size = 1 << max(6, (n - 1).bit_length())
    return torch.cat([pixel, pixel[-1:].expand(size - n)]) if size > n else pixel


def render_pixels(scene: Scene, pixel: torch.Tensor, sampler, options: TraceOptions):
    """Estimates (n, 3) and coverage (n,) of the pixels `pixel` (n,), as `render._render_pixels` returns
    them (every thin-lens ray is valid with weight 1)."""
    from renderer.mitsuba.intersect import engine

    n, spp = pixel.shape[0], sampler.spp
    pixel = _padded(pixel)
    tb, cam = _state(scene)
    eng = engine(scene)
    if eng.fallback:
        raise AssertionError("fused: every shape should be traced by Embree (see applies)")
    rays = _compiled(_camera_rays)(sampler, pixel, scene.camera.width, cam)
    o, d = _Rows(rays[:3]), _Rows(rays[3:])
    t, obj, aux = eng.nearest(o, d, scene.ray_epsilon)
    found, origin, shadow, ambient, unshadowed = _compiled(_shade)(
        o, d, t, obj, aux, tb.faces, tb.center, tb.inv_r, tb.colors, tb.kd, tb)
    vis = [eng.visible(_Rows(origin), _Rows(s[:3]), s[3], scene.ray_epsilon) for s in shadow]
    estimate = _compiled(_pixel_means)(found, ambient, unshadowed, vis, tb.background, spp)
    return estimate[:n], torch.ones(n, dtype=estimate.dtype)
