"""The shape interface: batched ray intersection, surface normal and texture coordinates.

Every shape answers three calls on flat batches of N rays or points (world frame, scene units):
- `intersect(o, d, t_min)` -> (t, aux): nearest hit with t > t_min, +inf on a miss; aux (long) is what
  `surface` needs to find the normal (a face or triangle index; 0 when unused);
- `surface(p, aux)` -> (normal, uv): outward unit normal (N, 3) and texture coordinates (N, 2) in scene
  units (so a checker `size` means the same length on every shape);
- `bounding_sphere()` -> (center (3,), radius) or None for unbounded shapes; the scene uses it to send each
  shape only the rays that can reach it.
Two optional fast paths, same results (tests/renderer/test_fast_paths.py):
- `intersect_soa(o, d, t_min)` with o, d as (3, N) component rows ("structure of arrays"): eager torch runs
  element-wise operations on (N,) rows several times faster than on (N, 3) rows, whose length-3 last axis
  defeats its vectorised loops. Shapes with `soa_native = True` implement it (and `intersect` calls it,
  keeping their former (N, 3) code as `intersect_reference`); the default transposes;
- `normal_at(p, aux)` -> (N, 3): the normal alone, for untextured objects (no texture coordinates computed);
  shapes with `soa_native` also have `normal_rows(p, aux)` for (3, N) rows (renderer/tracing/direct.py).
Shapes keep their parameters in float64 and convert them once per device/dtype (`_param`), again when one
is replaced or edited in place. A bad
parameter raises `ParameterError` naming it; `build_shape` prefixes the scene-file path.
"""
from __future__ import annotations

import math

import torch

from renderer.core.rays import component_rows

INF = float("inf")


