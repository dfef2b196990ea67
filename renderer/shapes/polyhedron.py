"""Convex polyhedron given as an intersection of half-spaces n·x ≤ c.

Scene-file keys:

| key | kind | default | meaning |
|---|---|---|---|
| `halfspaces` | list | required | `[[nx, ny, nz, c], ...]`, each the half-space n·x ≤ c (scene units) |

The half-spaces must bound a solid (at least four planes whose normals surround the origin); an
unbounded, empty or flat intersection is an error. Redundant planes are allowed. The normal of a hit is
the outward normal n/|n| of the plane the ray crossed (`aux` is that plane's index in the list).
Texture coordinates are the hit point's two coordinates across the plane's dominant normal axis
(x-facing planes: (y, z); y-facing: (x, z); z-facing: (x, y)), in scene units.
"""
from __future__ import annotations

import itertools
import math

import torch

from .base import INF, ParameterError, Shape


def clip_convex(num: torch.Tensor, den: torch.Tensor, t_min: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Nearest crossing of a ray with the boundary of a convex set {x : n_k·x ≤ c_k for all k}.

    Along the ray x = o + t·d each plane gives t·den_k ≤ num_k with den_k = n_k·d, num_k = c_k − n_k·o:
    entering where den < 0 (t ≥ num/den), exiting where den > 0 (t ≤ num/den); a parallel ray (den = 0)
    is inside the slab everywhere if num ≥ 0 and misses otherwise. The ray meets the set on
    [t_enter, t_exit] = [max entering, min exiting] when that interval is non-empty.

    Args:
        num, den: (N, K) per ray and plane.
        t_min: hits must lie beyond this ray parameter.
    Returns:
        t (N,): t_enter if beyond t_min, else t_exit for rays starting inside, else +inf;
        plane (N,) long: the plane index of that crossing (0 on a miss).
    """
    t_enter, k_enter, t_exit, k_exit, met = slab_interval(num, den)
    use_enter = t_enter > t_min
    t = torch.where(use_enter, t_enter, t_exit)
    plane = torch.where(use_enter, k_enter, k_exit)
    hit = met & (t > t_min) & (t < INF)
    return torch.where(hit, t, torch.full_like(t, INF)), torch.where(hit, plane, torch.zeros_like(plane))


def slab_interval(num: torch.Tensor, den: torch.Tensor):
    """The ray-parameter interval inside the intersection of half-spaces t·den_k ≤ num_k (last axis k).

    Returns:
        t_enter, k_enter: the largest entering crossing and its plane; t_exit, k_exit: the smallest exiting
        crossing and its plane; met: t_enter ≤ t_exit (a parallel ray outside one slab gets [+inf, −inf]).
    """
    ratio = num / torch.where(den == 0, torch.ones_like(den), den)
    inf = torch.full_like(ratio, INF)
    outside = (den == 0) & (num < 0)
    t_in = torch.where(outside, inf, torch.where(den < 0, ratio, -inf))
    t_out = torch.where(outside, -inf, torch.where(den > 0, ratio, inf))
    t_enter, k_enter = t_in.max(-1)
    t_exit, k_exit = t_out.min(-1)
    return t_enter, k_enter, t_exit, k_exit, t_enter <= t_exit


def polytope_vertices(normals: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
    """Vertices of the bounded polyhedron {x : normals·x ≤ offsets}.

    Every vertex is where three planes with independent normals meet; brute force over all triples
    (K choose 3 small solves), keeping the points that satisfy every half-space.

    Args:
        normals: (K, 3) unit normals, float64; offsets: (K,) scene units.
    Returns:
        (V, 3) vertices, duplicates included (several triples can meet at one vertex).
    Raises:
        ParameterError (`halfspaces`) if the set is unbounded, empty or flat.
    """
    k = normals.shape[0]
    if k < 4:
        raise ParameterError("halfspaces", f"expected at least 4 half-spaces to bound a solid, got {k}")
    if int(torch.linalg.matrix_rank(normals)) < 3:
        raise ParameterError("halfspaces", "unbounded: all plane normals lie in one plane")
    # Bounded iff no direction r ≠ 0 has n_k·r ≤ 0 for every k. With normals of rank 3 that cone of
    # directions is pointed, so if it is not {0} one of its edges ±(n_i × n_j) lies in it.
    pairs = torch.tensor(list(itertools.combinations(range(k), 2)), dtype=torch.long)
    r = torch.linalg.cross(normals[pairs[:, 0]], normals[pairs[:, 1]])
    length = torch.linalg.vector_norm(r, dim=-1, keepdim=True)
    independent = length[:, 0] > 1e-9
    r = r[independent] / length[independent]
    r = torch.cat([r, -r])
    escaping = ((r @ normals.T) <= 1e-12).all(-1)
    if bool(escaping.any()):
        direction = [round(float(x), 4) for x in r[escaping][0]]
        raise ParameterError("halfspaces", f"unbounded: the solid extends to infinity along {direction}")
    triples = torch.tensor(list(itertools.combinations(range(k), 3)), dtype=torch.long)
    a = normals[triples]
    regular = torch.linalg.det(a).abs() > 1e-9
    a, b = a[regular], offsets[triples[regular]]
    x = torch.linalg.solve(a, b[..., None])[..., 0]
    scale = 1.0 + float(offsets.abs().max())
    feasible = ((x @ normals.T) <= offsets + 1e-9 * scale).all(-1)
    vertices = x[feasible]
    if vertices.shape[0] == 0:
        raise ParameterError("halfspaces", "empty: no point satisfies every half-space")
    # A solid has interior points; the vertices' mean is one unless every vertex shares a plane.
    slack = offsets - normals @ vertices.mean(0)
    if float(slack.min()) <= 1e-7 * scale:
        raise ParameterError("halfspaces", "flat: the half-spaces meet in a set of zero volume")
    return vertices


def coordinates_across(p: torch.Tensor, axis: torch.Tensor) -> torch.Tensor:
    """(N, 2) the two coordinates of p (N, 3) other than `axis` (N,) long, in increasing axis order.

    Used as texture coordinates on faces facing `axis`: x-facing (y, z), y-facing (x, z), z-facing (x, y).
    """
    axis = axis[:, None]
    u_axis = torch.where(axis == 0, 1, 0)
    v_axis = torch.where(axis == 2, 1, 2)
    return torch.cat([p.gather(-1, u_axis), p.gather(-1, v_axis)], -1)


# Half-spaces of one polyhedron: its vertices are solved for over all K-choose-3 triples of planes (341,376
# small solves at this limit, well under a second); 600 half-spaces would need 36 million.
MAX_HALFSPACES = 128


class Polyhedron(Shape):
    """The convex solid {x : n_k·x ≤ c_k for all k}, scene units.

    Args:
        halfspaces: (K, 4) rows [nx, ny, nz, c]; normals need not be unit (each row is rescaled).
    """

    type_name = "polyhedron"

    def __init__(self, halfspaces):
        super().__init__()
        rows = halfspaces.tolist() if isinstance(halfspaces, torch.Tensor) else list(halfspaces)
        if len(rows) > MAX_HALFSPACES:
            raise ParameterError("halfspaces", f"expected at most {MAX_HALFSPACES} half-spaces, got {len(rows)} "
                                               "(the vertices are found over all triples of planes)")
        for i, row in enumerate(rows):
            numbers = isinstance(row, (list, tuple)) and all(
                isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in row)
            if not numbers or len(row) != 4:
                raise ParameterError(f"halfspaces[{i}]", f"expected [nx, ny, nz, c] (4 finite numbers), got {row!r}")
            if not any(row[:3]):
                raise ParameterError(f"halfspaces[{i}]", f"expected a non-zero normal, got {row!r}")
        h = torch.tensor(rows, dtype=torch.float64).reshape(-1, 4)
        length = torch.linalg.vector_norm(h[:, :3], dim=-1)
        self.normals = h[:, :3] / length[:, None]
        self.offsets = h[:, 3] / length
        self.vertices = polytope_vertices(self.normals, self.offsets)
        lo, hi = self.vertices.min(0).values, self.vertices.max(0).values
        self._center = (lo + hi) / 2
        self._radius = float(torch.linalg.vector_norm(self.vertices - self._center, dim=-1).max())

    def intersect(self, o, d, t_min):
        normals = self._param("normals", o)
        num = self._param("offsets", o) - o @ normals.T
        return clip_convex(num, d @ normals.T, t_min)

    def surface(self, p, aux):
        n = self._param("normals", p)[aux]
        return n, coordinates_across(p, n.abs().argmax(-1))

    def bounding_sphere(self):
        return self._center, self._radius
