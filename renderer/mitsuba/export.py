"""Convert a renderer `Scene` into a Mitsuba 3 scene dict, to time and cross-check against a named peer.

What carries over (exactly, up to tessellation where noted):
- camera: `pinhole` (pose, horizontal field of view, square pixels, centred principal point) as a Mitsuba
  `perspective` sensor with a box pixel filter, so pixel (x, y) of both images covers the same solid angle;
  an untilted `thin_lens` with square pixels and centred principal point as Mitsuba's `thinlens`
  (aperture_radius d/2, focus_distance U); a tilted thin lens (or any thin lens), the `inverted_perspective`
  camera, the `orthographic` camera and any other pinhole (its α = 1 and α = 0 cases), and any camera with
  a lens distortion (each pixel traced through its undistorted position) through our sensor plugins
  (`renderer.mitsuba.sensors`);
- lights: `point` (radiant intensity, 1/r² fall-off in both); `ambient` (intensity · albedo, no shadows)
  added after the render from Mitsuba's albedo AOV of the first hit (`develop`);
- the background colour: composited after the render where Mitsuba's alpha says the camera ray missed
  (`develop`), as ours adds it where the primary ray hits nothing;
- shapes: `sphere`, `cylinder` (Mitsuba's open cylinder plus two disc caps), `rectangle`, `box`,
  `polyhedron` and `mesh` (their exact triangles), `csg` (the triangles of its boundary: each leaf's faces
  cut by the other leaves' planes, kept where the solid changes across them), `plane` (a square covering
  what the camera sees of the plane and the feet of the lights and objects on it, see `plane_pieces`),
  `cone` (triangles, `segments` around the axis, smooth side normals);
- materials: Lambert with reflectance (1 − reflect − transmit) · diffuse · albedo, two-sided as the
  renderer shades both sides of every surface; with a Phong highlight (which Mitsuba 3 lacks), or a diffuse
  weight other than 1 under ambient light, our `renderer_phong` plugin (`renderer.mitsuba.bsdfs`). The
  albedo is the colour, a checker texture (Mitsuba's `checkerboard`) or an image texture (Mitsuba's
  `bitmap`, bilinear, repeated, linear values): each shape's Mitsuba uv is mapped onto our texture
  coordinates (an affine `to_uv`; the sphere and cylinder turned so that their seams fall where ours do;
  triangle meshes carry our uv at their vertices), so checker cells and image texels land where ours do.
What does not: mirror reflection and refraction (the `direct` integrator follows no secondary rays; the
local term keeps its weight 1 − reflect − transmit, so only the reflected and refracted light is missing,
and a transparent object casts a full shadow), and layers; `to_mitsuba` names what it dropped in the
returned `dropped` list, and raises NotImplementedError for a camera it cannot express.

Frames. Mitsuba's camera looks along its local +z with +x to the left and +y up in the image; ours looks
along +z with x right and y down (OpenCV). So the sensor's to_world has columns (−x_cam, −y_cam, z_cam,
position) in world coordinates, which keeps the image unmirrored (checked in `benchmarks/renderer/bench_fig6_mitsuba.py`
by comparing the two images). Our sensor plugins work in our camera frame and need no flip.

Mitsuba is an optional extra (`pip install -e '.[test]'` or `'.[bench]'`); it is imported on first use.
"""
from __future__ import annotations

import math
import os

import numpy as np
import torch

from renderer.scene.materials import CheckerTexture, GridTexture, ImageTexture

from renderer.core.transforms import world_from_local_4x4 as _matrix

DEFAULT_VARIANT = "llvm_ad_rgb"


_LLVM_RUNS: dict = {}  # variant -> whether its JIT runs here (probed once per process)
_PROBE = ("import drjit as dr, mitsuba as mi; mi.set_variant({v!r}); "
          "x = dr.maximum(mi.Float([1, 2]), mi.Float([2, 1])); dr.eval(x); print(x)")


#: Set (to anything but "" or "0") to hide Mitsuba's JIT variants, as on a machine without libLLVM >= 16: CI runs
#: the suite once this way so the pure-torch fallback of `intersector="auto"` stays tested.
HIDE_JIT_ENV = "RENDERER_HIDE_MITSUBA_JIT"


def jit_hidden() -> bool:
    """Whether `HIDE_JIT_ENV` hides Mitsuba's JIT variants in this process."""
    return os.environ.get(HIDE_JIT_ENV, "") not in ("", "0")


