"""Our shapes as what Mitsuba 3 can load: the exact triangles of boxes, convex polyhedra, meshes and CSG
boundaries, tessellated cones and discs with our texture coordinates at their corners, Mitsuba meshes of
independent triangles, and the finite rectangles that stand in for an infinite plane (`plane_pieces`).
All in world coordinates, float64 numpy until `_triangle_mesh` hands them to Mitsuba as float32.
"""
from __future__ import annotations

import math

import numpy as np
import torch

# Rays nearly parallel to a plane meet it very far away: `plane_pieces` stops them at this many times the
# camera's height above the plane (at least the scene's extent), where what is left of the plane up to the
# horizon subtends less than 1e-5 rad (a hundredth of a pixel of a 1000-pixel, 60° view).
PLANE_REACH = 1e5
# `plane_pieces`: the first square holds the hits within this many times the camera's height; each ring of
# rectangles around it reaches this many times farther than the last.
PLANE_NEAR = 100.0
PLANE_RING = 10.0
# Pixel positions per image side, and lens points, whose rays `plane_pieces` follows to the plane.
PLANE_GRID = 33
_LENS_RIM = [(a, b) for a in (0.0, 0.5, 1 - 1e-9) for b in (0.0, 0.5, 1 - 1e-9)]


def _our_uv(shape, tri, aux):
    """(T, 3, 2) our texture coordinates at the corners of triangles tri (T, 3, 3) lying on the faces `aux`
    (T,) of `shape`, from the shape's own `surface` (affine on each flat face, so exact when Mitsuba
    interpolates them across the triangle)."""
    p = torch.as_tensor(np.ascontiguousarray(tri).reshape(-1, 3), dtype=torch.float64)
    a = torch.as_tensor(np.repeat(np.asarray(aux, dtype=np.int64), 3))
    return shape.surface(p, a)[1].numpy().reshape(-1, 3, 2)


def _fan(ring):
    """Triangles (m, 3, 3) fanned around the mean of a convex polygon's ordered corners ring (m, 3)."""
    centre = np.broadcast_to(ring.mean(0), ring.shape)
    return np.stack([centre, ring, np.roll(ring, -1, axis=0)], 1)


def _face_rings(normals, offsets, vertices):
    """[(plane index k, ordered corners (m, 3))] of the faces of the convex polyhedron n_k·x ≤ c_k with the
    given (V, 3) vertices (duplicates allowed)."""
    vertices = np.unique(np.round(vertices, 12), axis=0)
    scale = 1.0 + float(np.abs(offsets).max())
    rings = []
    for k, (n, c) in enumerate(zip(normals, offsets)):
        face = vertices[np.abs(vertices @ n - c) <= 1e-9 * scale]
        if len(face) < 3:
            continue
        centre = face.mean(0)
        u = face[0] - centre
        u /= np.linalg.norm(u)
        v = np.cross(n, u)
        rings.append((k, face[np.argsort(np.arctan2((face - centre) @ v, (face - centre) @ u))]))
    return rings


def _polyhedron_triangles(shape):
    """World-space triangles (T, 3, 3) of a convex polyhedron, each face fanned around its mean, and each
    triangle's plane index (T,) (our aux)."""
    rings = _face_rings(shape.normals.numpy(), shape.offsets.numpy(), shape.vertices.numpy())
    tri = [_fan(ring) for _, ring in rings]
    aux = [np.full(len(ring), k) for k, ring in rings]
    return np.concatenate(tri), np.concatenate(aux)


