"""Triangle mesh read from a Wavefront OBJ file, placed like a box.

Scene-file keys:

| key | kind | default | meaning |
|---|---|---|---|
| `file` | str | required | OBJ file, relative to the scene file's folder |
| `center` | vec3 | [0, 0, 0] | where the file's origin goes, scene units |
| `scale` | float or vec3 | [1, 1, 1] | uniform or per-axis scale applied in the file's frame, non-zero |
| `rotation_deg` | vec3 | [0, 0, 0] | Euler angles [rx, ry, rz] in degrees; R = Rz·Ry·Rx |

x_world = R · (scale ⊙ x_file) + center. Only `v` (vertex) and `f` (face) records are read: polygons are
split into fans of triangles, `f` entries may be `i`, `i/t`, `i//n` or `i/t/n` (1-based; negative indices
count back from the last vertex read) and everything else (vt, vn, groups, materials, comments) is ignored.
Triangles of zero area are dropped.

Normals are flat: the normal of triangle (a, b, c) is (b − a) × (c − a) normalised, so counter-clockwise
faces seen from outside (the OBJ convention) give outward normals; a scale with an odd number of negative
factors flips them back. `aux` is the triangle's index, counting kept triangles only. Texture coordinates
(scene units) are the two scaled file-frame coordinates across the triangle's dominant normal axis, as for
the polyhedron, so coplanar triangles map continuously.

Cost: brute force, every ray against every triangle (Möller–Trumbore), in chunks of triangles so that
memory stays near `_PAIRS_PER_CHUNK` ray-triangle pairs: O(N·T) time. Fine for the few hundred triangles
of a test object; large meshes need an acceleration structure, which this does not have.
"""
from __future__ import annotations

import torch

from renderer.core.transforms import euler_xyz_deg
from camio.checks import FLOAT32_MAX
from camio.errors import os_reason
from .base import INF, ParameterError, Shape
from .polyhedron import coordinates_across

# Ray-triangle pairs evaluated at once. The loop body holds about four (pairs, 3) temporaries: near 100 MB
# in float64, 50 MB in float32 (more only when a batch has more rays than this, one triangle at a time).
_PAIRS_PER_CHUNK = 1 << 20


def load_obj(path: str) -> tuple[torch.Tensor, torch.Tensor]:
    """Vertices (V, 3) float64 and triangles (T, 3) long (0-based) from an OBJ file.

    Raises:
        ParameterError (`file`): unreadable file, malformed record (with its line number), index out of
        range, or no faces.
    """
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            lines = f.readlines()
    except OSError as e:
        raise ParameterError("file", f"cannot read {path}: {os_reason(e)}") from None
    vertices, triangles = [], []
    for number, line in enumerate(lines, 1):
        words = line.split("#", 1)[0].split()
        if not words:
            continue

        def bad(why):
            return ParameterError("file", f"{path}:{number}: {why}: {line.strip()!r}")

        if words[0] == "v":
            try:
                xyz = [float(w) for w in words[1:4]]
            except ValueError:
                raise bad("expected numbers after 'v'") from None
            if len(xyz) != 3:
                raise bad("expected 3 coordinates after 'v'")
            if not all(abs(c) <= FLOAT32_MAX for c in xyz):  # NaN fails too
                raise bad("a vertex coordinate is NaN, infinite or beyond float32's range")
            vertices.append(xyz)
        elif words[0] == "f":
            if len(words) < 4:
                raise bad("a face needs at least 3 vertices")
            corners = []
            for w in words[1:]:
                try:
                    i = int(w.split("/")[0])
                except ValueError:
                    raise bad(f"bad vertex index {w!r}") from None
                i = i - 1 if i > 0 else len(vertices) + i
                if not 0 <= i < len(vertices):
                    raise bad(f"vertex index {w.split('/')[0]} out of range (have {len(vertices)} vertices)")
                corners.append(i)
            triangles.extend([corners[0], corners[j], corners[j + 1]] for j in range(1, len(corners) - 1))
    if not triangles:
        raise ParameterError("file", f"{path}: no faces ('f' records) found")
    return torch.tensor(vertices, dtype=torch.float64), torch.tensor(triangles, dtype=torch.long)


