"""Whitted-style recursive ray tracing, done breadth-first (wavefront) on flat ray batches.

Each bounce intersects one batch, adds the local shading (direct light with shadow rays, ambient) of every
hit weighted by the path throughput, and spawns at most two child batches (mirror reflection, refraction)
that carry their pixel index along. No per-pixel Python loop: every step is a tensor operation over a batch.
"""
from __future__ import annotations

import math

import torch

from .rays import normalize
from .scene import Scene

# Paths whose throughput falls below this contribute nothing visible and are dropped.
_MIN_THROUGHPUT = 1e-4


def _surface(scene: Scene, p, obj, aux):
    """Outward normals (n, 3) and uv (n, 2) for hit points, one shape call per object present."""
    normal = torch.zeros_like(p)
    uv = torch.zeros(p.shape[0], 2, dtype=p.dtype, device=p.device)
    for k, o in enumerate(scene.objects):
        idx = (obj == k).nonzero().squeeze(1)
        if idx.numel():
            n_k, uv_k = o.shape.surface(p[idx], aux[idx])
            normal[idx] = n_k
            uv[idx] = uv_k
    return normal, uv


def _albedo(scene: Scene, table, obj, uv):
    albedo = table.color[obj]
    for k in table.textured:
        idx = (obj == k).nonzero().squeeze(1)
        if idx.numel():
            albedo[idx] = table.textures[k].evaluate(uv[idx])
    return albedo


def direct_light(scene: Scene, p, n_f, view, albedo, table, obj):
    """Local shading: Lambert (albedo/π) and normalised Phong from point lights with shadows, plus ambient.

    Args:
        p: (n, 3) hit points; n_f: (n, 3) normals facing the incoming ray; view: (n, 3) unit vectors
        towards the viewer.
    Returns:
        (n, 3) radiance leaving p towards the viewer before the material's local weight is applied.
    """
    out = torch.zeros_like(p)
    eps = scene.ray_epsilon
    kd = table.diffuse[obj][:, None]
    ks = table.specular[obj][:, None]
    shin = table.shininess[obj][:, None]
    origin = p + n_f * eps
    for light in scene.lights:
        intensity = torch.tensor(light.intensity, dtype=p.dtype, device=p.device)
        if light.type == "ambient":
            out = out + intensity * albedo
            continue
        to_light = torch.tensor(light.position, dtype=p.dtype, device=p.device) - origin
        dist = torch.linalg.vector_norm(to_light, dim=-1)
        l = to_light / dist[:, None].clamp_min(1e-12)
        cos = (n_f * l).sum(-1).clamp_min(0)
        lit = (cos > 0).nonzero().squeeze(1)
        if lit.numel() == 0:
            continue
        trans = scene.transmittance(origin[lit], l[lit], dist[lit])
        irradiance = intensity * (cos[lit] / dist[lit] ** 2)[:, None] * trans
        shade = kd[lit] * albedo[lit] / math.pi
        if bool((ks > 0).any()):
            refl = 2 * cos[lit, None] * n_f[lit] - l[lit]
            rv = (refl * view[lit]).sum(-1, keepdim=True).clamp_min(0)
            shade = shade + ks[lit] * (shin[lit] + 2) / (2 * math.pi) * rv ** shin[lit]
        out[lit] = out[lit] + shade * irradiance
    return out


def trace(scene: Scene, o: torch.Tensor, d: torch.Tensor, first_hit_objects: list[bool] | None = None,
          max_depth: int | None = None):
    """Radiance along each ray.

    Args:
        o, d: (N, 3) origins and unit directions, world frame.
        first_hit_objects: per-object flags for the primary intersection only (layer composition: the
            first ray sees only the layer's objects; shadow, reflection and refraction rays see all).
        max_depth: number of secondary bounces allowed [scene.image.max_depth].
    Returns:
        radiance (N, 3) linear RGB, and found (N,) bool: whether the primary ray hit an object.
    """
    max_depth = scene.image.max_depth if max_depth is None else max_depth
    n_rays = o.shape[0]
    radiance = torch.zeros(n_rays, 3, dtype=o.dtype, device=o.device)
    background = torch.tensor(scene.image.background, dtype=o.dtype, device=o.device)
    table = scene.materials(o)
    pix = torch.arange(n_rays, device=o.device)
    thr = torch.ones(n_rays, 3, dtype=o.dtype, device=o.device)
    eps = scene.ray_epsilon
    found_primary = None
    for depth in range(max_depth + 1):
        hit = scene.intersect(o, d, first_hit_objects if depth == 0 else None)
        found = hit.found
        if depth == 0:
            found_primary = found
        miss = (~found).nonzero().squeeze(1)
        radiance.index_add_(0, pix[miss], thr[miss] * background)
        keep = found.nonzero().squeeze(1)
        if keep.numel() == 0:
            break
        o, d, thr, pix = o[keep], d[keep], thr[keep], pix[keep]
        obj, t, aux = hit.object_id[keep], hit.t[keep], hit.aux[keep]
        p = o + t[:, None] * d
        normal, uv = _surface(scene, p, obj, aux)
        cos_in = (normal * d).sum(-1)
        entering = cos_in < 0
        n_f = torch.where(entering[:, None], normal, -normal)
        albedo = _albedo(scene, table, obj, uv)
        kr, kt, ior = table.reflect[obj], table.transmit[obj], table.ior[obj]
        # Leaving a transparent object is a bare dielectric interface: no surface shading, full transmission.
        exiting = (~entering) & (kt > 0)
        kt = torch.where(exiting, torch.ones_like(kt), kt)
        kr = torch.where(exiting, torch.zeros_like(kr), kr)
        local_w = (1 - kr - kt).clamp_min(0)
        shaded = (local_w > 0).nonzero().squeeze(1)
        if shaded.numel():
            local = direct_light(scene, p[shaded], n_f[shaded], -d[shaded], albedo[shaded], table, obj[shaded])
            radiance.index_add_(0, pix[shaded], thr[shaded] * local_w[shaded, None] * local)
        if depth == max_depth:
            break
        cos_i = -(n_f * d).sum(-1)
        eta = torch.where(entering, 1 / ior, ior)
        k = 1 - eta**2 * (1 - cos_i**2)
        tir = k < 0
        refl_dir = d + 2 * cos_i[:, None] * n_f
        refr_dir = normalize(eta[:, None] * d + (eta * cos_i - k.clamp_min(0).sqrt())[:, None] * n_f)
        w_refl = kr + torch.where(tir, kt, torch.zeros_like(kt))
        w_refr = torch.where(tir, torch.zeros_like(kt), kt)
        tint = torch.where(entering[:, None], albedo, torch.ones_like(albedo))
        thr_refl = thr * w_refl[:, None]
        thr_refr = thr * w_refr[:, None] * tint
        r = (thr_refl.amax(-1) > _MIN_THROUGHPUT).nonzero().squeeze(1)
        s = (thr_refr.amax(-1) > _MIN_THROUGHPUT).nonzero().squeeze(1)
        if r.numel() + s.numel() == 0:
            break
        o = torch.cat([p[r] + n_f[r] * eps, p[s] - n_f[s] * eps])
        d = torch.cat([refl_dir[r], refr_dir[s]])
        thr = torch.cat([thr_refl[r], thr_refr[s]])
        pix = torch.cat([pix[r], pix[s]])
    return radiance, found_primary
