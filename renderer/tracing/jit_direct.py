"""Direct light beside Embree in Dr.Jit: the default path of `render` for direct-light thin-lens scenes.

With `intersector="mitsuba"` (the default `auto` where Mitsuba's llvm variant runs) the eager path hands each
batch of rays to Embree and back, and spends most of its time in a few hundred torch operations per batch, each
a pass over memory (docs/speed.md, "Where the time goes"). Here the whole per-sample computation of a batch is
written with Dr.Jit arrays, the JIT Embree already runs in, so that Dr.Jit traces it into a few LLVM kernels
(one loop over the samples, Embree's queries inside) as Mitsuba's own renders are:

    samples (Sobol here; other samplers from `Sampler.pixel_block`) -> thin-lens rays -> Embree nearest hits
        -> shading -> Embree shadow rays -> radiance -> pixel sums (`drjit.block_sum`)

Dr.Jit compiles each distinct kernel once (tens of milliseconds with LLVM) and keeps it in memory and on disk
(`~/.drjit`), so the first render of a new machine is not delayed by seconds as `torch.compile` is (`fused`).

Scenes (`applies`): direct light only (Lambert and Phong materials without mirror or refraction weights;
point and ambient lights); the thin-lens camera as `fused.camera_fits` takes it (plain-number parameters, no
tilt-axis turn, no distortion, no layers); spheres, boxes, rectangles and planes; checker and image textures
on rectangles and planes; CPU float32. Formulas: those of `renderer.tracing.direct` (and of
`integrator._lambert_phong` for a Phong lobe) and `ThinLensCamera._rays_in_place`, in float32 as they are (the
samples in float64 as `Sampler` makes them).
The images agree with the eager path to float rounding: Dr.Jit's sine and cosine are its own, so lens points
may differ in the last bit, and a ray grazing an edge may then change its hit (tests/renderer/test_jit_direct.py).
"""
from __future__ import annotations

import math

import numpy as np
import torch

from renderer.cameras.thin_lens import direction_rows, disc_rows, focus_weight_rows
from renderer.scene.materials import CheckerTexture, ImageTexture
from renderer.scene.model import Scene, TraceOptions
from renderer.tracing import fused
from renderer.tracing.sampling import camera_samples

# Rays a batch by default: a batch is one kernel launch and a few milliseconds of Python, so large batches pay;
# 2^22 (a 512 x 512 image at 16 spp in one batch, about 50 MB of results) was the fastest measured on the speed
# scene (docs/speed.md, "Defaults and where they come from").
CHUNK_RAYS = 1 << 22


def applies(scene: Scene, options: TraceOptions, device, dtype) -> bool:
    """Whether `render_pixels` computes this scene's image: eager Embree renders (`intersector="mitsuba"`,
    not `compile`, `fast_paths` and `jit_kernels` on) of the scenes in the module docstring."""
    if (options.compile or not options.fast_paths or not options.jit_kernels
            or options.intersector != "mitsuba"):
        return False
    # The camera and the lights are checked on every call (a caller may replace them between renders); what
    # depends on the objects only is kept until they change.
    if not fused.camera_fits(scene, device, dtype):
        return False
    if any(light.type not in ("point", "ambient") for light in scene.lights):
        return False
    return scene.derived("jit_direct.objects_fit", lambda: _objects_fit(scene))


# Shapes whose normals `NormalTables` holds and whose Embree counterpart is the same surface; of these, the flat
# ones may carry a checker or an image texture (their texture coordinates are an affine function of the hit point).
_KINDS = {"sphere", "box", "rectangle", "plane"}
_FLAT = {"rectangle", "plane"}


def _objects_fit(scene: Scene) -> bool:
    """Whether the scene's objects and materials are ones the kernels shade (see the module docstring)."""
    if not scene.objects or not all(o.shape.type_name in _KINDS for o in scene.objects):
        return False  # an empty scene has no tables to gather from (the eager path draws its background)
    table = scene.materials(torch.zeros(0, dtype=torch.float32))
    if bool(((table.reflect > 0) | (table.transmit > 0)).any()):
        return False
    return all(isinstance(tex, (CheckerTexture, ImageTexture)) and scene.objects[k].shape.type_name in _FLAT
               for k, tex in table.textures.items())


