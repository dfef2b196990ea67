"""Whitted-style recursive ray tracing, done breadth-first (wavefront) on flat ray batches.

Each bounce intersects one batch, groups the hits by object (one stable sort, so every shape computes its
normals on one contiguous slice and rays keep their screen order within an object), adds the local shading
(direct light with shadow rays, ambient) weighted by the path throughput, and spawns at most two child
batches (mirror reflection, refraction) that carry their pixel index along. No per-pixel Python loop: every
step is a tensor operation over a batch.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import torch

from renderer.tracing import direct
from renderer.core.rays import normalize
from renderer.scene.model import Scene, TraceOptions, compiled_call
from renderer.shapes.base import root

# Paths whose throughput falls below this contribute nothing visible and are dropped.
_MIN_THROUGHPUT = 1e-4


def _group_by_object(object_id: torch.Tensor, n_objects: int, multiple: int = 1) -> tuple[torch.Tensor, list[int]]:
    """Rays that hit something, grouped by object.

    Returns:
        order: (n_hit + pad,) long indices of the hitting rays, sorted by object id (stable, so screen
        order is kept within an object), padded with copies of the last index to a multiple of `multiple`
        (so that gathered batches fill whole culling packets); counts: hits per object (n_objects ints).
    """
    counts = torch.bincount(object_id + 1, minlength=n_objects + 1).tolist()  # misses (−1) first
    n_miss = counts[0]
    n_hit = object_id.shape[0] - n_miss
    if n_hit == 0:
        return object_id.new_zeros(0), counts[1:]
    if max(counts[1:]) == object_id.shape[0]:  # one object took every ray: already grouped
        order = torch.arange(n_hit, device=object_id.device)
    else:
        # Sorting is several times faster on narrow keys; misses (key 0) come first.
        narrow = torch.uint8 if n_objects < 255 else torch.int16 if n_objects < 32767 else torch.int32
        order = torch.argsort((object_id + 1).to(narrow), stable=True)[n_miss:]
    pad = (-n_hit) % multiple
    if pad:
        order = torch.cat([order, order[-1:].expand(pad)])
    return order, counts[1:]


def _slices(counts: list[int]):
    """(k, start, stop) of every object with hits, for arrays grouped by `_group_by_object`."""
    start = 0
    for k, c in enumerate(counts):
        if c:
            yield k, start, start + c
        start += c


def _surface(scene: Scene, p, aux, counts, options, textured=None):
    """Outward normals (n, 3) and uv (n, 2) for hit points grouped by object, one shape call per object.

    Objects not in `textured` (a set of object ids; None: all) get their normal only (`Shape.normal_at`, eager
    tracing): their uv rows are left unset, as nothing reads them.
    """
    normal = torch.empty_like(p)
    uv = torch.empty(p.shape[0], 2, dtype=p.dtype, device=p.device)
    for k, a, b in _slices(counts):
        if textured is None or k in textured or options.compile:
            normal[a:b], uv[a:b] = scene.surface(k, p[a:b], aux[a:b], options=options)
        else:
            normal[a:b] = scene.objects[k].shape.normal_at(p[a:b], aux[a:b])
    return normal, uv


def _albedo(table, uv, counts):
    """(n, 3) albedo of hits grouped by object: the colour, or the texture where there is one."""
    albedo = torch.empty(uv.shape[0], 3, dtype=uv.dtype, device=uv.device)
    for k, a, b in _slices(counts):
        albedo[a:b] = table.textures[k].evaluate(uv[a:b]) if k in table.textures else table.color[k]
    return albedo


def _hit_points(o, d, t, aux, order):
    """Hit points p = o + t·d (n, 3), directions (n, 3) and aux (n,) of the rays `order` (n,)."""
    d = d.index_select(0, order)
    return o.index_select(0, order) + t.index_select(0, order)[:, None] * d, d, aux.index_select(0, order)


def _orient(normal, d):
    """Normals turned to face the incoming rays (n, 3), and whether each ray enters the surface (n,)."""
    entering = (normal * d).sum(-1) < 0
    return torch.where(entering[:, None], normal, -normal), entering


def _to_light(p, n_f, light_pos, eps: float):
    """Shadow rays towards a point light: origin (offset along the normal), unit direction, length (the
    distance to the light, 0 where the light is behind the surface) and the clamped cosine between the
    normal and the light direction."""
    origin = p + n_f * eps
    to_light = light_pos - origin
    dist = torch.linalg.vector_norm(to_light, dim=-1)
    l = to_light / dist[:, None].clamp_min(1e-12)
    cos = (n_f * l).sum(-1).clamp_min(0)
    return origin, l, torch.where(cos > 0, dist, torch.zeros_like(dist)), cos


def _lambert(albedo, kd, cos, dist, trans, intensity):
    """Lambert term kd·albedo/π times the irradiance I·cos/r²·transmittance (0 where cos = 0)."""
    scale = kd * cos / (math.pi * (dist * dist).clamp_min(1e-30))
    return albedo * scale[:, None] * (intensity * trans)


def _lambert_phong(albedo, kd, ks, shin, cos, dist, trans, intensity, n_f, l, d):
    """Lambert plus normalised Phong, ks·(s + 2)/(2π)·max(0, r·v)^s with v = −d, times the irradiance."""
    refl = 2 * cos[:, None] * n_f - l
    rv = -(refl * d).sum(-1).clamp_max(0)
    shade = kd[:, None] * albedo / math.pi + (ks * (shin + 2) / (2 * math.pi) * rv**shin)[:, None]
    return shade * (intensity * (cos / (dist * dist).clamp_min(1e-30))[:, None] * trans)


def direct_light(scene: Scene, p, n_f, d, albedo, table, obj, *, options: TraceOptions | None = None,
                 outside: torch.Tensor | None = None):
    """Local shading: Lambert (albedo/π) and normalised Phong from point lights with shadows, plus ambient.

    Args:
        p: (n, 3) hit points; n_f: (n, 3) normals facing the incoming ray; d: (n, 3) unit directions of
        the incoming rays; albedo: (n, 3); obj: (n,) object ids.
    Returns:
        (n, 3) radiance leaving p towards the viewer before the material's local weight is applied.
    """
    options = scene.options if options is None else options
    fast = options.compile
    out = torch.zeros_like(p)
    eps = scene.ray_epsilon
    kd = table.diffuse.index_select(0, obj)
    leaving = None if outside is None else scene.self_shadow_free(obj, outside)
    specular = bool((table.specular > 0).any())
    if specular:
        ks, shin = table.specular.index_select(0, obj), table.shininess.index_select(0, obj)
    for light in scene.lights:
        intensity = torch.tensor(light.intensity, dtype=p.dtype, device=p.device)
        if light.type == "ambient":
            out = out + intensity * albedo
            continue
        light_pos = torch.tensor(light.position, dtype=p.dtype, device=p.device)
        # Points facing away from the light (cos = 0) get a zero-length shadow ray rather than being
        # compacted out: they contribute nothing either way and the batch keeps its screen order.
        origin, l, reach, cos = compiled_call(fast, _to_light, p, n_f, light_pos, eps)
        trans = scene.shadow(origin, l, reach, options=options, leaving=leaving)
        if specular:
            local = compiled_call(fast, _lambert_phong, albedo, kd, ks, shin, cos, reach, trans, intensity, n_f, l, d)
        else:
            local = compiled_call(fast, _lambert, albedo, kd, cos, reach, trans, intensity)
        out = out + local
    return out


def _add_background(radiance, found, background, pix, thr):
    """radiance (N, 3) plus the background seen by the rays of the batch that miss (~found) every object;
    pix, thr: the batch's pixels and throughputs (None: the primary rays, throughput one)."""
    miss = (~found).to(radiance.dtype)[:, None] * background
    if pix is None:
        return radiance + miss
    radiance.index_add_(0, pix, thr * miss)
    return radiance


