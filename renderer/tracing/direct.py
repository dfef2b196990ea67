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

from renderer.core.rays import component_rows
from renderer.scene.model import Scene, TraceOptions


# Shape types whose normals `NormalTables` knows (and that have `intersect_soa`): from its tables, or
# (cylinder, cone) from the shape's own `normal_rows` per object.
_KINDS = {"sphere", "box", "rectangle", "plane", "cylinder", "cone"}
_OWN_NORMALS = {"cylinder", "cone"}


def applies(scene: Scene, options: TraceOptions, table) -> bool:
    """Whether `trace_direct` computes exactly what `integrator.trace` would for this scene."""
    if options.compile or not getattr(options, "fast_paths", True) or not scene.objects:
        return False  # (no objects: no normal tables to gather from; the general integrator draws the background)
    if not all(o.shape.soa_native and o.shape.type_name in _KINDS for o in scene.objects):
        return False
    if any(light.type not in ("point", "ambient") for light in scene.lights):
        return False
    return not bool(((table.reflect > 0) | (table.transmit > 0) | (table.specular > 0)).any())


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
        normal = self._gather(self.faces, torch.add(aux.clamp(0, 5), obj, alpha=6))
        if self.any_sphere:
            # (p − centre) / r added to every row: the tables hold centre 0 and 1/r = 0 for other objects and
            # face normals 0 for spheres, so each row gets its own normal exactly (p is finite), without a
            # select between the two.
            normal = torch.addcmul(normal, p - self._gather(self.center, obj), self.inv_r.index_select(0, obj))
        for k in self.own:
            normal = torch.where(obj == k, scene.objects[k].shape.normal_rows(p, aux), normal)
        return normal