class _Kernel:
    """What the Dr.Jit computation of a scene reads, made once per scene: per-object tables as Dr.Jit arrays
    gathered by object id in the kernel (slot 0 of the material tables a miss, slot k + 1 object k), the
    textures' frames and the lights as Python numbers (literals in the kernel), the intersector, Mitsuba and
    Dr.Jit."""

    def __init__(self, scene: Scene):
        from renderer.mitsuba.intersect import engine
        from renderer.tracing.direct import NormalTables

        self.engine = engine(scene)
        if self.engine.fallback:
            raise AssertionError("jit_direct: every shape should be traced by Embree (see applies)")
        self.engine.ensure_variant()  # the tables below are built with `mi`'s types
        mi = self.mi = self.engine.mi
        self.dr = self.engine.dr
        table = scene.materials(torch.zeros(0, dtype=torch.float32))
        normals = NormalTables(scene, table, torch.zeros(0, dtype=torch.float32))
        F = lambda rows: [mi.Float(r.contiguous().numpy()) for r in rows]  # noqa: E731
        slots = lambda values: mi.Float(torch.cat([torch.zeros(1), values.float()]).numpy())  # noqa: E731
        self.faces, self.center, self.inv_r = F(normals.faces), F(normals.center), mi.Float(normals.inv_r.numpy())
        self.kd = slots(table.diffuse)
        self.specular = bool((table.specular > 0).any())  # a Phong lobe on some object
        self.ks, self.shininess = slots(table.specular), slots(table.shininess)
        colors = [torch.zeros(3, 1), table.color.T.float()]
        # Per texture (object, texture, origin (3), u and v axes (2 × 3), offset (2); its texture coordinates are
        # u = axis_u · (p − origin) + offset_u, likewise v: `Rectangle.uv_rows`, `Plane.surface`), then for a
        # checker its first palette slot (its colours extend the colour table), for an image its texels (three
        # (H·W,) channels).
        self.checkers, self.images = [], []
        for k in sorted(table.textures):
            shape, tex = scene.objects[k].shape, table.textures[k]
            if shape.type_name == "rectangle":
                axes = None if shape.axis_aligned else shape.local_from_world[:2].tolist()
                origin, offset = shape.origin, shape.half
            else:
                axes, origin, offset = [shape.tangent_u.tolist(), shape.tangent_v.tolist()], shape.point, (0.0, 0.0)
            frame = (k, tex, [float(v) for v in origin], axes, [float(v) for v in offset])
            if isinstance(tex, CheckerTexture):
                self.checkers.append((*frame, sum(c.shape[1] for c in colors)))
                colors.append(torch.tensor(tex.palette, dtype=torch.float32).T)
            else:
                texels = torch.as_tensor(tex.pixels, dtype=torch.float32).reshape(-1, 3).T
                self.images.append((*frame, F(texels.unbind(0))))
        self.colors = F(torch.cat(colors, 1).unbind(0))
        self.eps = float(scene.ray_epsilon)
        self.lights = [(light.type, [float(v) for v in light.intensity],
                        None if light.type == "ambient" else [float(v) for v in light.position])
                       for light in scene.lights]
        self.background = [float(v) for v in scene.image.background]


def _kernel(scene: Scene) -> _Kernel:
    """The scene's `_Kernel`, kept by the scene (`Scene.derived`: rebuilt after a move) for its lights and
    background: made again when they change, and only the latest kept (lights moved every frame of an animation
    do not pile up kernels)."""
    key = (tuple(scene.image.background),
           tuple((l.type, tuple(l.intensity), tuple(getattr(l, "position", None) or ())) for l in scene.lights))
    held = scene.derived("jit_direct.kernel", lambda: {})
    if held.get("key") != key:
        held.clear()
        held.update(key=key, kernel=_Kernel(scene))
    return held["kernel"]


