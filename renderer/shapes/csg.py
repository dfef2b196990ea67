"""Constructive solid geometry of half-space polyhedra: intersection, union and difference.

Scene-file keys:

| key | kind | default | meaning |
|---|---|---|---|
| `op` | str | required | `intersection`, `union` or `difference` (the first child minus all the others) |
| `children` | list | required | shapes: `polyhedron` (the leaf, n·x ≤ c half-spaces) or another `csg` |

The solid is closed (boundary points count as inside). A ray's hit is the first crossing beyond t_min
where the solid's inside/outside state changes: along the ray every convex leaf occupies one interval
[t_enter, t_exit], so the candidates are the leaves' interval ends, and the state just before and after
each candidate is the tree evaluated on the leaves' intervals. The normal is the outward normal of the
combined solid: the leaf plane's normal, turned round where a subtracted leaf bounds the solid.
`aux` packs (leaf, plane, turned). Texture coordinates are those of `polyhedron` (the two coordinates
across the normal's dominant axis, scene units).
"""
from __future__ import annotations

import torch

from .base import INF, ParameterError, Shape
from .polyhedron import Polyhedron, coordinates_across, slab_interval

OPS = ("intersection", "union", "difference")
# Leaves of one CSG tree: `intersect` evaluates the tree between every pair of interval ends, (rays, 2L + 1, L)
# booleans, so a batch of 2^17 rays needs about 2^18 · L² bytes (1 GiB at this limit).
MAX_LEAVES = 64


