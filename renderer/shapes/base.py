"""The shape interface: batched ray intersection, surface normal and texture coordinates.

Every shape answers three calls on flat batches of N rays or points (world frame, scene units):
- `intersect(o, d, t_min)` -> (t, aux): nearest hit with t > t_min, +inf on a miss; aux (long) is what
  `surface` needs to find the normal (a face or triangle index; 0 when unused);
- `surface(p, aux)` -> (normal, uv): outward unit normal (N, 3) and texture coordinates (N, 2) in scene
  units (so a checker `size` means the same length on every shape);
- `bounding_sphere()` -> (center (3,), radius) or None for unbounded shapes; the scene uses it to send each
  shape only the rays that can reach it.
Shapes keep their parameters in float64 and convert them once per device/dtype (`_param`).
"""
from __future__ import annotations

import torch

INF = float("inf")


class Shape:
    """Base class; see the module docstring for the contract."""

    type_name = "shape"

    def __init__(self):
        self._cache: dict = {}

    def _param(self, name: str, like: torch.Tensor) -> torch.Tensor:
        """Attribute `name` (a float64 tensor) converted to `like`'s device and dtype, cached."""
        key = (name, like.device, like.dtype)
        if key not in self._cache:
            self._cache[key] = getattr(self, name).to(device=like.device, dtype=like.dtype)
        return self._cache[key]

    def intersect(self, o: torch.Tensor, d: torch.Tensor, t_min: float) -> tuple[torch.Tensor, torch.Tensor]:
        raise NotImplementedError

    def surface(self, p: torch.Tensor, aux: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        raise NotImplementedError

    def bounding_sphere(self) -> tuple[torch.Tensor, float] | None:
        return None


def nearest_positive(t0: torch.Tensor, t1: torch.Tensor, t_min: float) -> torch.Tensor:
    """Smallest of two candidate ray parameters that exceeds t_min (+inf if neither does)."""
    inf = torch.full_like(t0, INF)
    a = torch.where(t0 > t_min, t0, inf)
    b = torch.where(t1 > t_min, t1, inf)
    return torch.minimum(a, b)