class _Surfaces(NamedTuple):
    """The hit points of one bounce, one row each (world frame): point, incoming unit direction and normal
    facing it (n, 3), whether the ray enters the surface (n,), albedo (n, 3) and object id (n,)."""
    p: torch.Tensor
    direction: torch.Tensor
    n_f: torch.Tensor
    entering: torch.Tensor
    albedo: torch.Tensor
    obj: torch.Tensor

    def first(self, n: int) -> "_Surfaces":
        """The first n rows."""
        return _Surfaces(*(x[:n] for x in self))


def _hit_surfaces(scene: Scene, table, o, d, hit, options: TraceOptions):
    """The rays of a batch that hit, grouped by object, and their surfaces.

    Returns:
        None where no ray hits; else hits (n,) long indices of the hitting rays in the batch, and their
        _Surfaces of n_rows ≥ n rows: the rows past n are the padding that fills
        the last culling packet (they repeat the last hit).
    """
    n_objects, fast = len(scene.objects), options.compile
    order, counts = _group_by_object(hit.object_id, n_objects, options.packet_size if options.culling else 1)
    if order.shape[0] == 0:
        return None
    n_hit, n_rows = sum(counts), order.shape[0]
    # The padding rows repeat the last hit: they join the last object's group and are dropped by the caller.
    last = max(k for k, c in enumerate(counts) if c)
    rows = counts[:last] + [counts[last] + n_rows - n_hit] + counts[last + 1:]
    p, d, aux = compiled_call(fast, _hit_points, o, d, hit.t, hit.aux, order)
    obj = torch.repeat_interleave(torch.arange(n_objects, device=o.device),
                                  torch.tensor(rows, device=o.device), output_size=n_rows)
    normal, uv = _surface(scene, p, aux, rows, options, table.textures)
    n_f, entering = compiled_call(fast, _orient, normal, d)
    return order[:n_hit], _Surfaces(p, d, n_f, entering, _albedo(table, uv, rows), obj)