class CSG(Shape):
    """A CSG tree whose leaves are convex `Polyhedron`s.

    Args:
        op: one of OPS.
        children: Polyhedron or CSG shapes (at least one; at least two for difference).

    Attributes:
        leaves: the Polyhedron leaves in depth-first order (leaf index = position here).
        tree: nested (op, [subtrees]) with ints (leaf indices) at the leaves.
    """

    type_name = "csg"

    def __init__(self, op: str, children: list):
        super().__init__()
        if op not in OPS:
            raise ParameterError("op", f"expected one of {', '.join(OPS)}, got {op!r}")
        if not children or (op == "difference" and len(children) < 2):
            raise ParameterError("children", f"expected {'2' if op == 'difference' else '1'} or more shapes, "
                                              f"got {len(children)}")
        self.op = op
        self.leaves: list[Polyhedron] = []
        self.tree = self._flatten(op, children)
        if len(self.leaves) > MAX_LEAVES:
            raise ParameterError("children", f"expected at most {MAX_LEAVES} polyhedron leaves in one CSG tree, got "
                                             f"{len(self.leaves)} (memory grows with the square of the leaves)")
        k_max = max(leaf.normals.shape[0] for leaf in self.leaves)
        n_leaves = len(self.leaves)
        # Padding planes 0·x <= 1 hold everywhere, so they never bound a leaf's interval.
        normals = torch.zeros(n_leaves, k_max, 3, dtype=torch.float64)
        offsets = torch.ones(n_leaves, k_max, dtype=torch.float64)
        for i, leaf in enumerate(self.leaves):
            k = leaf.normals.shape[0]
            normals[i, :k], offsets[i, :k] = leaf.normals, leaf.offsets
        self.k_max = k_max
        self.normals = normals.reshape(-1, 3)  # (L·K, 3)
        self.offsets = offsets.reshape(-1)  # (L·K,)
        vertices = torch.cat([leaf.vertices for leaf in self.leaves])
        lo, hi = vertices.min(0).values, vertices.max(0).values
        self._center = (lo + hi) / 2
        self._radius = float(torch.linalg.vector_norm(vertices - self._center, dim=-1).max())

    def _flatten(self, op, children):
        subtrees = []
        for i, child in enumerate(children):
            if isinstance(child, Polyhedron):
                self.leaves.append(child)
                subtrees.append(len(self.leaves) - 1)
            elif isinstance(child, CSG):
                subtrees.append(_shift(child.tree, len(self.leaves)))
                self.leaves.extend(child.leaves)
            else:
                raise ParameterError(f"children[{i}]", f"expected a polyhedron or csg shape, got "
                                                       f"{getattr(child, 'type_name', type(child).__name__)}")
        return (op, subtrees)

    # ------------------------------------------------------------------------------------- inside / outside

    def evaluate(self, leaf_inside: torch.Tensor) -> torch.Tensor:
        """The tree on leaf states: (..., L) bool -> (...,) bool (whether the solid holds the point)."""
        return _evaluate(self.tree, leaf_inside)

    def contains(self, p: torch.Tensor) -> torch.Tensor:
        """(N, 3) world points -> (N,) bool: inside or on the boundary of the solid."""
        normals, offsets = self._param("normals", p), self._param("offsets", p)
        scale = 1e-12 * (1.0 + float(self.offsets.abs().max()))
        inside_plane = (p @ normals.T) <= offsets + scale
        return self.evaluate(inside_plane.view(-1, len(self.leaves), self.k_max).all(-1))

    # ----------------------------------------------------------------------------------------- the shape API

    def intersect(self, o, d, t_min):
        n_rays, n_leaves = o.shape[0], len(self.leaves)
        normals, offsets = self._param("normals", o), self._param("offsets", o)
        num = (offsets - o @ normals.T).view(n_rays, n_leaves, self.k_max)
        den = (d @ normals.T).view(n_rays, n_leaves, self.k_max)
        # Each convex leaf along the ray: t·den_k <= num_k for every plane k; (N, L) intervals.
        t_enter, k_enter, t_exit, k_exit, met = slab_interval(num, den)
        t_enter = torch.where(met, t_enter, torch.full_like(t_enter, INF))
        t_exit = torch.where(met, t_exit, torch.full_like(t_exit, -INF))
        # Candidates: the finite interval ends; the others sort to the end as +inf.
        cand = torch.cat([t_enter, torch.where(met, t_exit, torch.full_like(t_exit, INF))], -1)  # (N, 2L)
        cand, order = cand.sort(-1)
        leaf_ids = torch.arange(n_leaves, device=o.device).repeat(2)
        is_enter = torch.arange(2 * n_leaves, device=o.device) < n_leaves
        planes = torch.cat([k_enter, k_exit], -1).gather(-1, order)
        leaf = leaf_ids[order]
        enter = is_enter[order]
        # State between consecutive candidates (and before the first / after the last).
        bounds = torch.cat([torch.full_like(cand[:, :1], -INF), cand, torch.full_like(cand[:, :1], INF)], -1)
        mid = (bounds[:, :-1] + bounds[:, 1:]) / 2  # (N, 2L + 1); NaN (inf − inf) reads as outside
        in_leaf = (t_enter[:, None, :] <= mid[..., None]) & (mid[..., None] <= t_exit[:, None, :])
        state = self.evaluate(in_leaf)  # (N, 2L + 1)
        change = (state[:, :-1] != state[:, 1:]) & (cand > t_min) & (cand < INF)
        first = change.to(torch.uint8).argmax(-1, keepdim=True)
        hit = change.gather(-1, first)[:, 0]
        t = torch.where(hit, cand.gather(-1, first)[:, 0], torch.full_like(cand[:, 0], INF))
        entering_solid = ~state.gather(-1, first)[:, 0]
        turned = enter.gather(-1, first)[:, 0] != entering_solid
        index = leaf.gather(-1, first)[:, 0] * self.k_max + planes.gather(-1, first)[:, 0]
        aux = torch.where(hit, index * 2 + turned.long(), torch.zeros_like(index))
        return t, aux

    def surface(self, p, aux):
        sign = 1 - 2 * (aux % 2).to(p.dtype)
        n = self._param("normals", p)[aux // 2] * sign[:, None]
        return n, coordinates_across(p, n.abs().argmax(-1))

    def bounding_sphere(self):
        return self._center, self._radius


def count_leaves(cfg) -> int:
    """Polyhedron leaves of a CSG scene-file entry (its nested `children`), counted without building any."""
    n, stack = 0, [cfg]
    while stack:
        c = stack.pop()
        children = c.get("children") if isinstance(c, dict) and c.get("type") == "csg" else None
        if isinstance(children, list):
            stack.extend(children)
        else:
            n += 1
    return n


def _shift(node, offset: int):
    """A subtree with its leaf indices moved by `offset` (a child CSG's leaves appended to its parent's)."""
    if isinstance(node, int):
        return node + offset
    return (node[0], [_shift(s, offset) for s in node[1]])


def _evaluate(node, leaf_inside: torch.Tensor) -> torch.Tensor:
    if isinstance(node, int):
        return leaf_inside[..., node]
    op, subtrees = node
    values = [_evaluate(s, leaf_inside) for s in subtrees]
    out = values[0]
    for v in values[1:]:
        if op == "intersection":
            out = out & v
        elif op == "union":
            out = out | v
        else:
            out = out & ~v
    return out