def render_pixels(scene: Scene, pixel: torch.Tensor, sampler, options: TraceOptions):
    """Estimates (n, 3) and coverage (n,) of the pixels `pixel` (n,), as `render._render_pixels` returns
    them (every thin-lens ray is valid with weight 1)."""
    k = _kernel(scene)
    k.engine.ensure_variant()  # the samples and camera below are built with `mi`'s types
    mi, dr = k.mi, k.dr
    spp = sampler.spp
    xs, ys, u, v = _samples(k, sampler, pixel, scene.camera.width)
    o, d = _camera_rays(k, xs, ys, u, v, _opaque_camera(k, fused._camera_constants(scene.camera)))
    eps = scene.ray_epsilon
    t, obj, aux = k.engine.jit_nearest(k.engine.jit_ray(o, d, eps), eps, mi.Int32)
    found, origin, shadow, ambient, unshadowed = _shade(k, o, d, t, obj, aux)
    rad = None if ambient is None else list(ambient)
    for (l, reach), term in zip(shadow, unshadowed):
        vis = k.engine.jit_visible(k.engine.jit_ray(origin, l, eps, reach))
        rad = [term[i] * vis + (0 if rad is None else rad[i]) for i in range(3)]
    if rad is None:  # no lights: black
        rad = [dr.zeros(mi.Float, dr.width(t)) for _ in range(3)]
    background = k.background
    if any(background):
        missed = dr.select(found, 0.0, mi.Float(1.0))
        rad = [rad[i] + background[i] * missed for i in range(3)]
    dr.eval(*rad)  # one kernel for the three channels (`block_sum` would evaluate each channel's own)
    sums = [dr.block_sum(r, spp) for r in rad]
    dr.eval(*sums)
    estimate = torch.stack([s.torch() for s in sums], 1) / spp
    return estimate, torch.ones(pixel.shape[0], dtype=estimate.dtype)


