"""Sphere: centre and radius."""
from __future__ import annotations

import math

import torch

from .base import INF, Shape, nearest_positive, nearest_positive_soa, positive, root


class Sphere(Shape):
    """Sphere of `radius` about `center` (scene units)."""

    type_name = "sphere"

    def __init__(self, center, radius: float):
        super().__init__()
        positive("radius", radius)
        self.center = torch.as_tensor(center, dtype=torch.float64)
        self.radius = float(radius)

    def intersect_reference(self, o, d, t_min):
        """The (N, 3) form of `intersect` kept as the reference of the (3, N) fast path (see tests)."""
        c = self._param("center", o)
        oc = o - c
        b = (oc * d).sum(-1)
        # r² − |oc − b d|² instead of b² − (|oc|² − r²): no cancellation for distant, small spheres.
        perp = oc - b[..., None] * d
        disc = self.radius**2 - (perp * perp).sum(-1)
        sq = root(disc)
        t = nearest_positive(-b - sq, -b + sq, t_min)
        t = torch.where(disc >= 0, t, torch.full_like(t, INF))
        return t, torch.zeros_like(t, dtype=torch.long)

    soa_native = True

    def intersect_soa(self, o, d, t_min, need_aux: bool = True):
        c = self._param("center", o)
        ox, oy, oz = o[0] - c[0], o[1] - c[1], o[2] - c[2]
        dx, dy, dz = d[0], d[1], d[2]
        b = ox * dx + oy * dy + oz * dz
        px, py, pz = ox - b * dx, oy - b * dy, oz - b * dz
        disc = self.radius**2 - (px * px + py * py + pz * pz)
        sq = root(disc, math.nan)  # NaN where disc < 0: every comparison below is then False, a miss
        return nearest_positive_soa(-b - sq, -b + sq, t_min), torch.zeros(o.shape[1], dtype=torch.long, device=o.device)

    def normal_rows(self, p, aux):
        """(3, N) outward normals at hit points given as (3, N) component rows."""
        return (p - self._param("center", p)[:, None]) / self.radius

    def normal_at(self, p, aux):
        return (p - self._param("center", p)) / self.radius

    def surface(self, p, aux):
        n = (p - self._param("center", p)) / self.radius
        phi = torch.atan2(n[..., 0], n[..., 2])
        theta = torch.acos(n[..., 1].clamp(-1, 1))
        return n, torch.stack([phi * self.radius, theta * self.radius], -1)

    def bounding_sphere(self):
        return self.center, self.radius
