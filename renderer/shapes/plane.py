"""Infinite plane through a point with a normal."""
from __future__ import annotations

import torch

from renderer.core.rays import normalize
from .base import INF, ParameterError, Shape


def tangent_frame(n: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Two unit vectors completing the unit normal n (float64, shape (3,)) to a right-handed frame."""
    helper = torch.tensor([0.0, 0.0, 1.0], dtype=n.dtype) if abs(float(n[2])) < 0.9 else torch.tensor(
        [1.0, 0.0, 0.0], dtype=n.dtype)
    u = normalize(torch.linalg.cross(helper, n))
    return u, torch.linalg.cross(n, u)


class Plane(Shape):
    """The plane {x : n·(x − point) = 0}; its normal is the given `normal` (one-sided only for shading)."""

    type_name = "plane"

    def __init__(self, point, normal):
        super().__init__()
        self.point = torch.as_tensor(point, dtype=torch.float64)
        self.normal = normalize(torch.as_tensor(normal, dtype=torch.float64))
        if float(torch.linalg.vector_norm(self.normal)) < 0.5:
            raise ParameterError("normal", f"expected a non-zero direction, got {list(normal)}")
        self.tangent_u, self.tangent_v = tangent_frame(self.normal)

    def intersect_reference(self, o, d, t_min):
        """The (N, 3) form of `intersect` kept as the reference of the (3, N) fast path (see tests)."""
        n = self._param("normal", o)
        denom = d @ n
        t = ((self._param("point", o) - o) @ n) / torch.where(denom.abs() > 1e-12, denom, torch.full_like(denom, 1e-12))
        t = torch.where((t > t_min) & (denom.abs() > 1e-12), t, torch.full_like(t, INF))
        return t, torch.zeros_like(t, dtype=torch.long)

    soa_native = True

    def intersect_soa(self, o, d, t_min, need_aux: bool = True):
        n, q = self._param("normal", o), self._param("point", o)
        denom = d[0] * n[0] + d[1] * n[1] + d[2] * n[2]
        num = (q[0] - o[0]) * n[0] + (q[1] - o[1]) * n[1] + (q[2] - o[2]) * n[2]
        flat = denom.abs() > 1e-12
        t = num / torch.where(flat, denom, 1e-12)
        return torch.where((t > t_min) & flat, t, INF), torch.zeros(o.shape[1], dtype=torch.long, device=o.device)

    def normal_rows(self, p, aux):
        """(3, N) normals (the constant one) at hit points given as (3, N) component rows."""
        return self._param("normal", p)[:, None].expand_as(p)

    def normal_at(self, p, aux):
        return self._param("normal", p).expand_as(p)

    def surface(self, p, aux):
        rel = p - self._param("point", p)
        uv = torch.stack([rel @ self._param("tangent_u", p), rel @ self._param("tangent_v", p)], -1)
        return self._param("normal", p).expand_as(p), uv
