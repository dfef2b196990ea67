"""Cone: closed right circular cone (side and base cap), apex at base + axis·height.

Scene-file keys:

| key | kind | default | meaning |
|---|---|---|---|
| `center` | vec3 | required | centre of the base disc, scene units |
| `axis` | vec3 | required | direction from the base towards the apex (normalised; non-zero) |
| `radius` | float | required | base radius, scene units, > 0 |
| `height` | float | required | distance from the base to the apex, scene units, > 0 |

In the local frame (z along the axis, origin at the base centre) the solid is x² + y² ≤ (k·(h − z))²,
0 ≤ z ≤ h, with k = r/h. `aux`: 0 side, 1 base cap (normal −axis). The side normal is ∝ (x/ρ, y/ρ, k),
ρ = √(x² + y²), and +axis at the apex itself. Texture coordinates as for the cylinder: (r·φ, z) on the side,
local (x, y) on the base.
"""
from __future__ import annotations

import math

import torch

from .base import INF, positive, quadratic_roots
from .cylinder import (BASE, SIDE, axial_normal, cap_hits, cap_hits_rows, nearest_of, nearest_of_rows,
                       side_hits_rows, side_uv)
from .placed import PlacedShape, frame_from_axis


class Cone(PlacedShape):
    """Closed cone with base centre `center`, `axis`, base `radius`, `height` (see module docstring)."""

    type_name = "cone"

    def __init__(self, center, axis, radius: float, height: float):
        super().__init__(center, frame_from_axis(axis))
        self.radius = float(positive("radius", radius))
        self.height = float(positive("height", height))
        self.slope = self.radius / self.height

    soa_native = True

    def intersect_soa(self, o, d, t_min, need_aux: bool = True):
        o_l, d_l = self._rays_to_local_soa(o, d)
        h, k2 = self.height, self.slope**2
        (ox, oy, oz), (dx, dy, dz) = o_l, d_l
        w = h - oz
        a = dx * dx + dy * dy - k2 * dz * dz
        half_b = ox * dx + oy * dy + k2 * w * dz
        c = ox * ox + oy * oy - k2 * w * w
        t0, t1, real = quadratic_roots(a, half_b, c)
        sides = side_hits_rows(o_l, d_l, t0, t1, real, t_min, h)
        return nearest_of_rows(sides + [cap_hits_rows(o_l, d_l, 0.0, self.radius, t_min)], [SIDE, SIDE, BASE])

    def normal_rows(self, p, aux):
        """(3, N) outward normals at hit points given as (3, N) component rows (+axis at the apex)."""
        x, y, _ = self._points_to_local_soa(p)
        rho = (x * x + y * y).sqrt()
        sz = self.slope * rho
        length = (x * x + y * y + sz * sz).sqrt()
        inv = 1 / length.clamp_min(1e-30)
        apex = length > 0
        side = aux == SIDE
        one, zero = torch.ones_like(x), torch.zeros_like(x)
        nx = torch.where(side & apex, x * inv, zero)
        ny = torch.where(side & apex, y * inv, zero)
        nz = torch.where(side, torch.where(apex, sz * inv, one), -one)
        return self._param("world_from_local", p) @ torch.stack([nx, ny, nz])

    def intersect_reference(self, o, d, t_min):
        """The (N, 3) form of `intersect` kept as the reference of the (3, N) fast path (see tests)."""
        o_l, d_l = self._rays_to_local(o, d)
        h, k2 = self.height, self.slope**2
        ox, oy, oz = o_l.unbind(-1)
        dx, dy, dz = d_l.unbind(-1)
        w = h - oz  # height below the apex
        # (ox + t dx)² + (oy + t dy)² = k² (w − t dz)²: the double cone; the z range keeps one nappe.
        a = dx * dx + dy * dy - k2 * dz * dz
        half_b = ox * dx + oy * dy + k2 * w * dz
        c = ox * ox + oy * oy - k2 * w * w
        t0, t1, real = quadratic_roots(a, half_b, c)
        sides = []
        for t in (t0, t1):
            z = oz + t * dz
            ok = real & (t > t_min) & (z >= 0) & (z <= h)
            sides.append(torch.where(ok, t, torch.full_like(t, INF)))
        base = cap_hits(o_l, d_l, 0.0, self.radius, t_min)
        return nearest_of(sides + [base], [SIDE, SIDE, BASE])

    def surface(self, p, aux):
        p_l = self._points_to_local(p)
        rho = torch.linalg.vector_norm(p_l[:, :2], dim=-1, keepdim=True)
        slanted = torch.cat([p_l[:, :2], self.slope * rho], -1)
        length = torch.linalg.vector_norm(slanted, dim=-1, keepdim=True)
        up = axial_normal(torch.ones_like(p_l[:, 0]), p)
        side_n = torch.where(length > 0, slanted / length.clamp_min(1e-30), up)
        side = (aux == SIDE)[:, None]
        n_l = torch.where(side, side_n, -up)
        uv = torch.where(side, side_uv(p_l, self.radius), p_l[:, :2])
        return self._vectors_to_world(n_l), uv

    def bounding_sphere(self):
        # Smallest sphere through the base rim and the apex, centred on the axis at z0 ≥ 0.
        r, h = self.radius, self.height
        z0 = max(0.0, (h * h - r * r) / (2 * h))
        return self.origin + self.world_from_local[:, 2] * z0, math.hypot(r, z0)
