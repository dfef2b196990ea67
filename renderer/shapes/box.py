"""Box: an axis-aligned cuboid in its local frame, rotated and moved into place.

Scene-file keys:

| key | kind | default | meaning |
|---|---|---|---|
| `center` | vec3 | required | centre, scene units |
| `size` | vec3 | required | edge lengths [sx, sy, sz] along the local axes, scene units, > 0 |
| `rotation_deg` | vec3 | [0, 0, 0] | Euler angles [rx, ry, rz] in degrees; R = Rz·Ry·Rx maps local to world |

x_world = R · x_local + center. Faces are numbered 2·axis + side (side 0 at −size/2, 1 at +size/2), so
`aux` 0..5 is −x, +x, −y, +y, −z, +z of the local frame. Texture coordinates on a face are its two other
local coordinates, in increasing axis order, shifted by size/2 so that they run from 0 to the edge
lengths (x-faces (y, z), y-faces (x, z), z-faces (x, y): a z-face maps like a `rectangle`).
"""
from __future__ import annotations

import torch

from ..transforms import euler_xyz_deg
from .base import INF, positive
from .placed import PlacedShape
from .polyhedron import clip_convex, coordinates_across


class Box(PlacedShape):
    """Cuboid of edge lengths `size` centred on `center`, rotated by `rotation_deg` (see module docstring)."""

    type_name = "box"

    def __init__(self, center, size, rotation_deg=(0.0, 0.0, 0.0)):
        super().__init__(center, euler_xyz_deg(rotation_deg))
        positive("size", size, 3)
        self.half = torch.as_tensor(size, dtype=torch.float64) / 2

    def intersect_reference(self, o, d, t_min):
        """The (N, 3) form of `intersect` kept as the reference of the (3, N) fast path (see tests)."""
        # The slab method written as six planes ±e_a·x ≤ half_a in the local frame, numbered as the faces.
        o_l, d_l = self._rays_to_local(o, d)
        half = self._param("half", o)
        num = torch.stack([half + o_l, half - o_l], -1).flatten(-2)
        den = torch.stack([-d_l, d_l], -1).flatten(-2)
        return clip_convex(num, den, t_min)

    soa_native = True

    def intersect_soa(self, o, d, t_min):
        """The same crossings and face numbers as `intersect` (up to ties at edges), as a plain slab test
        per local axis on (3, N) rows: t_enter = max of the per-axis entries, t_exit = min of the exits."""
        o_l, d_l = self._rays_to_local_soa(o, d)
        half = self._param("half", o)
        t_in = t_out = face_in = face_out = None
        for a in range(3):
            oa, da, h = o_l[a], d_l[a], half[a]
            parallel = da == 0
            inv = 1 / torch.where(parallel, 1.0, da)
            t_lo, t_hi = (-h - oa) * inv, (h - oa) * inv
            neg = da < 0  # enters through the + face (side 1) and leaves through the − face
            near, far = torch.where(neg, t_hi, t_lo), torch.where(neg, t_lo, t_hi)
            # A parallel ray is inside the slab everywhere or nowhere.
            outside = parallel & (oa.abs() > h)
            near = torch.where(parallel, torch.where(outside, INF, -INF), near)
            far = torch.where(parallel, torch.where(outside, -INF, INF), far)
            if a == 0:
                t_in, t_out, face_in, face_out = near, far, neg.long(), 1 - neg.long()
            else:
                later, sooner = near > t_in, far < t_out
                t_in, face_in = torch.where(later, near, t_in), torch.where(later, 2 * a + neg.long(), face_in)
                t_out, face_out = torch.where(sooner, far, t_out), torch.where(sooner, 2 * a + 1 - neg.long(), face_out)
        use_in = t_in > t_min
        t = torch.where(use_in, t_in, t_out)
        hit = (t_in <= t_out) & (t > t_min) & (t < INF)
        return torch.where(hit, t, INF), torch.where(hit, torch.where(use_in, face_in, face_out), 0)

    def normal_rows(self, p, aux):
        """(3, N) outward normals at hit points given as (3, N) component rows, from the face index aux."""
        axis, sign = aux // 2, (2 * (aux % 2) - 1).to(p.dtype)
        zero = torch.zeros((), dtype=p.dtype, device=p.device)
        n = torch.stack([torch.where(axis == a, sign, zero) for a in range(3)])
        return n if self.axis_aligned else self._param("world_from_local", p) @ n

    def normal_at(self, p, aux):
        axis, side = aux // 2, aux % 2
        normal_local = torch.zeros_like(p)
        normal_local.scatter_(-1, axis[:, None], (2 * side - 1)[:, None].to(p.dtype))
        return normal_local if self.axis_aligned else self._vectors_to_world(normal_local)

    def surface(self, p, aux):
        axis, side = aux // 2, aux % 2
        normal_local = torch.zeros_like(p)
        normal_local.scatter_(-1, axis[:, None], (2 * side - 1)[:, None].to(p.dtype))
        p_corner = self._points_to_local(p) + self._param("half", p)
        return self._vectors_to_world(normal_local), coordinates_across(p_corner, axis)

    def bounding_sphere(self):
        return self.origin, float(torch.linalg.vector_norm(self.half))
