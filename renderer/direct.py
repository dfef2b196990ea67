"""Fast path of `integrator.trace` for direct lighting only, on (3, N) component rows.

Taken when nothing in the scene bounces light (no mirror or refraction weights), every shape is a sphere,
box, rectangle, plane, cylinder or cone (the shapes with the (3, N) intersection, `Shape.soa_native`),
lights are point or ambient, materials have no specular term (the Phong lobe is left to the general path)
and tracing is eager. Then one camera ray and one shadow ray per point light per sample is the whole
computation, and it runs without grouping hits by object: every
stage is an element-wise operation over all N rays (misses masked at the end), per-object values come
from small tables gathered by object id, and only textured objects gather their own hits for texture
coordinates. Eager torch runs such (N,) rows several times faster than (N, 3) ones (see
`renderer/shapes/base.py`).

Same formulas as `integrator.trace` / `direct_light` (Lambert kd·albedo/π · I cos/r² · visibility, plus
ambient · albedo; the background where the primary ray misses); the images agree to float rounding
(tests/renderer/test_fast_paths.py).
"""
from __future__ import annotations

import math

import torch

from .scene import Scene, TraceOptions
from .shapes.base import geometry_key


# Shape types whose normals `NormalTables` knows (and that have `intersect_soa`): from its tables, or
# (cylinder, cone) from the shape's own `normal_rows` per object.
_KINDS = {"sphere", "box", "rectangle", "plane", "cylinder", "cone"}
_OWN_NORMALS = {"cylinder", "cone"}


def applies(scene: Scene, options: TraceOptions, table) -> bool:
    """Whether `trace_direct` computes exactly what `integrator.trace` would for this scene."""
    if options.compile or not getattr(options, "fast_paths", True):
        return False
    if not all(o.shape.soa_native and o.shape.type_name in _KINDS for o in scene.objects):
        return False
    if any(light.type not in ("point", "ambient") for light in scene.lights):
        return False
    return not bool(((table.reflect > 0) | (table.transmit > 0) | (table.specular > 0)).any())


def _rows(x: torch.Tensor) -> torch.Tensor:
    """(N, 3) -> (3, N) contiguous rows (free where x is already a transposed view of such rows)."""
    return x.T if x.T.is_contiguous() else torch.stack(x.unbind(-1))


# Local outward normals of the box faces 0..5 (−x, +x, −y, +y, −z, +z), as (3, 6) columns.
_FACES = torch.tensor([[-1, 1, 0, 0, 0, 0], [0, 0, -1, 1, 0, 0], [0, 0, 0, 0, -1, 1]], dtype=torch.float64)


class NormalTables:
    """Per-object parameters stacked so that the normals of all hits come from gathers by object id.

    Flat shapes and boxes: a table of world normals per (object, face), gathered at 6·object + aux (flat
    shapes repeat their one normal; turned boxes have their faces turned in the table). Spheres: centre and
    1/radius per object. Cylinders and cones: their own `normal_rows` over all rows, kept where they were
    hit. Textured objects without `uv_rows` gather their own hits (`Shape.surface`).
    """

    def __init__(self, scene: Scene, table, like: torch.Tensor):
        K = len(scene.objects)
        f64 = dict(dtype=torch.float64)
        sphere, center, inv_r = torch.zeros(K, dtype=torch.bool), torch.zeros(3, K, **f64), torch.zeros(K, **f64)
        faces = torch.zeros(3, K, 6, **f64)
        for k, item in enumerate(scene.objects):
            shape = item.shape
            if shape.type_name == "sphere":
                sphere[k], center[:, k], inv_r[k] = True, shape.center, 1 / shape.radius
            elif shape.type_name in ("rectangle", "plane"):
                faces[:, k, :] = shape.normal[:, None]
            elif shape.type_name == "box":
                faces[:, k, :] = shape.world_from_local @ _FACES
        self.textured = sorted(table.textures)
        self.own = [k for k, item in enumerate(scene.objects) if item.shape.type_name in _OWN_NORMALS]
        self.any_sphere = bool(sphere.any())
        to = dict(dtype=like.dtype, device=like.device)
        # One 1-D table per component: gathers along a tensor's first axis are the fast ones.
        self.sphere = sphere.to(like.device)
        self.center, self.inv_r = center.to(**to).unbind(0), inv_r.to(**to)
        self.faces = faces.reshape(3, K * 6).to(**to).unbind(0)

    @staticmethod
    def _gather(rows, index):
        """(len(rows), N): each 1-D table gathered at `index`, written straight into its output row."""
        out = torch.empty(len(rows), index.shape[0], dtype=rows[0].dtype, device=rows[0].device)
        for i, r in enumerate(rows):
            torch.index_select(r, 0, index, out=out[i])
        return out

    def normals(self, scene: Scene, p, aux, obj, found):
        """(3, N) outward normals at the hit points p (3, N) of objects obj (N, clamped to >= 0)."""
        normal = self._gather(self.faces, obj * 6 + aux.clamp(0, 5))
        if self.any_sphere:
            sphere = (p - self._gather(self.center, obj)) * self.inv_r.index_select(0, obj)
            normal = torch.where(self.sphere.index_select(0, obj), sphere, normal)
        for k in self.own:
            normal = torch.where(obj == k, scene.objects[k].shape.normal_rows(p, aux), normal)
        return normal


