"""Shapes defined in a local frame and placed in the world by a rotation and a translation.

x_world = world_from_local · x_local + origin (column vectors). Rays are moved to the local frame once per
call, the local geometry is simple there (axis-aligned box, z = 0 rectangle, z-axis cylinder), and normals
are moved back with the same rotation.
"""
from __future__ import annotations

import torch

from .base import ParameterError, Shape
from .plane import tangent_frame


class PlacedShape(Shape):
    """A shape with a local frame.

    Attributes:
        origin: (3,) float64, the local origin in the world, scene units.
        world_from_local: (3, 3) float64 rotation; its columns are the local axes in the world.
    """

    def __init__(self, origin, world_from_local: torch.Tensor):
        super().__init__()
        self.origin = torch.as_tensor(origin, dtype=torch.float64).reshape(3)
        self.world_from_local = world_from_local.to(torch.float64)
        # Precomputed for the (3, N) fast path: the local frame is the world's, shifted (no rotation needed).
        self.axis_aligned = bool(torch.equal(self.world_from_local, torch.eye(3, dtype=torch.float64)))
        self.local_from_world = self.world_from_local.T.contiguous()
        self.origin_column = self.origin[:, None].clone()

    def _rays_to_local(self, o: torch.Tensor, d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(N, 3) world origins and directions -> local ones (directions keep their length)."""
        R = self._param("world_from_local", o)
        return (o - self._param("origin", o)) @ R, d @ R

    def _rays_to_local_soa(self, o: torch.Tensor, d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(3, N) world origins and directions -> local ones, (3, N) each (directions keep their length)."""
        o = o - self._param("origin_column", o)
        if self.axis_aligned:
            return o, d
        R = self._param("local_from_world", o)
        return R @ o, R @ d

    def _points_to_local_soa(self, p: torch.Tensor) -> torch.Tensor:
        """(3, N) world points -> (3, N) local points."""
        p = p - self._param("origin_column", p)
        return p if self.axis_aligned else self._param("local_from_world", p) @ p

    def _points_to_local(self, p: torch.Tensor) -> torch.Tensor:
        return (p - self._param("origin", p)) @ self._param("world_from_local", p)

    def _vectors_to_world(self, v_local: torch.Tensor) -> torch.Tensor:
        return v_local @ self._param("world_from_local", v_local).T


def frame_from_axis(axis) -> torch.Tensor:
    """(3, 3) float64 rotation world_from_local whose local z is the unit `axis` (ParameterError if zero).

    The local x and y are an arbitrary right-handed completion; they only orient texture coordinates.
    """
    a = torch.as_tensor(axis, dtype=torch.float64).reshape(3)
    length = float(torch.linalg.vector_norm(a))
    if not length > 0:
        raise ParameterError("axis", f"expected a non-zero direction, got {list(map(float, a))}")
    z = a / length
    x, y = tangent_frame(z)
    return torch.stack([x, y, z], dim=1)