def _split_weights(table, obj, entering):
    """Mirror, transmitted and local weights kr, kt, 1 − kr − kt (n,) and ior (n,) of the hits' materials.

    Leaving a transparent object is a bare dielectric interface: no shading, full transmission.
    """
    kr, kt, ior = (x.index_select(0, obj) for x in (table.reflect, table.transmit, table.ior))
    exiting = (~entering) & (kt > 0)
    kt = torch.where(exiting, torch.ones_like(kt), kt)
    kr = torch.where(exiting, torch.zeros_like(kr), kr)
    return kr, kt, (1 - kr - kt).clamp_min(0), ior


def _add_local(radiance, scene: Scene, table, surfaces: _Surfaces, pix, thr, local_w, options: TraceOptions) -> None:
    """Add the local shading of the hits whose material keeps a local weight (in place into radiance)."""
    p, d, n_f, entering, albedo, obj = surfaces
    weight = local_w[:, None] if thr is None else thr * local_w[:, None]
    shaded = (local_w > 0).nonzero().squeeze(1)
    if shaded.numel():
        sel = (lambda x: x) if shaded.shape[0] == p.shape[0] else (lambda x: x.index_select(0, shaded))
        local = direct_light(scene, sel(p), sel(n_f), sel(d), sel(albedo), table, sel(obj), options=options,
                             outside=sel(entering))
        radiance.index_add_(0, sel(pix), sel(weight) * local)


