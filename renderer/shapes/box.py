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

from renderer.core.transforms import euler_xyz_deg
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

    def intersect_soa(self, o, d, t_min, need_aux: bool = True):
        """The same crossings and face numbers as `intersect_reference`, as a plain slab test on (3, N) rows:
        per local axis the two plane distances (−half − o)/d and (half − o)/d, their min and max; t_enter the
        largest min, t_exit the smallest max. A ray parallel to an axis is inside that slab everywhere, faces included, or nowhere. The face index (aux) is worked out only
        for the winning axis, and not at all with `need_aux=False` (shadow rays)."""
        o_l, d_l = self._rays_to_local_soa(o, d)
        half = self._param("half", o)
        inv = 1 / d_l
        t_lo = (-half[:, None] - o_l) * inv  # (3, N) distances to the − faces
        t_hi = (half[:, None] - o_l) * inv   # and to the + faces
        near, far = torch.minimum(t_lo, t_hi), torch.maximum(t_lo, t_hi)
        # Parallel to an axis: inside that slab everywhere (on its faces too) or nowhere, as the reference.
        # (Always applied: a data-dependent branch would need a host sync.)
        parallel, inside = d_l == 0, o_l.abs() <= half[:, None]
        near = torch.where(parallel, torch.where(inside, -INF, INF), near)
        far = torch.where(parallel, torch.where(inside, INF, -INF), far)
        t_in = torch.maximum(torch.maximum(near[0], near[1]), near[2])
        t_out = torch.minimum(torch.minimum(far[0], far[1]), far[2])
        use_in = t_in > t_min
        t = torch.where(use_in, t_in, t_out)
        hit = (t_in <= t_out) & (t > t_min) & (t < INF)
        t = torch.where(hit, t, INF)
        if not need_aux:
            return t, None
        neg = d_l < 0  # (3, N): enters through the + face (side 1), leaves through the − face
        axis_in = torch.where(near[0] == t_in, 0, torch.where(near[1] == t_in, 1, 2))
        axis_out = torch.where(far[0] == t_out, 0, torch.where(far[1] == t_out, 1, 2))
        side_in = neg.gather(0, axis_in[None])[0].long()
        side_out = 1 - neg.gather(0, axis_out[None])[0].long()
        face = torch.where(use_in, 2 * axis_in + side_in, 2 * axis_out + side_out)
        return t, torch.where(hit, face, 0)

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
