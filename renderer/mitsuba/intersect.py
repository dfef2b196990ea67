"""Ray intersection by Mitsuba 3 (Embree on the CPU) for batches of torch rays; cameras and shading stay in torch.

`TraceOptions(intersector="mitsuba")` (or `render(..., intersector="mitsuba")`, `renderer render
--intersector mitsuba`) sends the scene's nearest-hit queries and shadow rays here; so does the default,
`intersector="auto"`, where `auto_engine` finds that this engine answers the render exactly as asked
(else our own tracer answers, without a word). The scene's shapes are
built once per scene as a Mitsuba scene in a JIT variant (`llvm_ad_rgb`, shapes mapped by
`renderer.mitsuba.shapes.shape_dicts`) and cached; each batch of rays goes to Dr.Jit as zero-copy views of the
torch rows (DLPack), Mitsuba's `ray_intersect_preliminary` / `ray_test` run in one fused kernel with the
look-ups below, and the results come back as zero-copy torch views.

What comes back is what `Scene.intersect` returns, a `Hit` (t, object id, aux), so the integrator computes
normals and texture coordinates from (object, aux) exactly as for its own hits: aux is the box face
(0..5 −x, +x, −y, +y, −z, +z), the polyhedron's plane, the mesh triangle, the cylinder part (0 side, 1 base,
2 top), 0 for spheres, rectangles and planes. It is looked up per Mitsuba shape and triangle from tables
built at load time (`aux_table`), by Mitsuba's shape registry id and primitive index.

Shapes whose Mitsuba counterpart is the same surface: sphere, rectangle, box (Mitsuba's `cube` mesh),
cylinder (open cylinder + two discs), polyhedron and mesh (their exact triangles), plane (a rectangle of
side `PLANE_SIDE` times the scene's extent: the same plane for every hit within that distance). Other
objects (a cone, which Mitsuba would tessellate, CSG) are tested by their own torch code against every ray of
the batch (no culling) and merged by distance (`fallback`). Layers' first-hit object masks and transparent
blockers (which need each object's transmittance on a shadow ray) are answered by our own tracer
(`Scene.intersect`, `Scene.shadow`).

Precision: Mitsuba traces in float32, and its hits carry no gradients, so `Scene` sends only float32 rays
that need no gradients here (float64 and differentiable rays stay with our tracer). Hits beyond the
minimum distance t_min = `Scene.ray_epsilon` are emulated by starting each ray at o + t_min·d. Shadow rays
do not skip the object they leave (`Scene.self_shadow_free`): their origins are already offset along the
normal by t_min, which Embree's watertight triangle and Mitsuba's analytic tests respect up to rounding.
"""
from __future__ import annotations

import math
import sys

import numpy as np
import torch

from camio.interrupts import held
from .shapes import shape_dicts
from .variants import load_mitsuba

# Shape types with an exact Mitsuba counterpart (see the module docstring).
EXACT = {"sphere", "rectangle", "box", "cylinder", "polyhedron", "mesh", "plane"}
# Side of the square standing in for an infinite plane, in units of the scene's extent.
PLANE_SIDE = 1e4
DEFAULT_VARIANT = "llvm_ad_rgb"
_CYLINDER_PART = {"": 0, "_base": 1, "_top": 2}
# Local outward normals of the box faces 0..5, as in renderer/shapes/box.py.
_BOX_FACES = np.array([[-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1]], dtype=np.float64)


def _triangle_aux(shape, tri: np.ndarray) -> np.ndarray:
    """(T,) aux of each Mitsuba triangle tri (T, 3, 3) (world frame) of a box, polyhedron or mesh."""
    kind = shape.type_name
    if kind == "mesh":
        return np.arange(tri.shape[0])
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    if kind == "box":
        faces = _BOX_FACES @ shape.world_from_local.numpy().T  # (6, 3) world normals
        return np.argmax(n @ faces.T, axis=1)
    # polyhedron: the plane n_k·x = c_k through the triangle's centre whose normal it shares
    normals, offsets = shape.normals.numpy(), shape.offsets.numpy()
    scale = np.linalg.norm(normals, axis=1)
    centre = tri.mean(1)
    off_plane = np.abs(centre @ normals.T - offsets) / scale  # (T, K) distances to each plane
    facing = (n @ (normals / scale[:, None]).T) > 1 - 1e-6
    return np.argmin(np.where(facing, off_plane, np.inf), axis=1)


