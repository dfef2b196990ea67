"""Shapes, registered by name and built from plain dicts (a scene object's `shape` section).

`register_shape(name, params)` registers a builder `fn(path, cfg, base_dir) -> Shape`; `build_shape` validates
the dict against the declared params (unknown keys, wrong types, NaN are errors naming the field) and builds.
Each shape's module docstring documents its keys (units, defaults, frames, `aux` and uv conventions).
"""
from __future__ import annotations

import os

import torch

from renderer.core.params import Param, SceneError, check_value, parse_params
from .base import ParameterError, Shape

SHAPES: dict[str, tuple[list[Param], object]] = {}


def register_shape(name: str, params: list[Param]):
    def deco(fn):
        SHAPES[name] = (params, fn)
        return fn

    return deco


def build_shape(path: str, cfg: dict, base_dir: str = ".") -> Shape:
    """Validate a `shape` section and build the shape it names (`type`)."""
    if not isinstance(cfg, dict):
        raise SceneError(f"{path}: expected an object, got {cfg!r}")
    kind = cfg.get("type")
    if kind not in SHAPES:
        from renderer.scene.plugins import load_plugins

        load_plugins()
    if kind not in SHAPES:
        raise SceneError(f"{path}.type: unknown shape {kind!r} (expected one of: {', '.join(sorted(SHAPES))})")
    params, fn = SHAPES[kind]
    parsed = parse_params(path, cfg, params, ignore=("type",))
    try:
        return fn(path, parsed, base_dir)
    except SceneError:
        raise
    except ParameterError as e:
        raise SceneError(f"{path}.{e.field}: {e.message}") from None
    except ValueError as e:
        raise SceneError(f"{path}: {e}") from None


from .box import Box  # noqa: E402
from .cone import Cone  # noqa: E402
from .cylinder import Cylinder  # noqa: E402
from .mesh import Mesh, load_obj  # noqa: E402
from .plane import Plane  # noqa: E402
from .polyhedron import Polyhedron  # noqa: E402
from .rectangle import Rectangle  # noqa: E402
from .sphere import Sphere  # noqa: E402

_ROTATION = Param("rotation_deg", "vec3", (0.0, 0.0, 0.0), "Euler angles [rx, ry, rz], degrees; R = Rz·Ry·Rx")
_AXIAL = [
    Param("center", "vec3", doc="centre of the base disc, scene units"),
    Param("axis", "vec3", doc="direction from the base to the top (normalised)"),
    Param("radius", "float", doc="radius of the base, scene units, > 0"),
    Param("height", "float", doc="length along the axis, scene units, > 0"),
]


@register_shape("sphere", [Param("center", "vec3", doc="centre"), Param("radius", "float", doc="radius")])
def _sphere(path, cfg, base_dir):
    return Sphere(cfg["center"], cfg["radius"])


@register_shape("plane", [Param("point", "vec3", doc="a point on the plane"), Param("normal", "vec3", doc="normal")])
def _plane(path, cfg, base_dir):
    return Plane(cfg["point"], cfg["normal"])


@register_shape("box", [Param("center", "vec3", doc="centre, scene units"),
                        Param("size", "vec3", doc="edge lengths [sx, sy, sz] along the local axes, > 0"), _ROTATION])
def _box(path, cfg, base_dir):
    return Box(cfg["center"], cfg["size"], cfg["rotation_deg"])


@register_shape("rectangle", [Param("center", "vec3", doc="centre, scene units"),
                              Param("size", "vec2", doc="[sx, sy] along local x and y (u and v), > 0"), _ROTATION])
def _rectangle(path, cfg, base_dir):
    return Rectangle(cfg["center"], cfg["size"], cfg["rotation_deg"])


@register_shape("cylinder", _AXIAL)
def _cylinder(path, cfg, base_dir):
    return Cylinder(cfg["center"], cfg["axis"], cfg["radius"], cfg["height"])


@register_shape("cone", _AXIAL)
def _cone(path, cfg, base_dir):
    return Cone(cfg["center"], cfg["axis"], cfg["radius"], cfg["height"])


@register_shape("mesh", [Param("file", "str", doc="OBJ file, relative to the scene file's folder"),
                         Param("center", "vec3", (0.0, 0.0, 0.0), "where the file's origin goes, scene units"),
                         Param("scale", "any", None, "uniform (number) or per-axis [sx, sy, sz] scale [1]"),
                         Param("size", "vec3", None, "as for a box: the file's bounding box is centred on `center` "
                                                     "and stretched to [sx, sy, sz] (instead of `scale`)"),
                         _ROTATION])
def _mesh(path, cfg, base_dir):
    vertices, triangles = load_obj(os.path.join(base_dir, cfg["file"]))
    if cfg["size"] is not None:
        if cfg["scale"] is not None:
            raise SceneError(f"{path}: give size or scale, not both")
        if min(cfg["size"]) <= 0:
            raise SceneError(f"{path}.size: expected 3 positive numbers, got {list(cfg['size'])}")
        lo, hi = vertices.amin(0), vertices.amax(0)
        extent = (hi - lo).clamp_min(1e-12)
        vertices = vertices - (lo + hi) / 2
        scale = tuple(float(s) for s in torch.tensor(cfg["size"], dtype=vertices.dtype) / extent)
    else:
        scale = 1.0 if cfg["scale"] is None else cfg["scale"]
        kind = "float" if isinstance(scale, (int, float)) and not isinstance(scale, bool) else "vec3"
        scale = check_value(f"{path}.scale", kind, scale)
    return Mesh(vertices, triangles, cfg["center"], scale, cfg["rotation_deg"])


_HALFSPACES = Param("halfspaces", "list", doc="[[nx, ny, nz, c], ...]: the convex solid where every n·x <= c")


@register_shape("polyhedron", [_HALFSPACES])
def _polyhedron(path, cfg, base_dir):
    return Polyhedron(cfg["halfspaces"])


from .csg import OPS as _CSG_OPS, CSG  # noqa: E402


@register_shape("csg", [Param("op", "str", doc="intersection, union or difference (first minus the rest)",
                              choices=_CSG_OPS),
                        Param("children", "list", doc="shapes: polyhedron (the leaf) or csg")])
def _csg(path, cfg, base_dir):
    from .csg import MAX_LEAVES, count_leaves

    if count_leaves(cfg) > MAX_LEAVES:  # before any leaf is built
        raise SceneError(f"{path}.children: expected at most {MAX_LEAVES} polyhedron leaves in one CSG tree, got "
                         f"{count_leaves(cfg)} (memory grows with the square of the leaves)")
    children = [build_shape(f"{path}.children[{i}]", c, base_dir) for i, c in enumerate(cfg["children"])]
    return CSG(cfg["op"], children)
