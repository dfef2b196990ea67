"""Shapes, registered by name and built from plain dicts (a scene object's `shape` section).

`register_shape(name, params)` registers a builder `fn(path, cfg, base_dir) -> Shape`; `build_shape` validates
the dict against the declared params (unknown keys, wrong types, NaN are errors naming the field) and builds.
"""
from __future__ import annotations

from ..params import Param, SceneError, parse_params
from .base import Shape

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
        raise SceneError(f"{path}.type: unknown shape {kind!r} (expected one of: {', '.join(sorted(SHAPES))})")
    params, fn = SHAPES[kind]
    parsed = parse_params(path, cfg, params, ignore=("type",))
    try:
        return fn(path, parsed, base_dir)
    except ValueError as e:
        if isinstance(e, SceneError):
            raise
        raise SceneError(f"{path}: {e}") from None


from .plane import Plane  # noqa: E402
from .sphere import Sphere  # noqa: E402


@register_shape("sphere", [Param("center", "vec3", doc="centre"), Param("radius", "float", doc="radius")])
def _sphere(path, cfg, base_dir):
    return Sphere(cfg["center"], cfg["radius"])


@register_shape("plane", [Param("point", "vec3", doc="a point on the plane"), Param("normal", "vec3", doc="normal")])
def _plane(path, cfg, base_dir):
    return Plane(cfg["point"], cfg["normal"])
