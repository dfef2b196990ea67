"""Convert a renderer `Scene` into a Mitsuba 3 scene dict, to time and cross-check against a named peer.

What carries over (exactly, up to tessellation where noted):
- camera: `pinhole` (pose, horizontal field of view, square pixels, centred principal point) as a Mitsuba
  `perspective` sensor with a box pixel filter, so pixel (x, y) of both images covers the same solid angle;
  an untilted `thin_lens` with square pixels and centred principal point as Mitsuba's `thinlens`
  (aperture_radius d/2, focus_distance U); a tilted thin lens (or any thin lens) and the
  `inverted_perspective` camera through our sensor plugins (`renderer.mitsuba.sensors`);
- lights: `point` (radiant intensity, 1/r² fall-off in both);
- shapes: `sphere`, `cylinder` (Mitsuba's open cylinder plus two disc caps), `rectangle`, `box` (Mitsuba's
  `cube` scaled and rotated), `plane` (a square of side `plane_size` centred on the plane's point), `cone`
  (triangles, `segments` around the axis, smooth side normals), `polyhedron` and `mesh` (triangles);
- materials: Lambert with reflectance diffuse · colour, or diffuse · a checker texture, made two-sided as
  the renderer shades both sides of every surface.
What does not: specular, mirror and refractive terms, ambient lights, image textures, the background
colour (Mitsuba would light the scene with it), layers, the lens distortion (neither Mitsuba's sensors nor
ours apply it), and the other cameras; `to_mitsuba` says which
it dropped in the returned `dropped` list, and raises NotImplementedError for a camera it cannot express.

Frames. Mitsuba's camera looks along its local +z with +x to the left and +y up in the image; ours looks
along +z with x right and y down (OpenCV). So the sensor's to_world has columns (−x_cam, −y_cam, z_cam,
position) in world coordinates, which keeps the image unmirrored (checked in `benchmarks/bench_fig6_mitsuba.py`
by comparing the two images). Our sensor plugins work in our camera frame and need no flip.

Mitsuba is an optional extra (`pip install -e '.[test]'` or `'.[bench]'`); it is imported on first use.
"""
from __future__ import annotations

import math
import os

import numpy as np

from ..transforms import world_from_local_4x4 as _matrix

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


def _cone_triangles(shape, segments: int):
    """World-space triangles (T, 3, 3) and per-corner normals (T, 3, 3) of a closed cone."""
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
    centre = np.zeros((segments, 3))
    base = np.stack([rim[1:], rim[:-1], centre], 1)
    base_normals = np.broadcast_to([0.0, 0.0, -1.0], base.shape)
    tri = np.concatenate([side, base]) @ R.T + o
    nrm = np.concatenate([side_normals, base_normals]) @ R.T
    return tri, nrm


def _polyhedron_triangles(shape):
    """World-space triangles (T, 3, 3) of a convex polyhedron: each face's vertices fanned around their mean."""
    normals, offsets = shape.normals.numpy(), shape.offsets.numpy()
    vertices = np.unique(np.round(shape.vertices.numpy(), 12), axis=0)
    scale = 1.0 + float(np.abs(offsets).max())
    tris = []
    for n, c in zip(normals, offsets):
        face = vertices[np.abs(vertices @ n - c) <= 1e-9 * scale]
        if len(face) < 3:
            continue
        centre = face.mean(0)
        u = face[0] - centre
        u /= np.linalg.norm(u)
        v = np.cross(n, u)
        order = np.argsort(np.arctan2((face - centre) @ v, (face - centre) @ u))
        ring = face[order]
        for i in range(len(ring)):
            tris.append([centre, ring[i], ring[(i + 1) % len(ring)]])
    return np.asarray(tris)


def _mesh_triangles(shape):
    v0, e1, e2 = shape.v0.numpy(), shape.e1.numpy(), shape.e2.numpy()
    return np.stack([v0, v0 + e1, v0 + e2], 1)