def _dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(N,) dot products of (3, N) rows, a0·b0 + a1·b1 + a2·b2: three row operations instead of a (3, N)
    product and a sum over its first axis."""
    return (a[0] * b[0]).addcmul_(a[1], b[1]).addcmul_(a[2], b[2])


def _tables(scene: Scene, table, like: torch.Tensor) -> NormalTables:
    """The scene's `NormalTables` on like's device and in its dtype (`Scene.derived`: rebuilt after a move)."""
    return scene.derived(("direct.normals", like.device, like.dtype), lambda: NormalTables(scene, table, like))


def trace_direct(scene: Scene, o: torch.Tensor, d: torch.Tensor, first_hit_objects, table,
                 options: TraceOptions):
    """Radiance (N, 3) and found (N,) for rays o, d (N, 3), as `integrator.trace` returns them (the radiance
    as a transposed view of (3, N) rows)."""
    o_s, d_s = component_rows(o), component_rows(d)
    hit = scene.intersect_rows(o_s, d_s, first_hit_objects, options=options)
    lit = shade_hits(scene, table, _tables(scene, table, o_s), o_s, d_s, hit.t, hit.object_id, hit.aux)
    leaving, vis = None, []
    for origin, l, reach in lit[3]:
        if leaving is None and scene.answers_shadow_rays(options, origin, l, reach):
            # Only our own tracer skips the object a shadow ray leaves (Embree needs no such help).
            leaving = scene.self_shadow_free(hit.object_id.clamp_min(0), lit[1])
        vis.append(scene.visibility_rows(origin, l, reach, options=options, leaving=leaving))
    return add_light(scene, lit, vis).T, hit.found  # an (N, 3) view of the rows: no transposing copy


def shade_hits(scene: Scene, table, tables: NormalTables, o_s, d_s, t, obj, aux):
    """The direct light at the first hits of rays o_s, d_s ((3, N) rows) but the shadow rays' answers.

    Args:
        table: the scene's material table; tables: its `NormalTables` (`_tables`); t, obj, aux: (N,) the
            rays' `Hit` (object −1 on a miss).
    Returns:
        found (N,) bool; entering (N,) bool: the ray meets the outside of the surface
            (`Scene.self_shadow_free` takes it);
        ambient: (3, N) ambient light, or None; shadow: a list of (origin (3, N), unit direction (3, N),
        reach (N,)) per point light (reach 0: no shadow ray); unshadowed: a list of (3, N) radiance per point
        light, to be multiplied by its shadow ray's visibility (`add_light`).
    """
    dtype, device = o_s.dtype, o_s.device
    found = obj >= 0
    safe_obj = obj.clamp_min(0)
    p = torch.addcmul(o_s, torch.where(found, t, 0), d_s)  # (3, N); misses sit at their origin, masked below
    normal = tables.normals(scene, p, aux, safe_obj, found)
    # Albedo and kd: one gather each by slot = object + 1 from tables whose slot 0 (a miss) is zero, so misses
    # get no light and end up exactly 0 (the background is added in `add_light`). The colour table is extended
    # by the palette of each texture that has one (a checker's two colours) on a shape with `uv_rows`: its hits
    # index its palette instead of their object's colour.
    slot = obj + 1
    colors = [torch.zeros(3, 1, dtype=dtype, device=device), table.color.T]
    albedo_index = slot
    others = []
    for k in tables.textured:
        shape, texture = scene.objects[k].shape, table.textures[k]
        if texture.palette is not None and hasattr(shape, "uv_rows"):
            # Rows all through: the texture's palette index on every ray, kept where it hit k.
            uv = shape.uv_rows(p, aux)
            first = sum(c.shape[1] for c in colors)
            colors.append(torch.tensor(texture.palette, dtype=dtype, device=device).T)
            # Hits on k (slot k + 1) move to slot first + index: integer arithmetic, no select.
            albedo_index = albedo_index + (obj == k) * (texture.palette_index(uv[0], uv[1]) + (first - (k + 1)))
        else:
            others.append(k)
    albedo = NormalTables._gather(torch.cat(colors, 1).unbind(0), albedo_index)  # (3, N)
    for k in others:
        idx = (obj == k).nonzero().squeeze(1)
        if idx.numel():
            n_k, uv = scene.objects[k].shape.surface(p.index_select(1, idx).T, aux.index_select(0, idx))
            normal.index_copy_(1, idx, n_k.T.contiguous())
            albedo.index_copy_(1, idx, table.textures[k].evaluate(uv).T.contiguous())
    entering = _dot(normal, d_s) < 0
    n_f = normal * entering.to(dtype).mul_(2).sub_(1)  # the normal facing the ray (times ±1: exact)
    kd = torch.cat([torch.zeros(1, dtype=dtype, device=device), table.diffuse]).index_select(0, slot)
    eps = scene.ray_epsilon
    ambient, shadow, unshadowed = None, [], []
    for light in scene.lights:
        intensity = torch.tensor(light.intensity, dtype=dtype, device=device)[:, None]
        if light.type == "ambient":
            ambient = intensity * albedo if ambient is None else ambient.add_(intensity * albedo)
            continue
        origin = torch.add(p, n_f, alpha=eps)
        to_light = torch.tensor(light.position, dtype=dtype, device=device)[:, None] - origin
        dist = _dot(to_light, to_light).sqrt_()
        l = to_light / dist.clamp_min(1e-12)
        cos = _dot(n_f, l).clamp_min(0)
        reach = torch.where((cos > 0) & found, dist, 0)  # misses (background) trace no shadow ray
        shadow.append((origin, l, reach))
        scale = kd * cos / (math.pi * (reach * reach).clamp_min(1e-30))
        unshadowed.append(albedo * scale * intensity)
    if ambient is None and not unshadowed:  # no lights: black, and the background where rays missed
        ambient = torch.zeros_like(p)
    return found, entering, ambient, shadow, unshadowed


def add_light(scene: Scene, lit, vis: list[torch.Tensor]) -> torch.Tensor:
    """(3, N) radiance from `shade_hits`' results `lit` and each point light's visibility vis (N,) (0 or 1,
    so it multiplies exactly wherever it is applied); the background where the ray missed. Consumes `lit`: the
    light is added into its ambient rows in place (one (3, N) buffer less per batch)."""
    found, _, ambient, _, unshadowed = lit
    radiance = ambient
    for term, v in zip(unshadowed, vis):
        radiance = term * v if radiance is None else radiance.add_(term * v)
    if any(scene.image.background):  # misses are 0 so far: adding the background times "missed" is exact
        background = torch.tensor(scene.image.background, dtype=radiance.dtype, device=radiance.device)[:, None]
        radiance = radiance + background * ~found
    return radiance