def _split(poly, n, c, tol):
    """A convex polygon (m, 3) cut by the plane n·x = c: [the part with n·x ≤ c, the part beyond], each kept
    only if it has three corners (a polygon within tol of one side comes back whole)."""
    s = poly @ n - c
    if s.max() <= tol or s.min() >= -tol:
        return [poly]
    inside, outside = [], []
    for i in range(len(poly)):
        a, b, sa, sb = poly[i], poly[(i + 1) % len(poly)], s[i], s[(i + 1) % len(poly)]
        (inside if sa <= 0 else outside).append(a)
        if (sa < 0 < sb) or (sb < 0 < sa):
            x = a + (b - a) * (sa / (sa - sb))
            inside.append(x)
            outside.append(x)
    return [np.asarray(part) for part in (inside, outside) if len(part) >= 3]


def _csg_triangles(shape):
    """World-space triangles (T, 3, 3) of a CSG solid's boundary and their aux (T,) as `CSG.surface` reads it.

    Each face of each leaf is cut by the planes of every other leaf, so that each piece lies wholly inside or
    outside every other leaf; a piece is boundary where the solid holds the points just behind it and not
    those just in front, or the other way round (then its normal is turned)."""
    size = 1.0 + shape.bounding_sphere()[1]
    tol, step = 1e-12 * size, 1e-7 * size
    pieces, normals, index = [], [], []
    for i, leaf in enumerate(shape.leaves):
        unit = leaf.normals.numpy() / np.linalg.norm(leaf.normals.numpy(), axis=1, keepdims=True)
        for k, ring in _face_rings(leaf.normals.numpy(), leaf.offsets.numpy(), leaf.vertices.numpy()):
            parts = [ring]
            for j, other in enumerate(shape.leaves):
                if j != i:
                    for n, c in zip(other.normals.numpy(), other.offsets.numpy()):
                        parts = [q for p in parts for q in _split(p, n, c, tol)]
            pieces += parts
            normals += [unit[k]] * len(parts)
            index += [i * shape.k_max + k] * len(parts)
    if not pieces:
        return np.zeros((0, 3, 3)), np.zeros(0, dtype=np.int64)
    centre = np.stack([p.mean(0) for p in pieces])
    normals = np.stack(normals)
    front = shape.contains(torch.as_tensor(centre + step * normals)).numpy()
    back = shape.contains(torch.as_tensor(centre - step * normals)).numpy()
    tri, aux = [], []
    for piece, k, f, b in zip(pieces, index, front, back):
        if f != b:
            tri.append(_fan(piece))
            aux.append(np.full(len(piece), 2 * k + int(f)))
    if not tri:
        return np.zeros((0, 3, 3)), np.zeros(0, dtype=np.int64)
    return np.concatenate(tri), np.concatenate(aux)


def _box_triangles(shape):
    """World-space triangles (12, 3, 3) of a box, outward normals by the right-hand rule (as Mitsuba's `cube`,
    and as `renderer.mitsuba.intersect` reads the faces), and their face index (12,) (our aux: 2·axis + side)."""
    R, o, half = shape.world_from_local.numpy(), shape.origin.numpy(), shape.half.numpy()
    tri, aux = [], []
    for axis in range(3):
        a, b = [k for k in range(3) if k != axis]
        for side in (0, 1):
            corners = np.zeros((4, 3))
            corners[:, axis] = (2 * side - 1)
            corners[:, a] = [-1, 1, 1, -1]
            corners[:, b] = [-1, -1, 1, 1]
            p = (corners * half) @ R.T + o
            if np.cross(np.eye(3)[a], np.eye(3)[b])[axis] != 2 * side - 1:  # wind counter-clockwise seen from outside
                p = p[::-1]
            tri += [p[[0, 1, 2]], p[[0, 2, 3]]]
            aux += [2 * axis + side] * 2
    return np.stack(tri), np.asarray(aux)


def _mesh_triangles(shape):
    """World-space triangles (T, 3, 3) of a mesh and their indices (T,) (our aux)."""
    v0, e1, e2 = shape.v0.numpy(), shape.e1.numpy(), shape.e2.numpy()
    return np.stack([v0, v0 + e1, v0 + e2], 1), np.arange(v0.shape[0])