class Mesh(Shape):
    """Triangles placed in the world (see module docstring).

    Args:
        vertices: (V, 3) in the file frame; triangles: (T, 3) 0-based vertex indices.
        center, scale, rotation_deg: placement, x_world = R · (scale ⊙ x_file) + center.
    """

    type_name = "mesh"

    def __init__(self, vertices, triangles, center=(0.0, 0.0, 0.0), scale=(1.0, 1.0, 1.0),
                 rotation_deg=(0.0, 0.0, 0.0)):
        super().__init__()
        scale = torch.as_tensor(scale, dtype=torch.float64).reshape(-1)
        if scale.numel() == 1:
            scale = scale.expand(3)
        if scale.numel() != 3 or not bool((scale != 0).all() & torch.isfinite(scale).all()):
            raise ParameterError("scale", f"expected a non-zero number or 3 non-zero numbers, got {scale.tolist()}")
        R = euler_xyz_deg(rotation_deg)
        v_scaled = torch.as_tensor(vertices, dtype=torch.float64) * scale
        tri = torch.as_tensor(triangles, dtype=torch.long)
        corners = v_scaled[tri] @ R.T + torch.as_tensor(center, dtype=torch.float64)  # (T, 3 corners, 3)
        e1, e2 = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
        cross = torch.linalg.cross(e1, e2)
        area2 = torch.linalg.vector_norm(cross, dim=-1, keepdim=True)
        # |e1 × e2| = |e1|·|e2|·sin(angle): drop triangles whose corners are (numerically) collinear.
        keep = area2[:, 0] > 1e-12 * torch.linalg.vector_norm(e1, dim=-1) * torch.linalg.vector_norm(e2, dim=-1)
        if not bool(keep.any()):
            raise ParameterError("file", "every triangle has zero area")
        flip = -1.0 if float(scale.prod()) < 0 else 1.0
        self.v0, self.e1, self.e2 = corners[keep, 0], e1[keep], e2[keep]
        self.normals = flip * cross[keep] / area2[keep]
        self.center = torch.as_tensor(center, dtype=torch.float64)
        self.world_from_scaled = R
        # Each triangle's uv axes follow its normal in the scaled file frame, so textures turn with the mesh.
        self.uv_axis = (self.normals @ R).abs().argmax(-1)
        points = corners[keep].reshape(-1, 3)
        lo, hi = points.min(0).values, points.max(0).values
        self._sphere_center = (lo + hi) / 2
        self._sphere_radius = float(torch.linalg.vector_norm(points - self._sphere_center, dim=-1).max())

    @classmethod
    def from_obj(cls, path: str, **placement) -> "Mesh":
        vertices, triangles = load_obj(path)
        return cls(vertices, triangles, **placement)

    @property
    def num_triangles(self) -> int:
        return self.v0.shape[0]

    def intersect(self, o, d, t_min):
        """Möller–Trumbore against every triangle, chunked over triangles (the hot loop of this shape)."""
        n = o.shape[0]
        v0_all, e1_all, e2_all = (self._param(name, o) for name in ("v0", "e1", "e2"))
        t_best = torch.full((n,), INF, dtype=o.dtype, device=o.device)
        aux = torch.zeros(n, dtype=torch.long, device=o.device)
        dd, oo = d[:, None], o[:, None]  # (N, 1, 3) against (1, C, 3) triangles
        chunk = max(1, _PAIRS_PER_CHUNK // max(n, 1))
        for start in range(0, self.num_triangles, chunk):
            v0, e1, e2 = (x[start:start + chunk][None] for x in (v0_all, e1_all, e2_all))
            # Barycentric (u, v) and t of o + t·d = v0 + u·e1 + v·e2 by Cramer's rule (Möller–Trumbore 1997).
            p = torch.linalg.cross(dd, e2.expand(n, -1, -1))
            det = (e1 * p).sum(-1)
            inv = 1 / torch.where(det == 0, torch.ones_like(det), det)
            s = oo - v0
            u = (s * p).sum(-1) * inv
            q = torch.linalg.cross(s, e1.expand(n, -1, -1))
            v = (dd * q).sum(-1) * inv
            t = (e2 * q).sum(-1) * inv
            ok = (det != 0) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > t_min)
            t_chunk, which = torch.where(ok, t, torch.full_like(t, INF)).min(-1)
            closer = t_chunk < t_best
            t_best = torch.where(closer, t_chunk, t_best)
            aux = torch.where(closer, which + start, aux)
        return t_best, aux

    def surface(self, p, aux):
        p_scaled = (p - self._param("center", p)) @ self._param("world_from_scaled", p)
        uv = coordinates_across(p_scaled, self.uv_axis.to(p.device)[aux])
        return self._param("normals", p)[aux], uv

    def bounding_sphere(self):
        return self._sphere_center, self._sphere_radius
