"""Mitsuba 3 shape dicts of a scene's objects (`shape_dicts`) and their BSDFs: two-sided Lambert, or our
`renderer_phong` plugin (`renderer.mitsuba.bsdfs`), with our textures mapped onto each shape's Mitsuba uv
(`_reflectance`). What carries over is listed in `renderer.mitsuba.export`'s docstring.
"""
from __future__ import annotations

import math

import numpy as np

from renderer.core.transforms import world_from_local_4x4 as _matrix
from renderer.scene.materials import CheckerTexture, GridTexture, ImageTexture

from .tessellate import (_box_triangles, _cone_triangles, _csg_triangles, _disc_triangles, _mesh_triangles,
                         _our_uv, _polyhedron_triangles, _triangle_mesh, plane_pieces)


# ------------------------------------------------------------------------------------------------ materials


def _uv_transform(mi, scale, offset):
    """The `to_uv` of a Mitsuba texture: (u, v) -> scale ⊙ (u, v) + offset."""
    return mi.ScalarTransform3f([[scale[0], 0.0, offset[0]], [0.0, scale[1], offset[1]], [0.0, 0.0, 1.0]])


def _reflectance(mi, material, weight: float, uv_map):
    """Mitsuba texture of weight · albedo. uv_map = (scale, offset): our texture coordinates (scene units) are
    scale ⊙ (Mitsuba's uv) + offset on this shape."""
    tex = material.texture
    scale, offset = (np.asarray(x, dtype=np.float64) for x in uv_map)
    if isinstance(tex, CheckerTexture):
        # Ours: cell (floor(u / size), floor(v / size)), colour by the parity of their sum. Mitsuba's
        # checkerboard repeats every texture unit with color0 on the cells (0, 0) and (1, 1) of its 2 × 2:
        # its coordinate is ours / (2 · size).
        cell = 2 * tex.size
        return {"type": "checkerboard",
                "color0": {"type": "rgb", "value": [weight * c for c in tex.colors[0]]},
                "color1": {"type": "rgb", "value": [weight * c for c in tex.colors[1]]},
                "to_uv": _uv_transform(mi, scale / cell, offset / cell)}
    if isinstance(tex, ImageTexture):
        # Ours: texel centres at ((i + 0.5) / w) · size, bilinear, repeated; Mitsuba's bitmap the same in
        # its coordinate ours / size (row 0 at v = 0 in both).
        size = np.asarray(tex.size, dtype=np.float64)
        return {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(weight * tex.pixels, dtype=np.float32)),
                "raw": True, "filter_type": "bilinear", "wrap_mode": "repeat",
                "to_uv": _uv_transform(mi, scale / size, offset / size)}
    if isinstance(tex, GridTexture):
        # Exact cells here; Mitsuba gets them sampled at texel centres (nearest texel, edges within half a
        # texel: GRID_TEXEL_FRACTION of the smallest cell, at most 8192 texels a side), clamped beyond the grid.
        cell = min(np.diff(tex.xs).min(), np.diff(tex.ys).min())
        pixels, origin, size = tex.raster(GRID_TEXEL_FRACTION * cell)
        size, origin = np.asarray(size), np.asarray(origin)
        return {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(weight * pixels, dtype=np.float32)),
                "raw": True, "filter_type": "nearest", "wrap_mode": "clamp",
                "to_uv": _uv_transform(mi, scale / size, (offset - origin) / size)}
    return {"type": "rgb", "value": [weight * c for c in material.color]}


#: A `GridTexture`'s texel for Mitsuba, as a fraction of its smallest cell.
GRID_TEXEL_FRACTION = 1.0 / 64


def _bsdf(mi, material, uv_map=((1.0, 1.0), (0.0, 0.0)), dropped=None, name="", ambient=False):
    """Two-sided Lambert with reflectance (1 − reflect − transmit) · diffuse · albedo (see `_reflectance` for
    uv_map; the default: the shape's Mitsuba uv are ours), or our `renderer_phong` plugin where the material
    has a Phong highlight or, under `ambient` light, a diffuse weight other than 1 (`renderer.mitsuba.bsdfs`);
    the terms it cannot express go to `dropped`."""
    weight = max(1.0 - material.reflect - material.transmit, 0.0)
    if dropped is not None:
        dropped += [f"{name}: {key}" for key in ("reflect", "transmit") if getattr(material, key) > 0]
    if material.specular > 0 or (ambient and material.diffuse != 1):
        from .bsdfs import register

        register(mi)
        return {"type": "renderer_phong", "reflectance": _reflectance(mi, material, weight, uv_map), "weight": weight,
                "diffuse": material.diffuse, "specular": material.specular, "shininess": material.shininess}
    return {"type": "twosided", "material": {
        "type": "diffuse", "reflectance": _reflectance(mi, material, weight * material.diffuse, uv_map)}}


# ---------------------------------------------------------------------------------------------------- shapes