def jit_variant_runs(variant: str) -> bool:
    """Whether a JIT variant (llvm_*, cuda_*) runs here, probed in a child process: Dr.Jit needs LLVM >= 16,
    and with an older libLLVM the first kernel aborts the whole process. False whenever `HIDE_JIT_ENV` is set."""
    if variant.startswith("scalar"):
        return True
    if jit_hidden():
        return False
    if variant not in _LLVM_RUNS:
        import subprocess
        import sys

        try:
            probe = subprocess.run([sys.executable, "-c", _PROBE.format(v=variant)], capture_output=True,
                                   text=True, timeout=300)
            _LLVM_RUNS[variant] = probe.returncode == 0
        except (OSError, subprocess.TimeoutExpired):
            _LLVM_RUNS[variant] = False
    return _LLVM_RUNS[variant]


def variant_runs(variant: str) -> None:
    """Record that a JIT variant runs here, without probing: for a worker process whose parent probed it."""
    _LLVM_RUNS[variant] = True


def load_mitsuba(variant: str | None = DEFAULT_VARIANT):
    """Import mitsuba and set `variant` (None: keep the current one, or the default if none is set); falls
    back to scalar_rgb where a JIT variant is missing or cannot run here (see `jit_variant_runs`)."""
    try:
        import mitsuba as mi
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError("mitsuba is not installed; pip install -e '.[test]'") from e
    if variant is None:
        if mi.variant() is not None:
            return mi
        variant = DEFAULT_VARIANT
    if mi.variant() == variant:
        return mi
    try:
        if not jit_variant_runs(variant):
            raise ImportError(variant)
        mi.set_variant(variant)
    except (ImportError, AttributeError):
        mi.set_variant("scalar_rgb")
    return mi


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


# ------------------------------------------------------------------------------------------------- geometry


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


# ------------------------------------------------------------------------------------------------ materials


def _uv_transform(mi, scale, offset):
    """The `to_uv` of a Mitsuba texture: (u, v) -> scale ⊙ (u, v) + offset."""
    return mi.ScalarTransform3f([[scale[0], 0.0, offset[0]], [0.0, scale[1], offset[1]], [0.0, 0.0, 1.0]])


def _reflectance(mi, material, weight: float, uv_map):
    """Mitsuba texture of weight · albedo. uv_map = (scale, offset): our texture coordinates (scene units) are
    scale ⊙ (Mitsuba's uv) + offset on this shape."""
    tex = material.texture
    scale, offset = (np.asarray(x, dtype=np.float64) for x in uv_map)
    if isinstance(tex, CheckerTexture):
        # Ours: cell (floor(u / size), floor(v / size)), colour by the parity of their sum. Mitsuba's
        # checkerboard repeats every texture unit with color0 on the cells (0, 0) and (1, 1) of its 2 × 2:
        # its coordinate is ours / (2 · size).
        cell = 2 * tex.size
        return {"type": "checkerboard",
                "color0": {"type": "rgb", "value": [weight * c for c in tex.colors[0]]},
                "color1": {"type": "rgb", "value": [weight * c for c in tex.colors[1]]},
                "to_uv": _uv_transform(mi, scale / cell, offset / cell)}
    if isinstance(tex, ImageTexture):
        # Ours: texel centres at ((i + 0.5) / w) · size, bilinear, repeated; Mitsuba's bitmap the same in
        # its coordinate ours / size (row 0 at v = 0 in both).
        size = np.asarray(tex.size, dtype=np.float64)
        return {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(weight * tex.pixels, dtype=np.float32)),
                "raw": True, "filter_type": "bilinear", "wrap_mode": "repeat",
                "to_uv": _uv_transform(mi, scale / size, offset / size)}
    if isinstance(tex, GridTexture):
        # Exact cells here; Mitsuba gets them sampled at texel centres (nearest texel, edges within half a
        # texel: GRID_TEXEL_FRACTION of the smallest cell, at most 8192 texels a side), clamped beyond the grid.
        cell = min(np.diff(tex.xs).min(), np.diff(tex.ys).min())
        pixels, origin, size = tex.raster(GRID_TEXEL_FRACTION * cell)
        size, origin = np.asarray(size), np.asarray(origin)
        return {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(weight * pixels, dtype=np.float32)),
                "raw": True, "filter_type": "nearest", "wrap_mode": "clamp",
                "to_uv": _uv_transform(mi, scale / size, (offset - origin) / size)}
    return {"type": "rgb", "value": [weight * c for c in material.color]}