class MitsubaIntersector:
    """The shapes of a `Scene` as a Mitsuba scene, answering nearest-hit and shadow queries for torch rays.

    Args:
        scene: the renderer scene; objects without an exact Mitsuba counterpart (`EXACT`) are traced by
            their own torch code (`fallback`, their indices).
        variant: a Mitsuba JIT variant that runs here (see `variants.jit_variant_runs`).
    Raises:
        NotImplementedError: no JIT variant runs here (one line).
    """

    def __init__(self, scene, variant: str = DEFAULT_VARIANT):
        self.shapes = [obj.shape for obj in scene.objects]
        exact = {k for k, shape in enumerate(self.shapes) if shape.type_name in EXACT}
        self.fallback = [k for k in range(len(self.shapes)) if k not in exact]
        mi = load_mitsuba(variant)
        if not mi.variant().startswith(("llvm", "cuda")):
            raise NotImplementedError(f"intersector mitsuba: variant {variant} does not run here (got {mi.variant()})")
        import drjit as dr

        self.mi, self.dr, self.variant = mi, dr, mi.variant()
        shapes = shape_dicts(mi, scene, plane_size=PLANE_SIDE * scene.extent, only=exact)
        for value in shapes.values():
            if isinstance(value, dict):
                value.pop("bsdf", None)  # intersection only
        self.mscene = mi.load_dict({"type": "scene", **shapes})
        # Per Mitsuba shape, indexed by its registry id: our object index (_obj_of), and where its aux values
        # start in _aux (_start) with _stride 1 (one per triangle: box, polyhedron, mesh) or 0 (one value).
        entries = []
        for s in self.mscene.shapes():
            key = s.id()
            base = key[:-5] if key.endswith("_base") else key[:-4] if key.endswith("_top") else key
            k = int(base.split("_")[1])
            shape = scene.objects[k].shape
            if shape.type_name in ("box", "polyhedron", "mesh"):
                tri = np.array(s.vertex_positions_buffer(), dtype=np.float64).reshape(-1, 3)
                faces = np.array(s.faces_buffer(), dtype=np.int64).reshape(-1, 3)
                aux = _triangle_aux(shape, tri[faces])
                per_prim = True
            else:
                aux = np.array([_CYLINDER_PART[key[len(base):]] if shape.type_name == "cylinder" else 0])
                per_prim = False
            sid = int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(s))[0])
            entries.append((sid, k, aux, per_prim))
        size = max([e[0] for e in entries] + [0]) + 1
        obj_of, start, stride, table = np.full(size, -1), np.zeros(size), np.zeros(size), []
        offset = 0
        for sid, k, aux, per_prim in entries:
            obj_of[sid], start[sid], stride[sid] = k, offset, int(per_prim)
            table.append(aux)
            offset += len(aux)
        # Object and aux tables as 64-bit integers: the hits come back as the torch longs `Hit` holds, no cast.
        self._obj_of = mi.Int64(obj_of.astype(np.int64))
        self._start = mi.UInt32(start.astype(np.uint32))
        self._stride = mi.UInt32(stride.astype(np.uint32))
        self._aux = mi.Int64(np.concatenate(table + [np.zeros(1)]).astype(np.int64))

    def _ray(self, o, d, t_min: float, t_max=None):
        """Mitsuba rays from (3, N) rows o, d (torch, float32 views, no copy), starting at o + t_min·d."""
        if o.device.type != "cpu":
            raise ValueError(f"intersector mitsuba: rays on {o.device}; it traces CPU tensors only (variant {self.variant})")
        self.ensure_variant()
        F = self.mi.Float
        return self.jit_ray([F(_f32(o[i])) for i in range(3)], [F(_f32(d[i])) for i in range(3)], t_min,
                            None if t_max is None else F(_f32(t_max)))

    def ensure_variant(self):
        """Mitsuba's global variant set back to this engine's where another caller switched it (a `--backend
        mitsuba` render with `scalar_rgb`, say): `mi.Float` and the other types follow the variant."""
        if self.mi.variant() != self.variant:
            self.mi.set_variant(self.variant)

    def jit_ray(self, o, d, t_min: float, t_max=None):
        """A Mitsuba ray from three Dr.Jit `mi.Float` components each of origin o and direction d (and of the
        distance t_max, None: unbounded), starting at o + t_min·d."""
        mi = self.mi
        self.ensure_variant()
        origin = mi.Point3f(o[0] + t_min * d[0], o[1] + t_min * d[1], o[2] + t_min * d[2])
        maxt = mi.Float(math.inf) if t_max is None else t_max - t_min
        return mi.Ray3f(origin, mi.Vector3f(*d), maxt, 0.0, mi.Color0f())

    def jit_nearest(self, ray, t_min: float, index_type=None):
        """The nearest hits of a Mitsuba `ray` (`jit_ray`) as Dr.Jit arrays, not evaluated (so that a caller's
        kernel takes them in): (t, object, aux), t +inf and object −1 on a miss; object and aux of
        `index_type` [mi.Int64, what `nearest` hands to torch]."""
        mi, dr = self.mi, self.dr
        index_type = mi.Int64 if index_type is None else index_type
        pi = self.mscene.ray_intersect_preliminary(ray, coherent=True)
        valid = pi.is_valid()
        sid = dr.reinterpret_array(mi.UInt32, pi.shape)
        obj = index_type(dr.gather(mi.Int64, self._obj_of, sid))
        index = dr.gather(mi.UInt32, self._start, sid) + dr.gather(mi.UInt32, self._stride, sid) * pi.prim_index
        aux = index_type(dr.gather(mi.Int64, self._aux, index, valid))
        t = dr.select(valid, pi.t + t_min, math.inf)
        return t, dr.select(valid, obj, -1), aux

    def jit_visible(self, ray):
        """1.0 where nothing blocks the Mitsuba `ray` (`jit_ray` with t_max) before its end, else 0.0, as a
        Dr.Jit `mi.Float`, not evaluated; rays of length <= 0 are visible."""
        mi, dr = self.mi, self.dr
        active = ray.maxt > 0
        blocked = self.mscene.ray_test(ray, active)
        return dr.select(blocked & active, 0.0, mi.Float(1.0))

    def nearest(self, o: torch.Tensor, d: torch.Tensor, t_min: float):
        """Nearest hits beyond t_min of the rays o, d given as (3, N) rows: (t, object, aux), each (N,) torch
        (t in o's dtype, +inf on a miss; object −1 on a miss, long; aux long)."""
        t, obj, aux = self.jit_nearest(self._ray(o, d, t_min), t_min)
        self.dr.eval(t, obj, aux)
        t, obj, aux = _to_torch(t, obj, aux)
        t, obj, aux = t.to(o.dtype), obj.long(), aux.long()
        for k in self.fallback:
            t_k, aux_k = self.shapes[k].intersect_soa(o, d, t_min)
            closer = t_k < t
            t, obj, aux = torch.where(closer, t_k, t), obj.masked_fill(closer, k), torch.where(closer, aux_k, aux)
        return t, obj, aux

    def visible(self, o: torch.Tensor, d: torch.Tensor, t_max: torch.Tensor, t_min: float) -> torch.Tensor:
        """(N,) 1 where nothing lies on o + t·d for t in (t_min, t_max), else 0 (o's dtype); o, d (3, N) rows."""
        vis = self.jit_visible(self._ray(o, d, t_min, t_max))
        self.dr.eval(vis)
        vis = _to_torch(vis)[0].to(o.dtype)
        for k in self.fallback:
            t_k, _ = self.shapes[k].intersect_soa(o, d, t_min, need_aux=False)
            vis = vis.masked_fill(t_k < t_max, 0)
        return vis