def _triangle_mesh(mi, name, tri, normals=None, bsdf=None):
    """A Mitsuba mesh of independent triangles (T, 3, 3), optionally with per-corner normals."""
    tri = np.ascontiguousarray(tri, dtype=np.float32).reshape(-1, 3)
    props = mi.Properties()
    if bsdf is not None:
        props["bsdf"] = bsdf
    mesh = mi.Mesh(name, tri.shape[0], tri.shape[0] // 3, props, has_vertex_normals=normals is not None)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(tri.ravel())
    params["faces"] = mi.UInt32(np.arange(tri.shape[0], dtype=np.uint32))
    if normals is not None:
        n = np.ascontiguousarray(normals, dtype=np.float32).reshape(-1, 3)
        params["vertex_normals"] = mi.Float(n.ravel())
    params.update()
    return mesh


def _bsdf(mi, material, uv_scale=None, dropped=None, name=""):
    """Two-sided Lambert: reflectance diffuse · colour or diffuse · checker (uv_scale: scene units per Mitsuba
    uv unit along (u, v), needed for a checker)."""
    kd = material.diffuse
    tex = material.texture
    if tex is not None and type(tex).__name__ == "CheckerTexture" and uv_scale is not None:
        # Ours: cell (i, j) = floor(u / size), floor(v / size) in scene units, colour i + j parity.
        # Mitsuba's checkerboard has two cells per texture unit: scale uv by uv_scale / (2 · size).
        sx, sy = (s / (2 * tex.size) for s in uv_scale)
        reflectance = {"type": "checkerboard",
                       "color0": {"type": "rgb", "value": [kd * c for c in tex.colors[0]]},
                       "color1": {"type": "rgb", "value": [kd * c for c in tex.colors[1]]},
                       "to_uv": mi.ScalarTransform4f().scale([sx, sy, 1.0])}
    else:
        if tex is not None and dropped is not None:
            dropped.append(f"{name}: texture (plain colour used)")
        reflectance = {"type": "rgb", "value": [kd * c for c in material.color]}
    if dropped is not None:
        for key in ("specular", "reflect", "transmit"):
            if getattr(material, key) > 0:
                dropped.append(f"{name}: {key}")
    return {"type": "twosided", "material": {"type": "diffuse", "reflectance": reflectance}}


def _native_lens(camera) -> bool:
    """Whether Mitsuba's own `perspective` / `thinlens` sensor reproduces the camera (square pixels, centred
    principal point, untilted)."""
    kind = type(camera).__name__
    if kind not in ("PinholeCamera", "ThinLensCamera"):
        return False
    (px, py), screen = camera.screen.pitch, camera.screen
    square = abs(px - py) <= 1e-9 * max(px, py)
    return square and screen.principal_point_px is None and (kind == "PinholeCamera" or camera.theta_F == 0)


def _sensor(mi, camera, spp: int, plugin: bool = False):
    """Mitsuba sensor dict: Mitsuba's own sensor where it matches the camera exactly (unless `plugin`), else
    our plugin (`renderer.mitsuba.sensors`)."""
    kind = type(camera).__name__
    if plugin or not _native_lens(camera):
        if kind in ("ThinLensCamera", "InvertedPerspectiveCamera"):
            from .sensors import sensor_dict

            return sensor_dict(mi, camera, spp)
        if kind != "PinholeCamera":
            raise NotImplementedError(f"mitsuba export: camera {kind} has no Mitsuba counterpart")
    screen = camera.screen
    W, H = screen.width_px, screen.height_px
    (px, py), q3 = screen.pitch, screen.distance
    if abs(px - py) > 1e-9 * max(px, py):
        raise NotImplementedError("mitsuba export: Mitsuba's perspective sensor needs square pixels")
    if screen.principal_point_px is not None:
        raise NotImplementedError("mitsuba export: only a centred principal point is supported")
    R = camera.transform.world_from_camera.numpy()
    t = camera.transform.position.numpy()
    to_world = _matrix(np.stack([-R[:, 0], -R[:, 1], R[:, 2]], axis=1), t)
    lens = {"type": "perspective"}
    if kind == "ThinLensCamera" and camera.d > 0:
        lens = {"type": "thinlens", "aperture_radius": camera.d / 2, "focus_distance": camera.U}
    return {
        **lens,
        "fov_axis": "x",
        "fov": math.degrees(2 * math.atan(screen.size[0] / 2 / q3)),
        "to_world": mi.ScalarTransform4f(to_world),
        "film": {"type": "hdrfilm", "width": W, "height": H, "rfilter": {"type": "box"},
                 "pixel_format": "rgb", "component_format": "float32"},
        "sampler": {"type": "independent", "sample_count": spp},
    }


def to_mitsuba(scene, spp: int | None = None, integrator: dict | None = None, *, variant: str | None = None,
               plane_size: float = 1e3, segments: int = 256, plugin_sensor: bool = False):
    """Mitsuba scene dict for `scene` (see the module docstring for what carries over).

    Args:
        spp: samples per pixel [scene.image.spp].
        integrator: Mitsuba integrator dict [direct lighting, one emitter sample, no BSDF samples].
        plane_size: side of the square standing in for an infinite plane, scene units.
        segments: facets around the axis of a cone.
        variant: Mitsuba variant to set [None: the current one, else the default, see `load_mitsuba`].
        plugin_sensor: use our sensor plugin even where Mitsuba's own sensor matches (pinhole excepted).
    Returns:
        (scene_dict, dropped): the dict for `mitsuba.load_dict`, and a list of what could not be expressed.
    """
    mi = load_mitsuba(variant)
    dropped: list[str] = []
    out = {
        "type": "scene",
        "integrator": integrator or {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0},
        "sensor": _sensor(mi, scene.camera, scene.image.spp if spp is None else spp, plugin_sensor),
    }
    distortion = scene.camera.distortion
    if distortion is not None and not distortion.is_identity:
        dropped.append("camera.distortion (brown_conrady) not applied")
    if any(scene.image.background):
        dropped.append("image.background (Mitsuba would light the scene with it)")
    if scene.layers:
        dropped.append("layers")
    for i, light in enumerate(scene.lights):
        if light.type == "point":
            out[f"light_{i}"] = {"type": "point", "position": list(light.position),
                                 "intensity": {"type": "rgb", "value": list(light.intensity)}}
        else:
            dropped.append(f"lights[{i}]: type {light.type}")
    out.update(shape_dicts(mi, scene, dropped, plane_size=plane_size, segments=segments))
    return out, dropped


def shape_dicts(mi, scene, dropped: list[str] | None = None, *, plane_size: float = 1e3, segments: int = 256,
                only=None) -> dict:
    """Mitsuba shapes of the scene's objects (those with an index in `only`, when given): {key: shape dict or
    loaded mesh}, keys `object_{i}` (a cylinder also `object_{i}_base` and `object_{i}_top`, its caps); what
    cannot be expressed is appended to `dropped`. See `to_mitsuba` for the other arguments."""
    T = mi.ScalarTransform4f
    out: dict = {}
    for i, obj in enumerate(scene.objects):
        if only is not None and i not in only:
            continue
        shape, kind, key = obj.shape, obj.shape.type_name, f"object_{i}"
        if kind == "sphere":
            out[key] = {"type": "sphere", "center": shape.center.tolist(), "radius": shape.radius,
                        "bsdf": _bsdf(mi, obj.material, (2 * math.pi * shape.radius, math.pi * shape.radius),
                                      dropped, obj.name)}
        elif kind == "rectangle":
            half = shape.half.tolist()
            out[key] = {"type": "rectangle",
                        "to_world": T(_matrix(shape.world_from_local.numpy(), shape.origin.numpy(), half + [1.0])),
                        "bsdf": _bsdf(mi, obj.material, (2 * half[0], 2 * half[1]), dropped, obj.name)}
        elif kind == "plane":
            R = np.stack([shape.tangent_u.numpy(), shape.tangent_v.numpy(), shape.normal.numpy()], axis=1)
            h = plane_size / 2
            out[key] = {"type": "rectangle", "to_world": T(_matrix(R, shape.point.numpy(), [h, h, 1.0])),
                        "bsdf": _bsdf(mi, obj.material, (plane_size, plane_size), dropped, obj.name)}
        elif kind == "box":
            out[key] = {"type": "cube",
                        "to_world": T(_matrix(shape.world_from_local.numpy(), shape.origin.numpy(), shape.half.tolist())),
                        "bsdf": _bsdf(mi, obj.material, None, dropped, obj.name)}
        elif kind == "cylinder":
            R, o = shape.world_from_local.numpy(), shape.origin.numpy()
            axis, r, h = R[:, 2], shape.radius, shape.height
            bsdf = _bsdf(mi, obj.material, None, dropped, obj.name)
            out[key] = {"type": "cylinder", "p0": o.tolist(), "p1": (o + h * axis).tolist(), "radius": r,
                        "bsdf": bsdf}
            out[key + "_base"] = {"type": "disk", "to_world": T(_matrix(R, o, [r, r, 1.0])), "bsdf": bsdf}
            out[key + "_top"] = {"type": "disk", "to_world": T(_matrix(R, o + h * axis, [r, r, 1.0])), "bsdf": bsdf}
        elif kind in ("cone", "polyhedron", "mesh"):
            bsdf = mi.load_dict(_bsdf(mi, obj.material, None, dropped, obj.name))
            if kind == "cone":
                tri, nrm = _cone_triangles(shape, segments)
            else:
                tri = _polyhedron_triangles(shape) if kind == "polyhedron" else _mesh_triangles(shape)
                nrm = None
            out[key] = _triangle_mesh(mi, key, tri, nrm, bsdf)
        else:
            raise NotImplementedError(f"mitsuba export: shape type {kind!r} ({obj.name})")
    return out