def _children(surfaces: _Surfaces, kr, kt, ior, thr, pix, eps: float):
    """The next batch: mirror and refracted rays (origin, direction, throughput, pixel) whose throughput
    stays above _MIN_THROUGHPUT, reflected rays first; None where there are none. Total internal reflection
    sends the transmitted weight into the mirror ray."""
    p, d, n_f, entering, albedo, _ = surfaces
    cos_i = -(n_f * d).sum(-1)
    eta = torch.where(entering, 1 / ior, ior)
    k = 1 - eta**2 * (1 - cos_i**2)
    tir = k < 0
    refl_dir = d + 2 * cos_i[:, None] * n_f
    refr_dir = normalize(eta[:, None] * d + (eta * cos_i - root(k))[:, None] * n_f)
    w_refl = kr + torch.where(tir, kt, torch.zeros_like(kt))
    w_refr = torch.where(tir, torch.zeros_like(kt), kt)
    tint = torch.where(entering[:, None], albedo, torch.ones_like(albedo))
    thr_refl = thr * w_refl[:, None]
    thr_refr = thr * w_refr[:, None] * tint
    r = (thr_refl.amax(-1) > _MIN_THROUGHPUT).nonzero().squeeze(1)
    s = (thr_refr.amax(-1) > _MIN_THROUGHPUT).nonzero().squeeze(1)
    if r.numel() + s.numel() == 0:
        return None
    return (torch.cat([p[r] + n_f[r] * eps, p[s] - n_f[s] * eps]), torch.cat([refl_dir[r], refr_dir[s]]),
            torch.cat([thr_refl[r], thr_refr[s]]), torch.cat([pix[r], pix[s]]))


def trace(scene: Scene, o: torch.Tensor, d: torch.Tensor, first_hit_objects: list[bool] | None = None,
          max_depth: int | None = None, *, options: TraceOptions | None = None):
    """Radiance along each ray.

    Args:
        o, d: (N, 3) origins and unit directions, world frame.
        first_hit_objects: per-object flags for the primary intersection only (layer composition: the
            first ray sees only the layer's objects; shadow, reflection and refraction rays see all).
        max_depth: number of secondary bounces allowed [scene.image.max_depth].
        options: how rays are traced [scene.options]; speed only.
    Returns:
        radiance (N, 3) linear RGB, and found (N,) bool: whether the primary ray hit an object.
    """
    options = scene.options if options is None else options
    max_depth = scene.image.max_depth if max_depth is None else max_depth
    radiance = torch.zeros(o.shape[0], 3, dtype=o.dtype, device=o.device)
    background = torch.tensor(scene.image.background, dtype=o.dtype, device=o.device)
    table = scene.materials(o)
    if direct.applies(scene, options, table):
        return direct.trace_direct(scene, o, d, first_hit_objects, table, options)
    bounces = bool(((table.reflect > 0) | (table.transmit > 0)).any())
    pix = None  # pixel (index into the N input rays) of each ray in the batch; None: the identity
    thr = None  # path throughput of each ray; None: all ones (primary rays)
    found_primary = None
    for depth in range(max_depth + 1):
        hit = scene.intersect(o, d, first_hit_objects if depth == 0 else None, options=options)
        if depth == 0:
            found_primary = hit.found
        if bool((background != 0).any()):
            radiance = _add_background(radiance, hit.found, background, pix, thr)
        batch = _hit_surfaces(scene, table, o, d, hit, options)
        if batch is None:
            break
        hits, surfaces = batch
        pix = hits if pix is None else pix.index_select(0, hits)
        thr = None if thr is None else thr.index_select(0, hits)
        if not bounces:
            s = surfaces
            local = direct_light(scene, s.p, s.n_f, s.direction, s.albedo, table, s.obj, options=options,
                                 outside=s.entering)[:hits.shape[0]]
            radiance.index_add_(0, pix, local if thr is None else thr * local)
            break
        surfaces = surfaces.first(hits.shape[0])
        kr, kt, local_w, ior = _split_weights(table, surfaces.obj, surfaces.entering)
        _add_local(radiance, scene, table, surfaces, pix, thr, local_w, options)
        if depth == max_depth:
            break
        thr = torch.ones_like(surfaces.p) if thr is None else thr
        children = _children(surfaces, kr, kt, ior, thr, pix, scene.ray_epsilon)
        if children is None:
            break
        o, d, thr, pix = children
    return radiance, found_primary