def _to_torch(*arrays):
    """Evaluated Dr.Jit arrays as torch tensors sharing their memory (DLPack; waits for the kernel)."""
    return tuple(a.torch() for a in arrays)


def _f32(x: torch.Tensor) -> torch.Tensor:
    """x as a contiguous float32 tensor on the CPU (no copy where it already is one)."""
    return x.to(torch.float32).contiguous()


def engine(scene) -> MitsubaIntersector:
    """The scene's `MitsubaIntersector`, built on first use and kept by the scene (`Scene.derived`: rebuilt
    after `Scene.refresh` saw a shape move)."""
    return scene.derived("mitsuba.engine", lambda: MitsubaIntersector(scene))


def _engine_or_none(scene) -> MitsubaIntersector | None:
    try:
        return engine(scene)
    except Exception:  # noqa: BLE001 - a scene Mitsuba cannot build is traced by ours
        return None


_LLVM: list = []  # [whether Mitsuba's LLVM variant loads here], probed once per process


def llvm_available() -> bool:
    """Whether Mitsuba imports and its LLVM variant (`DEFAULT_VARIANT`) runs here; probed once per process
    (`variants.jit_variant_runs` tries a kernel in a child process), any failure meaning no."""
    if not _LLVM:
        # A Ctrl-C is held over the import and the probe: one inside the extension's import came back as an
        # ImportError, read here as "no Mitsuba", and the render went on (camio.interrupts).
        with held():
            try:
                _LLVM.append(load_mitsuba(DEFAULT_VARIANT).variant().startswith("llvm"))
            except Exception:  # noqa: BLE001 - not installed, broken install, no libLLVM: all mean "use ours"
                _LLVM.append(False)
    return _LLVM[0]


