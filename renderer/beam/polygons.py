"""Step (1) of the beam tracer: half-space polyhedra (and their CSG) converted once to planar polygons.

Every polygon lives in its own plane with a 2D frame: a world point x = o + s·u + t·v (o on the plane, u and
v orthonormal in it), and the polygon is a shapely Polygon (possibly with holes) in (s, t), scene units.
Mirroring moves only the frame (o, u, v, n), never the 2D polygon, so mirrored copies are cheap.

CSG to polygons: the candidate planes are the leaves' planes, grouped when two leaves share a plane
(either orientation). On one plane, every leaf is a 2D region on either side of it: its cross-section, or,
for a leaf bounded by that very plane, its face on the side it lies (empty on the other). Evaluating the CSG
tree with shapely on both sides gives where the solid lies behind the plane and where in front of it; the
solid's boundary on the plane is the symmetric difference, facing +n where the solid lies behind and −n
where it lies in front. Redundant half-spaces (planes that do not touch the solid) and face parts inside
other leaves give empty regions and are dropped: no redundant faces remain.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import shapely
from shapely.geometry import Polygon, box

from renderer.core.params import SceneError
from ..shapes.csg import CSG
from ..shapes.polyhedron import Polyhedron

# Planes closer than this (relative to the scene size) are the same plane; polygon parts thinner than
# this are dropped.
PLANE_TOL = 1e-9
MIN_AREA = 1e-12
EMPTY = Polygon()


@dataclass
class Face:
    """One planar polygon of the scene, world frame, scene units.

    Attributes:
        index: position in the scene's face list (the id used in ray-tree signatures).
        object_id: index of its scene object.
        n, c: the plane n·x = c with n the outward unit normal (3,).
        o, u, v: the 2D frame: x = o + s·u + t·v (each (3,)).
        poly: shapely Polygon in (s, t).
        vertices: (V, 3) every ring vertex in the world (outer ring and holes), for plane-side tests.
    """

    index: int
    object_id: int
    n: np.ndarray
    c: float
    o: np.ndarray
    u: np.ndarray
    v: np.ndarray
    poly: Polygon
    vertices: np.ndarray = field(repr=False)


def plane_frame(n: np.ndarray, c: float, near: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(o, u, v): o the point of the plane n·x = c nearest to `near`, u and v an orthonormal basis in it."""
    o = near - (n @ near - c) * n
    e = np.eye(3)[int(np.argmin(np.abs(n)))]
    u = np.cross(n, e)
    u /= np.linalg.norm(u)
    return o, u, np.cross(n, u)


def pyramid(apex: np.ndarray, edges: np.ndarray) -> list[tuple[np.ndarray, float]]:
    """Half-spaces a·x ≤ b (world) whose intersection is the pyramid from `apex` along the edge directions
    `edges` (K, 3), given in order around it: one plane through the apex and each pair of neighbouring edges,
    facing away from the sum of the edges (a direction inside)."""
    inside = edges.sum(0)
    planes = []
    for e0, e1 in zip(edges, np.roll(edges, -1, axis=0)):
        a = np.cross(e0, e1)
        if a @ inside > 0:
            a = -a
        planes.append((a, float(a @ apex)))
    return planes


def clip_halfplane(poly, a: float, b: float, h: float):
    """The part of a shapely geometry (2D) where a·s + b·t ≤ h ((a, b) need not be unit)."""
    if poly.is_empty:
        return poly
    length = float(np.hypot(a, b))
    if length < 1e-15:
        return poly if h >= -PLANE_TOL else EMPTY
    m = np.array([a, b]) / length
    h = h / length
    x0, y0, x1, y1 = poly.bounds
    center = np.array([(x0 + x1) / 2, (y0 + y1) / 2])
    radius = float(np.hypot(x1 - x0, y1 - y0)) / 2 + 1.0
    g = float(m @ center) - h
    if g < -radius:
        return poly
    if g > radius:
        return EMPTY
    w = np.array([-m[1], m[0]])
    p0 = center - g * m
    corners = np.array([p0 + 2 * radius * w, p0 - 2 * radius * w, p0 - 2 * radius * w - 4 * radius * m,
                        p0 + 2 * radius * w - 4 * radius * m])
    return shapely.intersection(poly, shapely.polygons(corners))  # Polygon(corners) without its Python checks


def clip_halfspace(poly, o, u, v, a: np.ndarray, b: float):
    """The part of a 2D polygon in frame (o, u, v) that lies in the 3D half-space a·x ≤ b."""
    return clip_halfplane(poly, float(a @ u), float(a @ v), float(b - a @ o))


def to_world(st: np.ndarray, o, u, v) -> np.ndarray:
    """(N, 2) plane coordinates -> (N, 3) world points."""
    return o + st[:, :1] * u + st[:, 1:2] * v