class ParameterError(ValueError):
    """A bad shape parameter. `field` is its key in the scene file (`size`, `file`, ...); `build_shape`
    reports it as `objects[i].shape.<field>: <message>`."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field
        self.message = message


def positive(field: str, value, count: int | None = None):
    """`value` (a number, or a sequence of `count` numbers) checked finite and > 0, else ParameterError."""
    values = [value] if count is None else list(value)
    shown = value if count is None else [float(v) for v in values]
    what = "a positive number" if count is None else f"{count} positive numbers"
    if len(values) != (count or 1) or not all(math.isfinite(v) and v > 0 for v in map(float, values)):
        raise ParameterError(field, f"expected {what}, got {shown}")
    return value


class Shape:
    """Base class; see the module docstring for the contract."""

    type_name = "shape"

    def __init__(self):
        self._cache: dict = {}

    def _param(self, name: str, like: torch.Tensor) -> torch.Tensor:
        """Attribute `name` (a float64 tensor) converted to `like`'s device and dtype, cached until the
        attribute is replaced or edited in place (its identity or version counter changes)."""
        value = getattr(self, name)
        if torch.compiler.is_compiling():  # traced into the graph: a cache check there (a tensor's version
            return value.to(device=like.device, dtype=like.dtype)  # counter) broke the graph at every call
        key, stamp = (name, like.device, like.dtype), (id(value), value._version)
        cached = self._cache.get(key)
        if cached is None or cached[0] != stamp:
            self._cache[key] = cached = (stamp, value.to(device=like.device, dtype=like.dtype))
        return cached[1]

    def intersect(self, o: torch.Tensor, d: torch.Tensor, t_min: float) -> tuple[torch.Tensor, torch.Tensor]:
        if self.soa_native:  # one implementation, so both layouts give the same bits
            return self.intersect_soa(component_rows(o), component_rows(d), t_min)
        raise NotImplementedError

    def surface(self, p: torch.Tensor, aux: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        raise NotImplementedError

    def bounding_sphere(self) -> tuple[torch.Tensor, float] | None:
        return None

    # True where `intersect_soa` is written for (3, N) rows rather than falling back to `intersect`.
    soa_native = False

    def intersect_soa(self, o: torch.Tensor, d: torch.Tensor, t_min: float,
                      need_aux: bool = True) -> tuple[torch.Tensor, torch.Tensor | None]:
        """`intersect` for rays given as (3, N) component rows (origins o, unit directions d): (t, aux), (N,).
        With need_aux=False a shape may return None for aux (shadow rays only need t)."""
        return self.intersect(o.T, d.T, t_min)

    def normal_at(self, p: torch.Tensor, aux: torch.Tensor) -> torch.Tensor:
        """(N, 3) outward unit normals at hit points p (N, 3): `surface` without the texture coordinates."""
        return self.surface(p, aux)[0]


def nearest_positive_soa(t0: torch.Tensor, t1: torch.Tensor, t_min: float) -> torch.Tensor:
    """`nearest_positive` for two candidate rows (N,) with t0 <= t1 (or NaN): t0 if beyond t_min, else t1 if
    beyond t_min, else +inf."""
    return torch.where(t0 > t_min, t0, torch.where(t1 > t_min, t1, INF))


def nearest_positive(t0: torch.Tensor, t1: torch.Tensor, t_min: float) -> torch.Tensor:
    """Smallest of two candidate ray parameters that exceeds t_min (+inf if neither does)."""
    inf = torch.full_like(t0, INF)
    a = torch.where(t0 > t_min, t0, inf)
    b = torch.where(t1 > t_min, t1, inf)
    return torch.minimum(a, b)


def root(disc: torch.Tensor, miss: float = 0.0) -> torch.Tensor:
    """√disc of an intersection test, `miss` where disc < 0 (0: callers mask misses with disc >= 0; NaN: every
    comparison with the root is then False, a miss without a mask).

    Without gradients this is the plain √ (with NaN for `miss=nan`). With gradients the backward pass stays
    finite at misses and grazing rays: √ has an infinite slope at 0, and the zero gradient a masked miss
    receives times that slope is NaN, which the sum over rays would carry to every camera and shape parameter.
    """
    if not disc.requires_grad:
        return disc.sqrt() if math.isnan(miss) else disc.clamp_min(0).sqrt()
    safe = disc.clamp_min(torch.finfo(disc.dtype).tiny).sqrt()
    return torch.where(disc >= 0, safe, torch.full_like(safe, miss))


def quadratic_roots(a: torch.Tensor, half_b: torch.Tensor, c: torch.Tensor,
                    disc: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Real roots of a·t² + 2·half_b·t + c = 0, batched, without cancellation.

    Uses q = −(half_b + sign(half_b)·√disc), roots q/a and c/q (Numerical Recipes §5.6), so a = 0 (a linear
    equation) gives one finite root and ±inf or NaN for the other, which callers mask with their own tests.

    Args:
        disc: half_b² − a·c if the caller has a better-conditioned form of it (default: computed).
    Returns:
        (t0, t1, real): the two roots (order not fixed) and a bool mask of where they are real.
    """
    if disc is None:
        disc = half_b * half_b - a * c
    sign = torch.where(half_b >= 0, torch.ones_like(half_b), -torch.ones_like(half_b))
    q = -(half_b + sign * root(disc))
    return q / a, c / q, disc >= 0


def geometry_key(scene) -> tuple:
    """What caches built from a scene's shapes (the Embree scene, `renderer.tracing.direct`'s normal tables) depend
    on, cheaply: per object its shape (type, identity) and, for each attribute, the tensor's identity,
    storage and in-place version counter (or the plain value). Replacing a shape (the way to move one: shapes
    convert their parameters once, `Shape._param`), giving it new tensors or editing them in place changes
    the key."""
    key = []
    for obj in scene.objects:
        items = [type(obj.shape).__name__, id(obj.shape), id(obj.material)]
        for name, value in sorted(vars(obj.shape).items()):
            if isinstance(value, torch.Tensor):
                items.append((name, id(value), value.data_ptr(), value._version, tuple(value.shape)))
            elif isinstance(value, (int, float, str, bool, tuple)) or value is None:
                items.append((name, value))
        key.append(tuple(items))
    return tuple(key)