def auto_engine(scene, device, dtype) -> MitsubaIntersector | None:
    """The engine `intersector="auto"` uses for the scene's rays on `device` in `dtype`, or None for our own
    tracer. Embree answers where its hits are the ones asked for: rays on the CPU in float32, a scene with
    objects all of an `EXACT` type and no tensor that needs gradients (Embree's hits carry none), and
    Mitsuba's LLVM variant loading here (`llvm_available`) and not another variant chosen by someone else in
    this process (switching Mitsuba's global variant costs about 30 ms and would change theirs). A scene
    Mitsuba fails to build falls back too. Per-ray rules stay `Scene`'s (rays that need gradients, layers'
    first-hit masks go to ours)."""
    if torch.device(device).type != "cpu" or dtype != torch.float32 or not scene.objects:
        return None
    mi = sys.modules.get("mitsuba")
    if mi is not None and mi.variant() not in (None, DEFAULT_VARIANT):
        return None
    if any(obj.shape.type_name not in EXACT for obj in scene.objects) or scene.requires_grad():
        return None
    if not llvm_available():
        return None
    with held():  # a Ctrl-C raised inside Mitsuba's scene build would read as a scene it cannot build
        return scene.derived("mitsuba.auto_engine", lambda: _engine_or_none(scene))  # a failure is not tried again


def set_jit_threads(n: int) -> int:
    """Set Dr.Jit's thread pool to n threads (what the Embree kernels run on); returns the previous size."""
    import drjit as dr

    previous = dr.thread_count()
    if n != previous:
        dr.set_thread_count(n)
    return previous


def use_intersector(scene, name: str, device="cpu") -> None:
    """Set `scene.options.intersector` to `name`, building the Mitsuba scene now (for the command line: a
    machine it cannot serve fails before any rendering).

    Raises:
        ValueError: `mitsuba` asked for on a device other than the CPU.
        NotImplementedError, ImportError: no Mitsuba JIT variant runs here.
    """
    from dataclasses import replace

    if name == "mitsuba":
        if torch.device(device).type != "cpu":
            raise ValueError(f"traces on the CPU only, not on {device}")
        engine(scene)
    scene.options = replace(scene.options, intersector=name)