#: A `GridTexture`'s texel for Mitsuba, as a fraction of its smallest cell.
GRID_TEXEL_FRACTION = 1.0 / 64


def _bsdf(mi, material, uv_map=((1.0, 1.0), (0.0, 0.0)), dropped=None, name="", ambient=False):
    """Two-sided Lambert with reflectance (1 − reflect − transmit) · diffuse · albedo (see `_reflectance` for
    uv_map; the default: the shape's Mitsuba uv are ours), or our `renderer_phong` plugin where the material
    has a Phong highlight or, under `ambient` light, a diffuse weight other than 1 (`renderer.mitsuba.bsdfs`);
    the terms it cannot express go to `dropped`."""
    weight = max(1.0 - material.reflect - material.transmit, 0.0)
    if dropped is not None:
        dropped += [f"{name}: {key}" for key in ("reflect", "transmit") if getattr(material, key) > 0]
    if material.specular > 0 or (ambient and material.diffuse != 1):
        from .bsdfs import register

        register(mi)
        return {"type": "renderer_phong", "reflectance": _reflectance(mi, material, weight, uv_map), "weight": weight,
                "diffuse": material.diffuse, "specular": material.specular, "shininess": material.shininess}
    return {"type": "twosided", "material": {
        "type": "diffuse", "reflectance": _reflectance(mi, material, weight * material.diffuse, uv_map)}}


def _native_lens(camera) -> bool:
    """Whether Mitsuba's own `perspective` / `thinlens` sensor reproduces the camera (square pixels, centred
    principal point, untilted, no lens distortion)."""
    kind = type(camera).__name__
    if kind not in ("PinholeCamera", "ThinLensCamera"):
        return False
    (px, py), screen = camera.screen.pitch, camera.screen
    square = abs(px - py) <= 1e-9 * max(px, py)
    undistorted = camera.distortion is None or camera.distortion.is_identity
    return (square and undistorted and screen.principal_point_px is None
            and (kind == "PinholeCamera" or camera.lens.theta_F == 0))


def _sensor(mi, camera, spp: int, plugin: bool = False):
    """Mitsuba sensor dict: Mitsuba's own sensor where it matches the camera exactly (a thin lens: unless
    `plugin`), else our plugin (`renderer.mitsuba.sensors`)."""
    kind = type(camera).__name__
    if not _native_lens(camera) or (plugin and kind != "PinholeCamera"):
        from .sensors import sensor_dict

        return sensor_dict(mi, camera, spp)
    screen = camera.screen
    W, H = screen.width_px, screen.height_px
    q3 = screen.distance
    R = camera.transform.world_from_camera.numpy()
    t = camera.transform.position.numpy()
    to_world = _matrix(np.stack([-R[:, 0], -R[:, 1], R[:, 2]], axis=1), t)
    lens = {"type": "perspective"}
    if kind == "ThinLensCamera" and camera.lens.d > 0:
        lens = {"type": "thinlens", "aperture_radius": camera.lens.d / 2, "focus_distance": camera.lens.U}
    return {
        **lens,
        "fov_axis": "x",
        "fov": math.degrees(2 * math.atan(screen.size[0] / 2 / q3)),
        "to_world": mi.ScalarTransform4f(to_world),
        "film": {"type": "hdrfilm", "width": W, "height": H, "rfilter": {"type": "box"},
                 "pixel_format": "rgb", "component_format": "float32"},
        "sampler": {"type": "independent", "sample_count": spp},
    }


# --------------------------------------------------------------------------------------------------- scene