def _cone_triangles(shape, segments: int):
    """World-space triangles (T, 3, 3), per-corner normals (T, 3, 3) and our uv (T, 3, 2) of a closed cone.

    Side uv = (radius · φ, z) with φ in (−π, π] as `side_uv`: `segments` is even, so φ = π is a rim corner
    and no triangle straddles the seam; the apex corner takes its triangle's middle φ. Base uv = local (x, y)."""
    segments += segments % 2
    R = shape.world_from_local.numpy()
    o = shape.origin.numpy()
    r, h, k = shape.radius, shape.height, shape.slope
    phi = np.linspace(0.0, 2 * math.pi, segments + 1)
    rim = np.stack([r * np.cos(phi), r * np.sin(phi), np.zeros_like(phi)], -1)
    side_n = np.stack([np.cos(phi), np.sin(phi), np.full_like(phi, k)], -1) / math.hypot(1.0, k)
    mid = (phi[:-1] + phi[1:]) / 2
    apex_n = np.stack([np.cos(mid), np.sin(mid), np.full_like(mid, k)], -1) / math.hypot(1.0, k)
    apex = np.broadcast_to([0.0, 0.0, h], (segments, 3))
    side = np.stack([rim[:-1], rim[1:], apex], 1)
    side_normals = np.stack([side_n[:-1], side_n[1:], apex_n], 1)
    wrap = np.where(mid > math.pi, -2 * math.pi, 0.0)  # φ of the upper half as atan2 gives it, in (−π, 0)
    side_phi = np.stack([phi[:-1] + wrap, phi[1:] + wrap, mid + wrap], 1)
    side_uv = np.stack([r * side_phi, np.broadcast_to([0.0, 0.0, h], side_phi.shape)], -1)
    centre = np.zeros((segments, 3))
    base = np.stack([rim[1:], rim[:-1], centre], 1)
    base_normals = np.broadcast_to([0.0, 0.0, -1.0], base.shape)
    tri = np.concatenate([side, base]) @ R.T + o
    nrm = np.concatenate([side_normals, base_normals]) @ R.T
    uv = np.concatenate([side_uv, base[..., :2]])
    return tri, nrm, uv


def _disc_triangles(R, o, radius: float, segments: int):
    """World-space triangles (segments, 3, 3) of the disc of `radius` about o in the plane of R's local x, y,
    and our cap uv (local x, y) at their corners."""
    phi = np.linspace(0.0, 2 * math.pi, segments + 1)
    rim = np.stack([radius * np.cos(phi), radius * np.sin(phi), np.zeros_like(phi)], -1)
    local = np.stack([np.zeros((segments, 3)), rim[:-1], rim[1:]], 1)
    return local @ R.T + o, local[..., :2]


def _triangle_mesh(mi, name, tri, normals=None, bsdf=None, texcoords=None):
    """A Mitsuba mesh of independent triangles (T, 3, 3), optionally with per-corner normals and uv (T, 3, 2)."""
    tri = np.ascontiguousarray(tri, dtype=np.float32).reshape(-1, 3)
    props = mi.Properties()
    if bsdf is not None:
        props["bsdf"] = bsdf
    mesh = mi.Mesh(name, tri.shape[0], tri.shape[0] // 3, props, has_vertex_normals=normals is not None,
                   has_vertex_texcoords=texcoords is not None)
    params = mi.traverse(mesh)
    floats = type(params["vertex_positions"])  # mi.Float in JIT variants, a dynamic array in scalar ones
    params["vertex_positions"] = floats(tri.ravel())
    params["faces"] = type(params["faces"])(np.arange(tri.shape[0], dtype=np.uint32))
    if normals is not None:
        params["vertex_normals"] = floats(np.ascontiguousarray(normals, dtype=np.float32).ravel())
    if texcoords is not None:
        params["vertex_texcoords"] = floats(np.ascontiguousarray(texcoords, dtype=np.float32).ravel())
    params.update()
    return mesh


