"""Rectangle: a finite piece of its local z = 0 plane, rotated and moved into place.

Scene-file keys:

| key | kind | default | meaning |
|---|---|---|---|
| `center` | vec3 | required | centre, scene units |
| `size` | vec2 | required | [sx, sy]: extent along local x and local y, scene units, > 0 |
| `rotation_deg` | vec3 | [0, 0, 0] | Euler angles [rx, ry, rz] in degrees; R = Rz·Ry·Rx maps local to world |

x_world = R · x_local + center; the rectangle is |x_local| ≤ sx/2, |y_local| ≤ sy/2, z_local = 0 and its
normal is R · (0, 0, 1) (rays hit both sides; the integrator faces the normal towards the ray).

Texture coordinates (scene units): u = x_local + sx/2, v = y_local + sy/2, so (0, 0) is the corner at
local (−sx/2, −sy/2), u runs along local x and v along local y. An image texture of `size` [sx, sy] then
covers the rectangle once with its first column at local x = −sx/2 and its first row at local
y = −sy/2; with no rotation, seen by the default camera (x right, y down, looking along +z), the image
appears upright and unmirrored — the layout of a calibration target whose X runs along its columns and Y
along its rows.
"""
from __future__ import annotations

import torch

from renderer.core.transforms import euler_xyz_deg
from .base import INF, positive
from .placed import PlacedShape


class Rectangle(PlacedShape):
    """Rectangle of `size` [sx, sy] in the local z = 0 plane (see module docstring)."""

    type_name = "rectangle"

    def __init__(self, center, size, rotation_deg=(0.0, 0.0, 0.0)):
        super().__init__(center, euler_xyz_deg(rotation_deg))
        positive("size", size, 2)
        self.half = torch.as_tensor(size, dtype=torch.float64) / 2
        self.normal = self.world_from_local[:, 2].clone()

    def intersect_reference(self, o, d, t_min):
        """The (N, 3) form of `intersect` kept as the reference of the (3, N) fast path (see tests)."""
        o_l, d_l = self._rays_to_local(o, d)
        dz = d_l[:, 2]
        parallel = dz == 0
        t = -o_l[:, 2] / torch.where(parallel, torch.ones_like(dz), dz)
        xy = o_l[:, :2] + t[:, None] * d_l[:, :2]
        inside = (xy.abs() <= self._param("half", o)).all(-1)
        hit = inside & ~parallel & (t > t_min)
        return torch.where(hit, t, torch.full_like(t, INF)), torch.zeros_like(t, dtype=torch.long)

    soa_native = True

    def intersect_soa(self, o, d, t_min, need_aux: bool = True):
        o_l, d_l = self._rays_to_local_soa(o, d)
        half = self._param("half", o)
        dz = d_l[2]
        parallel = dz == 0
        t = -o_l[2] / torch.where(parallel, 1.0, dz)
        inside = ((o_l[0] + t * d_l[0]).abs() <= half[0]) & ((o_l[1] + t * d_l[1]).abs() <= half[1])
        hit = inside & ~parallel & (t > t_min)
        return torch.where(hit, t, INF), torch.zeros(o.shape[1], dtype=torch.long, device=o.device)

    def uv_rows(self, p, aux):
        """(2, N) texture coordinates (as `surface`) at hit points given as (3, N) component rows."""
        return self._points_to_local_soa(p)[:2] + self._param("half", p)[:, None]

    def normal_rows(self, p, aux):
        """(3, N) normals (the constant one) at hit points given as (3, N) component rows."""
        return self._param("normal", p)[:, None].expand_as(p)

    def normal_at(self, p, aux):
        return self._param("normal", p).expand_as(p)

    def surface(self, p, aux):
        uv = self._points_to_local(p)[:, :2] + self._param("half", p)
        return self._param("normal", p).expand_as(p), uv

    def bounding_sphere(self):
        return self.origin, float(torch.linalg.vector_norm(self.half))
