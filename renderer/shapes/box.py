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
from .base import positive
from .placed import PlacedShape
from .polyhedron import clip_convex, coordinates_across


class Box(PlacedShape):
    """Cuboid of edge lengths `size` centred on `center`, rotated by `rotation_deg` (see module docstring)."""

    type_name = "box"

    def __init__(self, center, size, rotation_deg=(0.0, 0.0, 0.0)):
        super().__init__(center, euler_xyz_deg(rotation_deg))
        positive("size", size, 3)
        self.half = torch.as_tensor(size, dtype=torch.float64) / 2

    def intersect(self, o, d, t_min):
        # The slab method written as six planes ±e_a·x ≤ half_a in the local frame, numbered as the faces.
        o_l, d_l = self._rays_to_local(o, d)
        half = self._param("half", o)
        num = torch.stack([half + o_l, half - o_l], -1).flatten(-2)
        den = torch.stack([-d_l, d_l], -1).flatten(-2)
        return clip_convex(num, den, t_min)

    def surface(self, p, aux):
        axis, side = aux // 2, aux % 2
        normal_local = torch.zeros_like(p)
        normal_local.scatter_(-1, axis[:, None], (2 * side - 1)[:, None].to(p.dtype))
        p_corner = self._points_to_local(p) + self._param("half", p)
        return self._vectors_to_world(normal_local), coordinates_across(p_corner, axis)

    def bounding_sphere(self):
        return self.origin, float(torch.linalg.vector_norm(self.half))
