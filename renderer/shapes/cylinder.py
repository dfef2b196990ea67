"""Cylinder: closed right circular cylinder (side and two caps).

Scene-file keys:

| key | kind | default | meaning |
|---|---|---|---|
| `center` | vec3 | required | centre of the base cap, scene units |
| `axis` | vec3 | required | direction from the base to the top cap (normalised; non-zero) |
| `radius` | float | required | radius, scene units, > 0 |
| `height` | float | required | distance between the caps along the axis, scene units, > 0 |

In the local frame (z along the axis, origin at the centre of the base) the solid is x² + y² ≤ r²,
0 ≤ z ≤ h. `aux`: 0 side, 1 base cap (normal −axis), 2 top cap (normal +axis). Texture coordinates
(scene units): on the side (r·φ, z) with φ = atan2(y, x) ∈ (−π, π] (arc length around the axis, height
along it); on the caps the local (x, y). The local x, y directions are an arbitrary completion of the axis.
"""
from __future__ import annotations

import math

import torch

from .base import INF, positive, quadratic_roots
from .placed import PlacedShape, frame_from_axis

SIDE, BASE, TOP = 0, 1, 2


def cap_hits(o_l, d_l, z_cap: float, radius: float, t_min: float) -> torch.Tensor:
    """(N,) ray parameter where local rays cross the disc z = z_cap, x² + y² ≤ radius² (+inf if not)."""
    dz = d_l[:, 2]
    parallel = dz == 0
    t = (z_cap - o_l[:, 2]) / torch.where(parallel, torch.ones_like(dz), dz)
    xy = o_l[:, :2] + t[:, None] * d_l[:, :2]
    inside = (xy * xy).sum(-1) <= radius * radius
    return torch.where(inside & ~parallel & (t > t_min), t, torch.full_like(t, INF))


def cap_hits_rows(o_l, d_l, z_cap: float, radius: float, t_min: float) -> torch.Tensor:
    """`cap_hits` for local rays given as (3, N) component rows."""
    dz = d_l[2]
    parallel = dz == 0
    t = (z_cap - o_l[2]) / torch.where(parallel, 1.0, dz)
    x, y = o_l[0] + t * d_l[0], o_l[1] + t * d_l[1]
    inside = x * x + y * y <= radius * radius
    return torch.where(inside & ~parallel & (t > t_min), t, INF)


def nearest_of_rows(candidates: list[torch.Tensor], labels: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
    """`nearest_of` by a chain of minima (the first of equal candidates wins, as there)."""
    t, which = candidates[0], torch.full_like(candidates[0], labels[0], dtype=torch.long)
    for c, label in zip(candidates[1:], labels[1:]):
        closer = c < t
        t, which = torch.where(closer, c, t), torch.where(closer, label, which)
    return t, which


def side_hits_rows(o_l, d_l, t0, t1, real, t_min: float, height: float) -> list[torch.Tensor]:
    """The two roots on a surface of revolution kept where they are real, beyond t_min and 0 <= z <= height."""
    out = []
    for t in (t0, t1):
        z = o_l[2] + t * d_l[2]
        out.append(torch.where(real & (t > t_min) & (z >= 0) & (z <= height), t, INF))
    return out


def nearest_of(candidates: list[torch.Tensor], labels: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
    """Smallest of several (N,) candidate ray parameters and the label (aux) of the one chosen."""
    t, which = torch.stack(candidates, -1).min(-1)
    return t, torch.tensor(labels, device=t.device)[which]


def side_uv(p_l: torch.Tensor, radius: float) -> torch.Tensor:
    """(N, 2) (arc length r·φ, height z) on a surface of revolution about local z."""
    return torch.stack([radius * torch.atan2(p_l[:, 1], p_l[:, 0]), p_l[:, 2]], -1)


def axial_normal(sign: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """(N, 3) local normals ±z (sign (N,) of ±1) for cap hits."""
    n = torch.zeros_like(like)
    n[:, 2] = sign
    return n


class Cylinder(PlacedShape):
    """Closed cylinder with base centre `center`, `axis`, `radius`, `height` (see module docstring)."""

    type_name = "cylinder"

    def __init__(self, center, axis, radius: float, height: float):
        super().__init__(center, frame_from_axis(axis))
        self.radius = float(positive("radius", radius))
        self.height = float(positive("height", height))

    soa_native = True

    def intersect_soa(self, o, d, t_min, need_aux: bool = True):
        o_l, d_l = self._rays_to_local_soa(o, d)
        r, h = self.radius, self.height
        (ox, oy, _), (dx, dy, _) = o_l, d_l
        a = dx * dx + dy * dy
        cross = ox * dy - oy * dx
        t0, t1, real = quadratic_roots(a, ox * dx + oy * dy, ox * ox + oy * oy - r * r, a * r * r - cross * cross)
        sides = side_hits_rows(o_l, d_l, t0, t1, real, t_min, h)
        caps = [cap_hits_rows(o_l, d_l, 0.0, r, t_min), cap_hits_rows(o_l, d_l, h, r, t_min)]
        return nearest_of_rows(sides + caps, [SIDE, SIDE, BASE, TOP])

    def normal_rows(self, p, aux):
        """(3, N) outward normals at hit points given as (3, N) component rows."""
        x, y, _ = self._points_to_local_soa(p)
        rho = (x * x + y * y).sqrt().clamp_min(1e-30)
        side = aux == SIDE
        zero = torch.zeros_like(x)
        n_l = torch.stack([torch.where(side, x / rho, zero), torch.where(side, y / rho, zero),
                           torch.where(side, zero, torch.where(aux == TOP, 1.0, -1.0).to(p.dtype))])
        return self._param("world_from_local", p) @ n_l

    def intersect_reference(self, o, d, t_min):
        """The (N, 3) form of `intersect` kept as the reference of the (3, N) fast path (see tests)."""
        o_l, d_l = self._rays_to_local(o, d)
        r, h = self.radius, self.height
        ox, oy, oz = o_l.unbind(-1)
        dx, dy, dz = d_l.unbind(-1)
        a = dx * dx + dy * dy
        # Discriminant a·r² − (o × d)_z²: the Lagrange identity avoids cancelling b² against a·c.
        cross = ox * dy - oy * dx
        t0, t1, real = quadratic_roots(a, ox * dx + oy * dy, ox * ox + oy * oy - r * r, a * r * r - cross * cross)
        sides = []
        for t in (t0, t1):
            z = oz + t * dz
            ok = real & (t > t_min) & (z >= 0) & (z <= h)
            sides.append(torch.where(ok, t, torch.full_like(t, INF)))
        base = cap_hits(o_l, d_l, 0.0, r, t_min)
        top = cap_hits(o_l, d_l, h, r, t_min)
        return nearest_of(sides + [base, top], [SIDE, SIDE, BASE, TOP])

    def surface(self, p, aux):
        p_l = self._points_to_local(p)
        side = (aux == SIDE)[:, None]
        radial = torch.cat([p_l[:, :2], torch.zeros_like(p_l[:, 2:])], -1)
        radial = radial / torch.linalg.vector_norm(radial, dim=-1, keepdim=True).clamp_min(1e-30)
        cap = axial_normal(torch.where(aux == TOP, 1.0, -1.0).to(p), p)
        n_l = torch.where(side, radial, cap)
        uv = torch.where(side, side_uv(p_l, self.radius), p_l[:, :2])
        return self._vectors_to_world(n_l), uv

    def bounding_sphere(self):
        center = self.origin + self.world_from_local[:, 2] * (self.height / 2)
        return center, math.hypot(self.radius, self.height / 2)