def to_mitsuba(scene, spp: int | None = None, integrator: dict | None = None, *, variant: str | None = None,
               plane_size: float | None = None, segments: int = 256, plugin_sensor: bool = False):
    """Mitsuba scene dict for `scene` (see the module docstring for what carries over).

    Args:
        spp: samples per pixel [scene.image.spp].
        integrator: Mitsuba integrator dict [direct lighting, one emitter sample, no BSDF samples]; wrapped in
            an `aov` integrator adding the albedo where the scene has ambient light.
        plane_size: side of the square standing in for an infinite plane, scene units, centred on the
            plane's point [None: rectangles sized and placed by `plane_pieces`].
        segments: facets around the axis of a cone (and of a textured cylinder's caps).
        variant: Mitsuba variant to set [None: the current one, else the default, see `load_mitsuba`].
        plugin_sensor: use our sensor plugin even where Mitsuba's own sensor matches (pinhole excepted).
    Returns:
        (scene_dict, dropped): the dict for `mitsuba.load_dict`, and a list of what could not be expressed.
        Pass what `mitsuba.render` makes of the dict through `develop` for the image.
    Raises:
        NotImplementedError: a camera or shape type with no Mitsuba counterpart (one line).
    """
    mi = load_mitsuba(variant)
    dropped: list[str] = []
    integrator = integrator or {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0}
    ambient = [light for light in scene.lights if light.type == "ambient" and any(light.intensity)]
    if ambient:
        integrator = {"type": "aov", "aovs": "albedo:albedo", "integrator": integrator}
    try:
        sensor = _sensor(mi, scene.camera, scene.image.spp if spp is None else spp, plugin_sensor)
    except NotImplementedError as e:
        raise NotImplementedError(f"mitsuba export: {e}") from None
    if ambient or any(scene.image.background):  # the alpha channel tells where the camera ray hit nothing
        sensor["film"]["pixel_format"] = "rgba"
    out = {"type": "scene", "integrator": integrator, "sensor": sensor}
    if not _distortion_inverts(scene.camera):
        dropped.append("camera.distortion beyond its invertible zone (ours averages a pixel's valid samples, "
                       "Mitsuba counts the others black)")
    if scene.layers:
        dropped.append("layers")
    for i, light in enumerate(scene.lights):
        if light.type == "point":
            out[f"light_{i}"] = {"type": "point", "position": list(light.position),
                                 "intensity": {"type": "rgb", "value": list(light.intensity)}}
        elif light.type != "ambient":
            dropped.append(f"lights[{i}]: type {light.type}")
    out.update(shape_dicts(mi, scene, dropped, plane_size=plane_size, segments=segments, tessellate=True))
    return out, dropped


def _distortion_inverts(camera, step_px: float = 0.25) -> bool:
    """Whether the camera's lens distortion (if any) inverts at every point of the image's border, sampled
    every `step_px` pixels: where it does not (beyond the zone where the model is monotonic, which grows from
    the centre), our camera gives a sample no ray and the pixel the mean of the others, and Mitsuba's film
    counts it as black."""
    if camera.distortion is None or camera.distortion.is_identity:
        return True
    x0, y0, x1, y1 = -0.5, -0.5, camera.width - 0.5, camera.height - 0.5
    xs = np.arange(x0, x1 + step_px, step_px).clip(max=x1)
    ys = np.arange(y0, y1 + step_px, step_px).clip(max=y1)
    border = np.concatenate([np.stack([xs, np.full_like(xs, y0)], -1), np.stack([xs, np.full_like(xs, y1)], -1),
                             np.stack([np.full_like(ys, x0), ys], -1), np.stack([np.full_like(ys, x1), ys], -1)])
    with torch.no_grad():
        _, ok = camera.undistort_pixels(torch.as_tensor(border))
    return bool(ok.all())


def develop(scene, raw) -> np.ndarray:
    """The (H, W, 3) linear RGB image from what `mitsuba.render` made of `to_mitsuba(scene)`'s dict: its RGB,
    plus the background colour where the camera rays missed (1 − alpha) and each ambient light's intensity
    times the albedo AOV, as our tracer adds them."""
    raw = np.asarray(raw, dtype=np.float32)
    image = raw[..., :3].copy()
    if any(scene.image.background):
        image += (1.0 - raw[..., 3:4]) * np.asarray(scene.image.background, dtype=np.float32)
    for light in scene.lights:
        if light.type == "ambient" and any(light.intensity):
            image += raw[..., -3:] * np.asarray(light.intensity, dtype=np.float32)
    return image