_TABLES: dict = {}  # (id(scene), device, dtype) -> (scene, geometry key, NormalTables); the scene kept so its id
# stays unique, the key (`renderer.shapes.base.geometry_key`) so a moved shape rebuilds them


def _tables(scene: Scene, table, like: torch.Tensor) -> NormalTables:
    key, geometry = (id(scene), like.device, like.dtype), geometry_key(scene)
    cached = _TABLES.get(key)
    if cached is None or cached[0] is not scene or cached[1] != geometry:
        if len(_TABLES) > 16:
            _TABLES.clear()
        _TABLES[key] = cached = (scene, geometry, NormalTables(scene, table, like))
    return cached[2]


def trace_direct(scene: Scene, o: torch.Tensor, d: torch.Tensor, first_hit_objects, table,
                 options: TraceOptions):
    """Radiance (N, 3) and found (N,) for rays o, d (N, 3), as `integrator.trace` returns them (the radiance
    as a transposed view of (3, N) rows)."""
    o_s, d_s = _rows(o), _rows(d)
    dtype, device = o.dtype, o.device
    hit = scene.intersect_rows(o_s, d_s, first_hit_objects, options=options)
    found, obj = hit.found, hit.object_id
    safe_obj = obj.clamp_min(0)
    p = o_s + torch.where(found, hit.t, 0) * d_s  # (3, N); misses sit at their origin, masked below
    tables = _tables(scene, table, p)
    normal = tables.normals(scene, p, hit.aux, safe_obj, found)
    albedo = NormalTables._gather(table.color.T.unbind(0), safe_obj)  # (3, N)
    for k in tables.textured:
        shape, texture = scene.objects[k].shape, table.textures[k]
        if hasattr(shape, "uv_rows") and type(texture).__name__ == "CheckerTexture":
            # Rows all through: the checker of `CheckerTexture.evaluate` on every ray, kept where it hit k.
            mine = obj == k
            uv = shape.uv_rows(p, hit.aux)
            odd = torch.remainder(torch.floor(uv[0] / texture.size) + torch.floor(uv[1] / texture.size), 2) > 0
            c0, c1 = (torch.tensor(c, dtype=dtype, device=device)[:, None] for c in texture.colors)
            albedo = torch.where(mine, torch.where(odd, c1, c0), albedo)
            continue
        idx = (obj == k).nonzero().squeeze(1)
        if idx.numel():
            n_k, uv = scene.objects[k].shape.surface(p.index_select(1, idx).T, hit.aux.index_select(0, idx))
            normal.index_copy_(1, idx, n_k.T.contiguous())
            albedo.index_copy_(1, idx, table.textures[k].evaluate(uv).T.contiguous())
    entering = (normal * d_s).sum(0) < 0
    n_f = torch.where(entering, normal, -normal)
    kd = table.diffuse.index_select(0, safe_obj)
    leaving = scene.self_shadow_free(safe_obj, entering)
    eps = scene.ray_epsilon
    radiance = torch.zeros_like(p)
    for light in scene.lights:
        intensity = torch.tensor(light.intensity, dtype=dtype, device=device)[:, None]
        if light.type == "ambient":
            radiance = radiance + intensity * albedo
            continue
        origin = p + n_f * eps
        to_light = torch.tensor(light.position, dtype=dtype, device=device)[:, None] - origin
        dist2 = (to_light * to_light).sum(0)
        dist = dist2.sqrt()
        l = to_light / dist.clamp_min(1e-12)
        cos = (n_f * l).sum(0).clamp_min(0)
        reach = torch.where((cos > 0) & found, dist, 0)  # misses (background) trace no shadow ray
        vis = scene.visibility_rows(origin, l, reach, options=options, leaving=leaving)
        scale = kd * cos * vis / (math.pi * (reach * reach).clamp_min(1e-30))
        radiance = radiance + albedo * scale * intensity
    background = torch.tensor(scene.image.background, dtype=dtype, device=device)[:, None]
    radiance = torch.where(found, radiance, background)
    return radiance.T, found  # an (N, 3) view of the rows: no transposing copy