def plane_pieces(scene, shape):
    """Rectangles standing in for the infinite `shape` (a Plane): [(centre (2,), half sizes (2,))] in the
    plane's tangent coordinates (along tangent_u, tangent_v) about the camera's foot on the plane (3,), also
    returned.

    Together they cover every point where a camera ray meets the plane (rays from a `PLANE_GRID`² grid over
    the image, through the lens centre and eight points of its rim, stopped at `PLANE_REACH` times the
    camera's height or the scene's extent, whichever is larger; every ray reaches that far where the
    horizon is in view), and the camera's, lights' and objects' feet on it with the objects' bounding
    spheres (so a shadow ray between two such points crosses the plane where it is). The first is a square
    holding the feet and the hits within `PLANE_NEAR` times that length; rings of four rectangles, each
    `PLANE_RING` times wider than the last, reach out to the farthest hit. Mitsuba computes a rectangle's uv
    in float32 relative to its size, so one square reaching the horizon would move the checker cells near
    the camera by a few per cent of their size."""
    n, q = shape.normal.numpy(), shape.point.numpy()
    u, v = shape.tangent_u.numpy(), shape.tangent_v.numpy()
    camera = scene.camera
    xs = np.linspace(-0.5, camera.width - 0.5, PLANE_GRID)
    ys = np.linspace(-0.5, camera.height - 0.5, PLANE_GRID)
    pixels = np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 1, 2)
    lens = np.asarray(_LENS_RIM if camera.uses_lens_samples else [(0.5, 0.5)])
    pixels, lens = np.broadcast_arrays(pixels, lens[None])
    with torch.no_grad():
        rays = camera.generate_rays(torch.as_tensor(pixels.reshape(-1, 2)), torch.as_tensor(lens.reshape(-1, 2)))
    o, d = rays.origin.double().numpy(), rays.direction.double().numpy()
    position = camera.transform.position.double().numpy()
    scale = max(abs(float((position - q) @ n)), scene.extent)
    along = d @ n
    t = np.where(along != 0, ((q - o) @ n) / np.where(along != 0, along, 1.0), np.inf)
    seen = rays.valid.numpy() & (t > 0)
    hits = o[seen] + np.minimum(t[seen], PLANE_REACH * scale)[:, None] * d[seen]
    feet = [position[None]] + [np.asarray(light.position, dtype=np.float64)[None]
                               for light in scene.lights if light.position is not None]
    radii = [0.0] * len(feet)
    for obj in scene.objects:
        sphere = obj.shape.bounding_sphere()
        if sphere is not None:
            feet.append(np.asarray(sphere[0], dtype=np.float64).reshape(1, 3))
            radii.append(float(sphere[1]))
    centre = position - ((position - q) @ n) * n

    def reach(points, margin=0.0):  # half side of the square about `centre` holding the points' feet
        rel = points - centre
        return np.maximum(np.abs(rel @ u), np.abs(rel @ v)) + margin

    near = np.concatenate([reach(np.concatenate(feet), np.asarray(radii)), [scene.extent]])
    far = reach(hits) if len(hits) else np.zeros(1)
    if seen.any() and (rays.valid.numpy() & ~seen).any():  # the horizon is in view: rays come arbitrarily close
        far = np.append(far, PLANE_REACH * scale)
    h = 1.01 * max(near.max(), far[far <= PLANE_NEAR * scale].max(initial=0.0))
    pieces = [((0.0, 0.0), (h, h))]
    while h < far.max():
        outer = min(PLANE_RING * h, 1.01 * far.max())
        mid, width = (h + outer) / 2, (outer - h) / 2 * (1 + 1e-6)  # overlapping a little: no seams
        pieces += [((0.0, -mid), (outer, width)), ((0.0, mid), (outer, width)),
                   ((-mid, 0.0), (width, h)), ((mid, 0.0), (width, h))]
        h = outer
    return centre, pieces