def shape_dicts(mi, scene, dropped: list[str] | None = None, *, plane_size: float | None = None,
                segments: int = 256, only=None, tessellate: bool = False) -> dict:
    """Mitsuba shapes of the scene's objects (those with an index in `only`, when given): {key: shape dict or
    loaded mesh}, keys `object_{i}` (a cylinder also `object_{i}_base` and `object_{i}_top`, its caps); what
    cannot be expressed is appended to `dropped`. tessellate: a textured cylinder's caps as triangle fans of
    `segments` facets carrying our uv (Mitsuba's disc has polar uv), else exact discs. See `to_mitsuba` for
    the other arguments."""
    T = mi.ScalarTransform4f
    ambient = any(light.type == "ambient" and any(light.intensity) for light in scene.lights)
    out: dict = {}
    for i, obj in enumerate(scene.objects):
        if only is not None and i not in only:
            continue
        shape, kind, key, material = obj.shape, obj.shape.type_name, f"object_{i}", obj.material

        def bsdf(uv_map=((1.0, 1.0), (0.0, 0.0)), note=True):
            return _bsdf(mi, material, uv_map, dropped if note else None, obj.name, ambient)

        if kind == "sphere":
            # Mitsuba: φ = atan2(y, x) in [0, 2π), θ = acos(z) in its local frame; ours: φ = atan2(x, z)
            # in (−π, π], θ = acos(y) in the world's, uv = r · (φ, θ). Local axes (−z, −x, y): φ' = φ + π,
            # so ours = r · (2π u' − π, π v').
            r = shape.radius
            R = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]])
            out[key] = {"type": "sphere", "to_world": T(_matrix(R, shape.center.numpy(), [r, r, r])),
                        "bsdf": bsdf(((2 * math.pi * r, math.pi * r), (-math.pi * r, 0.0)))}
        elif kind == "rectangle":
            # Mitsuba's uv = (local + 1) / 2 over [−1, 1]²; ours = local + half, scene units.
            half = shape.half.tolist()
            out[key] = {"type": "rectangle",
                        "to_world": T(_matrix(shape.world_from_local.numpy(), shape.origin.numpy(), half + [1.0])),
                        "bsdf": bsdf(((2 * half[0], 2 * half[1]), (0.0, 0.0)))}
        elif kind == "plane":
            R = np.stack([shape.tangent_u.numpy(), shape.tangent_v.numpy(), shape.normal.numpy()], axis=1)
            if plane_size is None:
                centre, pieces = plane_pieces(scene, shape)
            else:
                centre, pieces = shape.point.numpy(), [((0.0, 0.0), (plane_size / 2, plane_size / 2))]
            shift = (centre - shape.point.numpy()) @ R[:, :2]  # the centre in our uv (from the plane's point)
            for j, (middle, half) in enumerate(pieces):
                # ours: u = (x − point)·tangent_u = shift + middle + half · (2 u' − 1), likewise v.
                offset = [shift[k] + middle[k] - half[k] for k in range(2)]
                out[key if j == 0 else f"{key}_{j}"] = {
                    "type": "rectangle", "to_world": T(_matrix(R, centre + R[:, :2] @ middle, [*half, 1.0])),
                    "bsdf": bsdf(((2 * half[0], 2 * half[1]), offset), note=j == 0)}
        elif kind == "cylinder":
            # Mitsuba's open cylinder: uv = (φ / 2π in [0, 2π), z / height) in its local frame; ours: (r · φ,
            # z) with φ = atan2(y, x) in (−π, π]. Local axes (−x, −y, z) give φ' = φ + π.
            R, o = shape.world_from_local.numpy(), shape.origin.numpy()
            r, h = shape.radius, shape.height
            side = bsdf(((2 * math.pi * r, h), (-math.pi * r, 0.0)))
            out[key] = {"type": "cylinder", "p0": [0.0, 0.0, 0.0], "p1": [0.0, 0.0, h], "radius": r,
                        "to_world": T(_matrix(R * [-1.0, -1.0, 1.0], o)), "bsdf": side}
            caps = {"_base": o, "_top": o + h * R[:, 2]}
            if tessellate and material.texture is not None:
                cap = mi.load_dict(bsdf(note=False))
                for part, centre in caps.items():
                    tri, uv = _disc_triangles(R, centre, r, segments)
                    out[key + part] = _triangle_mesh(mi, key + part, tri, None, cap, uv)
            else:
                cap = bsdf(note=False)
                for part, centre in caps.items():
                    out[key + part] = {"type": "disk", "to_world": T(_matrix(R, centre, [r, r, 1.0])), "bsdf": cap}
        elif kind in ("box", "cone", "polyhedron", "mesh", "csg"):
            mesh_bsdf = mi.load_dict(bsdf())
            nrm = None
            if kind == "cone":
                tri, nrm, uv = _cone_triangles(shape, segments)
            else:
                tri, aux = {"box": _box_triangles, "polyhedron": _polyhedron_triangles, "mesh": _mesh_triangles,
                            "csg": _csg_triangles}[kind](shape)
                uv = _our_uv(shape, tri, aux)
            out[key] = _triangle_mesh(mi, key, tri, nrm, mesh_bsdf, uv)
        else:
            raise NotImplementedError(f"mitsuba export: shape type {kind!r} ({obj.name})")
    return out