def shape_dicts(mi, scene, dropped: list[str] | None = None, *, plane_size: float | None = None,
                segments: int = 256, only=None, tessellate: bool = False) -> dict:
    """Mitsuba shapes of the scene's objects (those with an index in `only`, when given): {key: shape dict or
    loaded mesh}, keys `object_{i}` (a cylinder also `object_{i}_base` and `object_{i}_top`, its caps); what
    cannot be expressed is appended to `dropped`. tessellate: a textured cylinder's caps as triangle fans of
    `segments` facets carrying our uv (Mitsuba's disc has polar uv), else exact discs. See `to_mitsuba` for
    the other arguments."""
    T = mi.ScalarTransform4f
    ambient = any(light.type == "ambient" and any(light.intensity) for light in scene.lights)
    out: dict = {}
    for i, obj in enumerate(scene.objects):
        if only is not None and i not in only:
            continue
        shape, kind, key, material = obj.shape, obj.shape.type_name, f"object_{i}", obj.material

        def bsdf(uv_map=((1.0, 1.0), (0.0, 0.0)), note=True):
            return _bsdf(mi, material, uv_map, dropped if note else None, obj.name, ambient)

        if kind == "sphere":
            # Mitsuba: φ = atan2(y, x) in [0, 2π), θ = acos(z) in its local frame; ours: φ = atan2(x, z)
            # in (−π, π], θ = acos(y) in the world's, uv = r · (φ, θ). Local axes (−z, −x, y): φ' = φ + π,
            # so ours = r · (2π u' − π, π v').
            r = shape.radius
            R = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]])
            out[key] = {"type": "sphere", "to_world": T(_matrix(R, shape.center.numpy(), [r, r, r])),
                        "bsdf": bsdf(((2 * math.pi * r, math.pi * r), (-math.pi * r, 0.0)))}
        elif kind == "rectangle":
            # Mitsuba's uv = (local + 1) / 2 over [−1, 1]²; ours = local + half, scene units.
            half = shape.half.tolist()
            out[key] = {"type": "rectangle",
                        "to_world": T(_matrix(shape.world_from_local.numpy(), shape.origin.numpy(), half + [1.0])),
                        "bsdf": bsdf(((2 * half[0], 2 * half[1]), (0.0, 0.0)))}
        elif kind == "plane":
            R = np.stack([shape.tangent_u.numpy(), shape.tangent_v.numpy(), shape.normal.numpy()], axis=1)
            if plane_size is None:
                centre, pieces = plane_pieces(scene, shape)
            else:
                centre, pieces = shape.point.numpy(), [((0.0, 0.0), (plane_size / 2, plane_size / 2))]
            shift = (centre - shape.point.numpy()) @ R[:, :2]  # the centre in our uv (from the plane's point)
            for j, (middle, half) in enumerate(pieces):
                # ours: u = (x − point)·tangent_u = shift + middle + half · (2 u' − 1), likewise v.
                offset = [shift[k] + middle[k] - half[k] for k in range(2)]
                out[key if j == 0 else f"{key}_{j}"] = {
                    "type": "rectangle", "to_world": T(_matrix(R, centre + R[:, :2] @ middle, [*half, 1.0])),
                    "bsdf": bsdf(((2 * half[0], 2 * half[1]), offset), note=j == 0)}
        elif kind == "cylinder":
            # Mitsuba's open cylinder: uv = (φ / 2π in [0, 2π), z / height) in its local frame; ours: (r · φ,
            # z) with φ = atan2(y, x) in (−π, π]. Local axes (−x, −y, z) give φ' = φ + π.
            R, o = shape.world_from_local.numpy(), shape.origin.numpy()
            r, h = shape.radius, shape.height
            side = bsdf(((2 * math.pi * r, h), (-math.pi * r, 0.0)))
            out[key] = {"type": "cylinder", "p0": [0.0, 0.0, 0.0], "p1": [0.0, 0.0, h], "radius": r,
                        "to_world": T(_matrix(R * [-1.0, -1.0, 1.0], o)), "bsdf": side}
            caps = {"_base": o, "_top": o + h * R[:, 2]}
            if tessellate and material.texture is not None:
                cap = mi.load_dict(bsdf(note=False))
                for part, centre in caps.items():
                    tri, uv = _disc_triangles(R, centre, r, segments)
                    out[key + part] = _triangle_mesh(mi, key + part, tri, None, cap, uv)
            else:
                cap = bsdf(note=False)
                for part, centre in caps.items():
                    out[key + part] = {"type": "disk", "to_world": T(_matrix(R, centre, [r, r, 1.0])), "bsdf": cap}
        elif kind in ("box", "cone", "polyhedron", "mesh", "csg"):
            mesh_bsdf = mi.load_dict(bsdf())
            nrm = None
            if kind == "cone":
                tri, nrm, uv = _cone_triangles(shape, segments)
            else:
                tri, aux = {"box": _box_triangles, "polyhedron": _polyhedron_triangles, "mesh": _mesh_triangles,
                            "csg": _csg_triangles}[kind](shape)
                uv = _our_uv(shape, tri, aux)
            out[key] = _triangle_mesh(mi, key, tri, nrm, mesh_bsdf, uv)
        else:
            raise NotImplementedError(f"mitsuba export: shape type {kind!r} ({obj.name})")
    return out