def areal(geom):
    """The polygonal part of a shapely geometry (lines and points that an overlay leaves are dropped)."""
    if geom.geom_type in ("Polygon", "MultiPolygon"):
        return geom
    parts = polygons_of(geom)
    return parts[0] if len(parts) == 1 else shapely.MultiPolygon(parts) if parts else EMPTY


def polygons_of(geom) -> list[Polygon]:
    """The non-degenerate Polygons of any shapely geometry (MultiPolygon and collections split)."""
    if geom.is_empty:
        return []
    if geom.geom_type == "Polygon":
        return [geom] if geom.area > MIN_AREA else []
    if hasattr(geom, "geoms"):
        return [p for g in geom.geoms for p in polygons_of(g)]
    return []


def _section(normals: np.ndarray, offsets: np.ndarray, o, u, v, domain, skip: np.ndarray):
    """Cross-section of the convex set {x : normals·x ≤ offsets} with the plane of frame (o, u, v), clipped to
    `domain`, leaving out the planes flagged in `skip` (K,)."""
    poly = domain
    for k in range(normals.shape[0]):
        if not skip[k]:
            poly = clip_halfspace(poly, o, u, v, normals[k], offsets[k])
            if poly.is_empty:
                break
    return poly


def _evaluate(node, regions: list):
    if isinstance(node, int):
        return regions[node]
    op, subtrees = node
    values = [_evaluate(s, regions) for s in subtrees]
    if op == "union":
        return shapely.union_all(values)
    if op == "intersection":
        out = values[0]
        for g in values[1:]:
            out = shapely.intersection(out, g)
        return out
    rest = shapely.union_all(values[1:])
    return shapely.difference(values[0], rest)


def solid_faces(shape) -> list[tuple[np.ndarray, float, np.ndarray, np.ndarray, np.ndarray, Polygon]]:
    """Boundary polygons of a Polyhedron or CSG solid: [(n, c, o, u, v, poly)], n the outward normal.

    Raises:
        TypeError for other shapes.
    """
    if isinstance(shape, Polyhedron):
        leaves, tree = [shape], 0
    elif isinstance(shape, CSG):
        leaves, tree = shape.leaves, shape.tree
    else:
        raise TypeError(shape.type_name)
    data = [(leaf.normals.numpy(), leaf.offsets.numpy()) for leaf in leaves]
    center = shape.bounding_sphere()[0].numpy()
    radius = float(shape.bounding_sphere()[1])
    tol = PLANE_TOL * (1.0 + radius + float(np.linalg.norm(center)))
    # Plane groups: one entry per distinct plane up to orientation.
    groups: list[tuple[np.ndarray, float]] = []
    for normals, offsets in data:
        for n, c in zip(normals, offsets):
            if not any((np.abs(n - g).max() < 1e-9 and abs(c - gc) < tol)
                       or (np.abs(n + g).max() < 1e-9 and abs(c + gc) < tol) for g, gc in groups):
                groups.append((n, float(c)))
    domain_half = 2.0 * radius + 1.0
    out = []
    for n, c in groups:
        o, u, v = plane_frame(n, c, center)
        domain = box(-domain_half, -domain_half, domain_half, domain_half)
        back, front = [], []
        for normals, offsets in data:
            same = (np.abs(normals - n).max(-1) < 1e-9) & (np.abs(offsets - c) < tol)
            opposite = (np.abs(normals + n).max(-1) < 1e-9) & (np.abs(offsets + c) < tol)
            section = _section(normals, offsets, o, u, v, domain, same | opposite)
            if same.any():  # the leaf lies behind the plane (n·x ≤ c)
                back.append(section)
                front.append(EMPTY)
            elif opposite.any():
                back.append(EMPTY)
                front.append(section)
            else:
                back.append(section)
                front.append(section)
        behind, ahead = _evaluate(tree, back), _evaluate(tree, front)
        for normal, offset, geom in ((n, c, shapely.difference(behind, ahead)),
                                     (-n, -c, shapely.difference(ahead, behind))):
            for poly in polygons_of(geom):
                out.append((normal.copy(), offset, o, u, v, shapely.normalize(poly)))
    return out


def scene_faces(scene) -> list[Face]:
    """Every object's boundary polygons (step (1)); objects must be polyhedra or CSG of polyhedra.

    Raises:
        SceneError naming the object whose shape or material the beam tracer cannot handle.
    """
    faces = []
    for i, obj in enumerate(scene.objects):
        if obj.material.transmit > 0:
            raise SceneError(f"objects[{i}] ({obj.name}): beam tracing handles opaque diffuse and mirror "
                             f"materials, got transmit={obj.material.transmit}")
        try:
            parts = solid_faces(obj.shape)
        except TypeError:
            raise SceneError(f"objects[{i}] ({obj.name}): beam tracing handles polyhedron and csg shapes, got "
                             f"{obj.shape.type_name}") from None
        for n, c, o, u, v, poly in parts:
            vertices = to_world(shapely.get_coordinates(poly), o, u, v)
            faces.append(Face(len(faces), i, n, c, o, u, v, poly, vertices))
    return faces