def _samples(k: _Kernel, sampler, pixel: torch.Tensor, width: int):
    """Pixel positions x, y and lens samples u, v (`mi.Float` each, (n·spp,), a pixel's samples consecutive),
    as `sampling.camera_samples` makes them: Sobol points in Dr.Jit (the same integer hashes and float64 steps
    as `Sampler.pixel_block`), other samplers from `Sampler.pixel_block` itself."""
    mi, dr = k.mi, k.dr
    spp = sampler.spp
    if sampler.name != "sobol":
        uv_px, lens_uv = camera_samples(sampler, pixel, width, torch.float32)
        return [mi.Float(c.contiguous()) for c in (uv_px[:, 0], uv_px[:, 1], lens_uv[:, 0], lens_uv[:, 1])]
    U32, F64 = mi.UInt32, mi.Float64
    index = dr.arange(U32, pixel.shape[0] * spp)
    slot = index // spp
    px = dr.gather(U32, U32(pixel.numpy().astype(np.uint32)), slot)
    h = _chain(dr.opaque(U32, int(sampler.sobol_shift_key)), px)
    table = F64(sampler.sobol_points.reshape(-1).numpy())
    first = (index - slot * spp) * 4
    rows = []
    for dim in range(4):
        value = dr.gather(F64, table, first + dim) + F64(_chain(h, dim)) / 2.0**32  # in [0, 2)
        rows.append(dr.select(value >= 1, value - 1, value))
    rows[0] = rows[0] + (F64(px % width) - 0.5)
    rows[1] = rows[1] + (F64(px // width) - 0.5)
    return [mi.Float(r) for r in rows]


def _hash32(x):
    """`sampling._hash32` on Dr.Jit UInt32 arrays (whose products wrap at 2^32 as its masks do)."""
    x = x ^ (x >> 16)
    x = x * 0x7FEB352D
    x = x ^ (x >> 15)
    x = x * 0x846CA68B
    return x ^ (x >> 16)


def _chain(h, key):
    """`sampling._chain` on Dr.Jit UInt32 arrays."""
    return _hash32(key + h * 0x9E3779B1)


def _opaque_camera(k: _Kernel, cam: fused._CameraConstants) -> fused._CameraConstants:
    """The camera's numbers as opaque Dr.Jit scalars (`drjit.opaque`): inputs of the kernel, not constants in
    its code, so a moved camera (an animation's frames) runs the kernel already compiled instead of compiling
    and caching one per frame. The identity rotation stays None (one more kernel for turned cameras)."""
    mi, dr = k.mi, k.dr
    scalar = lambda v: dr.opaque(mi.Float, v)  # noqa: E731
    R = None if cam.R is None else [[scalar(v) for v in row] for row in cam.R]
    return fused._CameraConstants(*(scalar(v) for v in cam[:10]), R, [scalar(v) for v in cam.position])


def _camera_rays(k: _Kernel, xs, ys, u, v, cam: fused._CameraConstants):
    """World rays: origin and unit direction, three `mi.Float` each, as `fused._camera_rays` makes them."""
    dr = k.dr
    a, b = 2 * u - 1, 2 * v - 1  # `thin_lens.concentric_disk_xy`
    pick = dr.abs(a) > dr.abs(b)
    r, other = dr.select(pick, a, b), dr.select(pick, b, a)
    q = (math.pi / 4) * (other / (r + dr.select(r == 0, 1.0, 0.0)))
    sin, cos = dr.sincos(dr.select(pick, q, math.pi / 2 - q))
    lx, ly = r * cos, r * sin
    x, y, z = (xs - cam.cx) * cam.pitch_x, (ys - cam.cy) * cam.pitch_y, cam.w
    o0, o1, o2 = disc_rows(lx, ly, cam.half_d, cam.cos_theta_L, cam.sin_theta_L)
    weight = focus_weight_rows(y, z, cam.tan_theta_F, cam.U)
    d0, d1, d2 = direction_rows(x, y, z, o0, o1, o2, weight)
    inv = dr.minimum(dr.rsqrt(d0 * d0 + d1 * d1 + d2 * d2), 1e12)
    d0, d1, d2 = d0 * inv, d1 * inv, d2 * inv
    R, t = cam.R, cam.position
    if R is None:
        return [o0 + t[0], o1 + t[1], o2 + t[2]], [d0, d1, d2]
    o = [R[i][0] * o0 + R[i][1] * o1 + R[i][2] * o2 + t[i] for i in range(3)]
    d = [R[i][0] * d0 + R[i][1] * d1 + R[i][2] * d2 for i in range(3)]
    return o, d


def _uv(p, origin, axes):
    """Texture coordinates (before their offset) of points p (3 components) on a flat shape: p − origin along
    the shape's u and v axes (None: the world's x and y)."""
    q = [p[i] - origin[i] for i in range(3)]
    if axes is None:
        return q[0], q[1]
    return tuple(axes[j][0] * q[0] + axes[j][1] * q[1] + axes[j][2] * q[2] for j in range(2))


def _bilinear(k: _Kernel, tex: ImageTexture, texels, u, v, active):
    """`ImageTexture.evaluate` at texture coordinates u, v: bilinear between texel centres, wrapping at the tile
    edges (three `mi.Float`); texels read where `active`."""
    mi, dr = k.mi, k.dr
    h, w = tex.pixels.shape[:2]
    s, t = u / tex.size[0], v / tex.size[1]
    fx = (s - dr.floor(s)) * w - 0.5  # torch.remainder(·, 1.0): x − floor(x)
    fy = (t - dr.floor(t)) * h - 0.5
    x0, y0 = dr.floor(fx), dr.floor(fy)
    ax, ay = fx - x0, fy - y0
    x0, y0 = mi.Int32(x0), mi.Int32(y0)  # in [−1, w − 1] and [−1, h − 1]
    xa, ya = dr.select(x0 < 0, x0 + w, x0), dr.select(y0 < 0, y0 + h, y0)
    xb, yb = dr.select(x0 + 1 >= w, x0 + 1 - w, x0 + 1), dr.select(y0 + 1 >= h, y0 + 1 - h, y0 + 1)
    out = []
    for channel in texels:
        at = lambda y, x: dr.gather(mi.Float, channel, mi.UInt32(y * w + x), active)  # noqa: E731
        top = at(ya, xa) * (1 - ax) + at(ya, xb) * ax
        bottom = at(yb, xa) * (1 - ax) + at(yb, xb) * ax
        out.append(top * (1 - ay) + bottom * ay)
    return out


def _shade(k: _Kernel, o, d, t, obj, aux):
    """The direct light at the first hits but the shadow rays' answers, as `renderer.tracing.direct.shade_hits`
    (and, with a Phong lobe, `integrator._lambert_phong`) compute it: found, the shadow rays' origin (3
    components), per point light its shadow ray (direction (3 components), reach: 0 for none), the ambient
    radiance (3 components or None) and per point light the unshadowed radiance (3 components)."""
    mi, dr = k.mi, k.dr
    F, I = mi.Float, mi.Int32
    found = obj >= 0
    safe = dr.maximum(obj, 0)
    tt = dr.select(found, t, 0.0)
    p = [o[i] + tt * d[i] for i in range(3)]
    face = dr.clip(aux, 0, 5) + 6 * safe
    inv_r = dr.gather(F, k.inv_r, safe)
    n = [dr.gather(F, k.faces[i], face) + (p[i] - dr.gather(F, k.center[i], safe)) * inv_r for i in range(3)]
    slot = obj + 1
    index = slot
    for obj_k, tex, origin, axes, offset, first in k.checkers:  # the cell (`CheckerTexture.palette_index`)
        u, v = _uv(p, origin, axes)
        cell = dr.floor((u + offset[0]) / tex.size) + dr.floor((v + offset[1]) / tex.size)
        half_cell = cell * 0.5  # odd cells: half an integer (exact)
        odd = I(dr.select(half_cell != dr.floor(half_cell), 1, 0))
        index = dr.select(obj == obj_k, odd + first, index)
    albedo = [dr.gather(F, k.colors[i], index) for i in range(3)]
    for obj_k, tex, origin, axes, offset, texels in k.images:
        u, v = _uv(p, origin, axes)
        rgb = _bilinear(k, tex, texels, u + offset[0], v + offset[1], obj == obj_k)
        albedo = [dr.select(obj == obj_k, rgb[i], albedo[i]) for i in range(3)]
    entering = n[0] * d[0] + n[1] * d[1] + n[2] * d[2] < 0
    sign = dr.select(entering, 1.0, F(-1.0))
    nf = [n[i] * sign for i in range(3)]
    kd = dr.gather(F, k.kd, slot)
    if k.specular:
        ks, shininess = dr.gather(F, k.ks, slot), dr.gather(F, k.shininess, slot)
    origin = [p[i] + nf[i] * k.eps for i in range(3)]
    ambient, shadow, unshadowed = None, [], []
    for kind, intensity, position in k.lights:
        if kind == "ambient":
            ambient = [intensity[i] * albedo[i] + (0 if ambient is None else ambient[i]) for i in range(3)]
            continue
        to = [position[i] - origin[i] for i in range(3)]
        dist = dr.sqrt(to[0] * to[0] + to[1] * to[1] + to[2] * to[2])
        inv = 1 / dr.maximum(dist, 1e-12)
        l = [to[i] * inv for i in range(3)]
        cos = dr.maximum(nf[0] * l[0] + nf[1] * l[1] + nf[2] * l[2], 0.0)
        reach = dr.select((cos > 0) & found, dist, 0.0)
        shadow.append((l, reach))
        if not k.specular:
            scale = kd * cos / (math.pi * dr.maximum(reach * reach, 1e-30))
            unshadowed.append([albedo[i] * scale * intensity[i] for i in range(3)])
            continue
        irradiance = cos / dr.maximum(reach * reach, 1e-30)
        # Normalised Phong, ks (s + 2) / (2π) max(0, r·v)^s with r the mirrored light direction and v = −d
        # (`integrator._lambert_phong`); 0^0 = 1 as torch takes it.
        r = [2 * cos * nf[i] - l[i] for i in range(3)]
        rv = dr.maximum(-(r[0] * d[0] + r[1] * d[1] + r[2] * d[2]), 0.0)
        lobe = ks * (shininess + 2) / (2 * math.pi) * dr.select(shininess == 0, 1.0, dr.power(rv, shininess))
        unshadowed.append([(kd * albedo[i] / math.pi + lobe) * (intensity[i] * irradiance) for i in range(3)])
    return found, origin, shadow, ambient, unshadowed
