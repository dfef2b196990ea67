"""A scene: objects (shape + material), lights, a camera, image settings and optional layers.

`Scene.intersect` finds the nearest hit for a flat batch of rays; `Scene.transmittance` answers shadow rays.
Both cull by packets: consecutive rays are grouped into packets of `TraceOptions.packet_size`, each packet
is bounded by a ball around its origins and a cone around its directions, and each bounded object is tested
only against the packets whose bounds can reach its bounding sphere (a (packets, objects) test, then a
gather of whole packets). The render loop feeds rays in screen tiles, so primary rays of a packet are
neighbours and the test is tight; incoherent batches only lose the saving, never correctness. Shadow rays
also skip the convex or flat object they leave (`Scene.self_shadow_free`), which cannot block them.

With `TraceOptions.compile`, each shape type's intersection and normals run as one fused torch.compile
graph per type (`per_class`, `compiled_call`), as do the integrator's per-ray arithmetic steps.
"""
from __future__ import annotations

import math
import types
import warnings
from dataclasses import dataclass, field

import torch

from renderer.cameras.base import Camera
from renderer.scene.materials import Material, MaterialTable
from renderer.core.rays import Hit, component_rows
from renderer.shapes.base import Shape, geometry_key

# Above this fraction of candidate packets, testing every ray in place is cheaper than gathering.
_COMPACT_BELOW = 0.75
# Culling slack: bounding radii grow by this factor and cone angles by this many radians, so float32
# rounding in the bounds can never drop a ray that the shape's own (also rounded) test would hit.
_RADIUS_SLACK = 1e-3
_ANGLE_SLACK = 1e-4
# A ray leaving a convex solid's surface from its outside (origin offset along the outward normal,
# direction into that half-space) cannot meet the solid again; nor can a ray leaving a flat shape on
# either side.
_CONVEX = {"sphere", "box", "cylinder", "cone", "polyhedron"}
_FLAT = {"rectangle", "plane"}
# Shape types whose intersection is not worth compiling: the mesh's loop over triangle chunks depends on
# the batch size, so every new batch size would recompile.
_EAGER_ONLY = {"mesh"}


@dataclass(frozen=True)
class TraceOptions:
    """How rays are traced. None of these change the image beyond float rounding (see tests/renderer/test_render.py).

    Attributes:
        culling: test bounded objects only against ray packets that can reach their bounding sphere [True].
        packet_size: rays per culling packet [64].
        compile: run shape intersections and normals (one graph per shape type) and the integrator's per-ray
            arithmetic through torch.compile, any batch size; falls back to eager with a warning where
            compiling fails [False]. Costs tens of seconds of compilation on first use in a process (much
            of it cached on disk by torch between runs); pays for renders of a few million rays or more.
        fast_paths: eager tracing only: scenes that only need direct light from point and ambient lights
            take `renderer.tracing.direct.trace_direct` on (3, N) rows [True]; False forces the general integrator.
        intersector: who answers nearest-hit and shadow-ray queries: `torch` (ours), `mitsuba` (Embree
            through Mitsuba 3's llvm variant, CPU only; cameras and shading stay in torch; see
            `renderer.mitsuba.intersect`) or `auto`: `mitsuba` where it answers exactly what was asked (CPU,
            float32, every shape one Mitsuba has, no scene tensor needing gradients, Mitsuba's llvm variant
            loading here: `renderer.mitsuba.intersect.auto_engine`), else `torch`, silently. Either answers
            float32 rays without gradients only; float64 rays, rays that need gradients and layers' first
            hits stay with ours ["auto"; `torch` for our own intersection code bit for bit].
        jit_kernels: with the mitsuba intersector, eager tracing: the scenes `renderer.tracing.jit_direct` shades
            (direct light, thin lens; the speed scene's kind) are traced as Dr.Jit kernels beside Embree [True];
            False: shaded in torch between the Embree calls (`renderer.tracing.direct`), as before it.
    """

    culling: bool = True
    packet_size: int = 64
    compile: bool = False
    fast_paths: bool = True
    intersector: str = "auto"
    jit_kernels: bool = True


@dataclass
class SceneObject:
    name: str
    shape: Shape
    material: Material = field(default_factory=Material)


@dataclass(frozen=True)
class Light:
    """`point`: position (scene units) and intensity (linear RGB, radiant intensity; falls off as 1/r²).
    `ambient`: intensity only, added as ambient · albedo without shadows."""

    type: str
    intensity: tuple[float, float, float]
    position: tuple[float, float, float] | None = None


@dataclass(frozen=True)
class ImageSettings:
    """Output image: size in pixels, samples per pixel, recursion depth, background colour and sampler."""

    width: int
    height: int
    spp: int = 1
    max_depth: int = 5
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    sampler: str = "sobol"


_MISSING = object()
_COMPILED: dict = {}  # function -> its torch.compile wrapper, or None where compiling failed
_PER_CLASS: dict = {}  # (function, class) -> a copy of the function with its own code object
# Leading dimensions at least this long are batch dimensions: compiled graphs treat them as dynamic.
_MIN_DYNAMIC = 16


def per_class(fn, cls):
    """A copy of `fn` with its own code object for `cls`.

    torch.compile keeps one cache of graphs per code object, with a small limit; giving every shape class
    its own copy of a generic helper (`fn(shape, ...)`) gives each class its own cache.
    """
    key = (fn, cls)
    if key not in _PER_CLASS:
        code = fn.__code__.replace(co_name=f"{fn.__name__}__{cls.__name__}")
        _PER_CLASS[key] = types.FunctionType(code, fn.__globals__, code.co_name, fn.__defaults__, fn.__closure__)
    return _PER_CLASS[key]


def compiled_call(enabled: bool, fn, *args):
    """fn(*args), through torch.compile when `enabled`.

    One graph per function (per code object: see `per_class`), dynamic in the leading dimension of every
    tensor argument that has at least `_MIN_DYNAMIC` rows, so fixed sizes (3 coordinates, 6 box faces)
    stay static and vectorise, and any batch size reuses the graph. Falls back to eager, with one warning,
    where compiling is unavailable or fails; batches of fewer than 2 rays always run eagerly (torch
    specialises sizes 0 and 1).
    """
    first = next((a for a in args if isinstance(a, torch.Tensor)), None)
    if not enabled or first is None or first.shape[0] < 2:
        return fn(*args)
    entry = _COMPILED.get(fn, _MISSING)
    if entry is _MISSING:
        try:
            # Small matrix products (points @ 3×3 rotations) become fused arithmetic instead of GEMM calls.
            entry = torch.compile(fn, options={"decompose_mem_bound_mm": True})
        except Exception as e:  # no compiler backend on this platform
            warnings.warn(f"torch.compile unavailable ({e}); tracing eagerly", RuntimeWarning, stacklevel=2)
            entry = None
        _COMPILED[fn] = entry
    if entry is None:
        return fn(*args)
    for a in args:
        if isinstance(a, torch.Tensor) and a.dim() and a.shape[0] >= _MIN_DYNAMIC:
            torch._dynamo.maybe_mark_dynamic(a, 0)
    try:
        return entry(*args)
    except Exception as e:
        warnings.warn(f"torch.compile failed for {fn.__qualname__} ({type(e).__name__}: {e}); using eager",
                      RuntimeWarning, stacklevel=2)
        _COMPILED[fn] = None
        return fn(*args)


def _nearest(shape, o_p, d_p, sel, t_min: float, t_best, obj, aux, k):
    """Packets `sel` (all when None) of rays (B, P, 3) tested against `shape` and merged with the nearest
    hits so far: returns the merged (t, object, aux) rows of those packets, each (m, P)."""
    if sel is not None:
        o_p, d_p = o_p.index_select(0, sel), d_p.index_select(0, sel)
        t_best, obj, aux = t_best.index_select(0, sel), obj.index_select(0, sel), aux.index_select(0, sel)
    t, a = shape.intersect(o_p.reshape(-1, 3), d_p.reshape(-1, 3), t_min)
    t, a = t.view_as(t_best), a.view_as(aux)
    closer = t < t_best
    return torch.where(closer, t, t_best), torch.where(closer, k, obj), torch.where(closer, a, aux)


def _shape_hits(shape, o_p, d_p, sel, t_min: float, need_aux: bool = True):
    """(t, aux) of `shape` for the packets `sel` (all when None) of (3, B, P) component rows, each (m, P)
    (aux None where not needed and the shape skips it)."""
    if sel is not None:
        o_p, d_p = o_p.index_select(1, sel), d_p.index_select(1, sel)
    t, a = shape.intersect_soa(o_p.reshape(3, -1), d_p.reshape(3, -1), t_min, need_aux)
    return t.view(o_p.shape[1:]), None if a is None else a.view(o_p.shape[1:])


def _nearest_eager(shape, o_p, d_p, sel, t_min: float, t_best, obj, aux, k: int):
    """`_nearest` without torch.compile, on (3, B, P) component rows (see `Shape.intersect_soa`)."""
    t, a = _shape_hits(shape, o_p, d_p, sel, t_min)
    if sel is not None:
        t_best, obj, aux = t_best.index_select(0, sel), obj.index_select(0, sel), aux.index_select(0, sel)
    closer = t < t_best
    return torch.where(closer, t, t_best), obj.masked_fill(closer, k), torch.where(closer, a, aux)


def _blocked_eager(shape, o_p, d_p, sel, t_min: float, t_max, trans, factor):
    """`_occluded` (factor None) or `_attenuated` without torch.compile, on (3, B, P) component rows."""
    t, _ = _shape_hits(shape, o_p, d_p, sel, t_min, need_aux=False)
    if sel is not None:
        t_max, trans = t_max.index_select(0, sel), trans.index_select(0, sel)
    if factor is None:
        return trans.masked_fill(t < t_max, 0)
    return torch.where((t < t_max)[..., None], trans * factor, trans)


def _occluded(shape, o_p, d_p, sel, t_min: float, t_max, visible):
    """Visibility (m, P) of packets `sel` (all when None) after an opaque `shape`: 0 where it blocks."""
    if sel is not None:
        o_p, d_p = o_p.index_select(0, sel), d_p.index_select(0, sel)
        t_max, visible = t_max.index_select(0, sel), visible.index_select(0, sel)
    t, _ = shape.intersect(o_p.reshape(-1, 3), d_p.reshape(-1, 3), t_min)
    return visible.masked_fill(t.view_as(t_max) < t_max, 0)


def _attenuated(shape, o_p, d_p, sel, t_min: float, t_max, trans, factor):
    """Transmittance (m, P, 3) of packets `sel` (all when None) after `shape`, which passes `factor` (3,)."""
    if sel is not None:
        o_p, d_p = o_p.index_select(0, sel), d_p.index_select(0, sel)
        t_max, trans = t_max.index_select(0, sel), trans.index_select(0, sel)
    t, _ = shape.intersect(o_p.reshape(-1, 3), d_p.reshape(-1, 3), t_min)
    return torch.where((t.view_as(t_max) < t_max)[..., None], trans * factor, trans)


def _holds_grad(x, depth: int = 5) -> bool:
    """Whether x is, or holds within `depth` levels of attributes, lists and dicts, a tensor requiring grad."""
    if isinstance(x, torch.Tensor):
        return x.requires_grad
    if depth == 0 or isinstance(x, (str, bytes, int, float, bool)) or x is None:
        return False
    if isinstance(x, dict):
        items = x.values()
    elif isinstance(x, (list, tuple)):
        items = x
    elif hasattr(x, "__dict__"):
        items = vars(x).values()
    else:
        return False
    return any(_holds_grad(v, depth - 1) for v in items)


@dataclass
class Scene:
    """Everything needed to render. `layers` holds mixed-projection layers (see cameras.layers); `options`
    how rays are traced (speed only)."""

    objects: list[SceneObject]
    lights: list[Light]
    camera: Camera
    image: ImageSettings
    layers: list = field(default_factory=list)
    options: TraceOptions = field(default_factory=TraceOptions)

    def __post_init__(self):
        self.geometry = None
        self.refresh()

    def refresh(self) -> None:
        """Recompute what the scene derives from its objects (culling spheres, extent, and everything kept by
        `derived`) if an object, shape or material was replaced or a shape's tensor edited in place since it
        was last computed (`renderer.shapes.base.geometry_key`, kept as `geometry`). `render` calls it once
        per render; a caller tracing rays through `intersect`/`shadow` itself after moving a shape calls it
        first."""
        key = geometry_key(self)
        if key == self.geometry:
            return
        self.geometry = key
        self._derived: dict = {}
        names = [o.name for o in self.objects]
        self.index_of = {n: i for i, n in enumerate(names)}
        bounded = [o.shape.bounding_sphere() for o in self.objects]
        self._bounded_ids = [i for i, b in enumerate(bounded) if b is not None]
        self._unbounded_ids = [i for i, b in enumerate(bounded) if b is None]
        self._centers = torch.stack([torch.as_tensor(bounded[i][0], dtype=torch.float64).reshape(3)
                                     for i in self._bounded_ids]) if self._bounded_ids else torch.zeros(0, 3)
        self._radii = torch.tensor([float(bounded[i][1]) for i in self._bounded_ids], dtype=torch.float64)
        ext = [float(torch.linalg.vector_norm(c)) + r for c, r in zip(self._centers, self._radii.tolist())]
        self.extent = max(ext + [1.0])
        self._convex = torch.tensor([o.shape.type_name in _CONVEX for o in self.objects], dtype=torch.bool)
        self._flat = torch.tensor([o.shape.type_name in _FLAT for o in self.objects], dtype=torch.bool)

    def requires_grad(self) -> bool:
        """Whether any tensor held by its objects, lights, camera or layers requires grad (then the defaults
        `intersector="auto"` and `workers=None` of `render` keep to this process and our own tracer)."""
        return _holds_grad([self.objects, self.lights, self.camera, self.layers])

    @property
    def ray_epsilon(self) -> float:
        """Offset for secondary-ray origins and the minimum hit distance, relative to the scene size."""
        return 1e-5 * self.extent

    def derived(self, key, build):
        """What `build()` makes from the scene's objects (a material table, the Embree scene, normal tables),
        made on first use and kept under `key` (hashable; name the owner, e.g. ("direct.normals", device,
        dtype)) until `refresh` sees an object, shape or material change. Not pickled: a scene sent to a
        worker process builds its own."""
        if key not in self._derived:
            self._derived[key] = build()
        return self._derived[key]

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_derived"] = {}  # Dr.Jit scenes do not pickle, and a worker builds what it needs
        return state

    def __copy__(self):
        """A shallow copy shares the objects, so it shares what is derived from them too (until one of the two
        sees a change in `refresh`, which gives that one a new cache)."""
        copy = object.__new__(type(self))
        copy.__dict__.update(self.__dict__)
        return copy

    def materials(self, like: torch.Tensor) -> MaterialTable:
        """The objects' materials stacked as tensors on `like`'s device and in its dtype."""
        return self.derived(("materials", like.device, like.dtype),
                            lambda: MaterialTable([o.material for o in self.objects], like.device, like.dtype))

    def _compiled(self, k: int, fn, options: TraceOptions, args):
        """fn(shape_k, *args), compiled per shape class when options.compile is set (see `compiled_call`)."""
        shape = self.objects[k].shape
        if not options.compile or shape.type_name in _EAGER_ONLY:
            return fn(shape, *args)
        # Fill the shape's parameter cache eagerly first, so that compiled graphs see it filled.
        self.derived(("compile.warm", k, args[0].device, args[0].dtype), lambda: _warm_up(shape, args[0]))
        return compiled_call(True, per_class(fn, type(shape)), shape, *args)

    def _external(self, options: TraceOptions, object_mask, *rays: torch.Tensor):
        """The external intersector named by `options.intersector`, or None for ours: also where it cannot
        honour a first-hit object mask, and for rays it would not answer exactly (float64, which it would
        round to float32, or rays that need gradients, which its hits do not carry)."""
        if options.intersector == "torch" or (object_mask is not None and not all(object_mask)):
            return None
        if options.intersector not in ("mitsuba", "auto"):
            raise ValueError(f"TraceOptions.intersector: unknown {options.intersector!r} (expected torch, mitsuba "
                             "or auto)")
        if rays[0].dtype != torch.float32 or (torch.is_grad_enabled() and any(r.requires_grad for r in rays)):
            return None
        from renderer.mitsuba.intersect import auto_engine, engine

        return engine(self) if options.intersector == "mitsuba" else auto_engine(self, rays[0].device, rays[0].dtype)

    @staticmethod
    def _all_packets(o_p):
        return torch.arange(o_p.shape[0], device=o_p.device)

    def surface(self, k: int, p: torch.Tensor, aux: torch.Tensor, *, options: TraceOptions | None = None):
        """Outward normals (n, 3) and uv (n, 2) of object k at its hit points p (n, 3) with `aux` (n,)."""
        options = self.options if options is None else options
        return self._compiled(k, _surface_of, options, (p, aux))

    def _packets(self, o, d, t_max, options: TraceOptions, object_mask, skip=None, rows: bool = False):
        """Split the batch into packets and decide which objects each packet must test.

        Args:
            o, d: (N, 3) origins and directions, or (3, N) component rows with `rows` (eager only).
            skip: optional (N,) object id (−1 for none) that each ray cannot meet (see `self_shadow_free`);
                a packet whose rays all skip the same object does not test it.
        Returns:
            (o_p, d_p, t_max_p, plan): the inputs padded to whole packets and viewed as (packets, P, 3), or
            as (3, packets, P) component rows when tracing eagerly (t_max_p (packets, P) either way),
            and plan = [(k, sel)] for every object k to test, sel the (m,) packet indices or None for all
            packets.
        """
        if not options.compile and not rows:  # eager tracing works on (3, N) rows: see `Shape.intersect_soa`
            o, d, rows = component_rows(o), component_rows(d), True
        n = o.shape[1] if rows else o.shape[0]
        P = max(1, int(options.packet_size)) if options.culling else 1
        pad = (-n) % P
        if pad and rows:
            o = torch.cat([o, o[:, -1:].expand(3, pad)], 1)
            d = torch.cat([d, d[:, -1:].expand(3, pad)], 1)
        elif pad:  # repeat the last ray: it does not widen the last packet's bounds
            o = torch.cat([o, o[-1:].expand(pad, 3)])
            d = torch.cat([d, d[-1:].expand(pad, 3)])
        if pad:
            if t_max is not None:
                t_max = torch.cat([t_max, t_max[-1:].expand(pad)])
            if skip is not None:
                skip = torch.cat([skip, skip[-1:].expand(pad)])
        t_p = None if t_max is None else t_max.view(-1, P)
        if options.compile:
            o_p, d_p = o.reshape(-1, P, 3), d.reshape(-1, P, 3)
        else:
            o_p, d_p = o.view(3, -1, P), d.view(3, -1, P)
        n_packets = o_p.shape[0 if options.compile else 1]
        wanted = [k for k in range(len(self.objects)) if object_mask is None or object_mask[k]]
        if P == 1:
            return o_p, d_p, t_p, [(k, None) for k in wanted]
        cand = torch.ones(n_packets, len(self.objects), dtype=torch.bool, device=o.device)
        if self._bounded_ids and options.compile:
            cand[:, self._bounded_ids] = compiled_call(options.compile, packet_candidates, o_p, d_p,
                                                       self._centers.to(o), self._radii.to(o), t_p)
        elif self._bounded_ids:
            # Bounds from component rows: reductions over a (B, P, 3) middle axis are slow in eager torch.
            o_lo, o_hi = packet_bounds_soa(o_p)
            d_lo, d_hi = packet_bounds_soa(d_p)
            cand[:, self._bounded_ids] = candidates_from_bounds(o_lo, o_hi, d_lo, d_hi, self._centers.to(o),
                                                                self._radii.to(o), t_p)
        if skip is not None:
            skip_p = skip.view(-1, P)
            first = skip_p[:, 0]
            rows = ((skip_p == first[:, None]).all(1) & (first >= 0)).nonzero().squeeze(1)
            cand[rows, first.index_select(0, rows)] = False
        counts = cand.sum(0).tolist()
        plan = []
        for k in wanted:
            if counts[k] == 0:
                continue
            plan.append((k, None if counts[k] > _COMPACT_BELOW * n_packets else cand[:, k].nonzero().squeeze(1)))
        return o_p, d_p, t_p, plan

    def self_shadow_free(self, obj: torch.Tensor, entering: torch.Tensor) -> torch.Tensor:
        """(n,) the object that a ray leaving its hit point cannot meet again, or −1.

        For hit points on object `obj` (n,) reached from outside (`entering`, n,) of a convex solid, or on
        either side of a flat shape, a ray whose origin is offset along the normal facing that side and
        whose direction points into that side cannot meet the object again: its shadow rays skip it.
        """
        convex, flat = self._convex.to(obj.device), self._flat.to(obj.device)
        free = flat.index_select(0, obj) | (entering & convex.index_select(0, obj))
        return torch.where(free, obj, -1)

    def intersect(self, o: torch.Tensor, d: torch.Tensor, object_mask: list[bool] | None = None, *,
                  options: TraceOptions | None = None) -> Hit:
        """Nearest hit of each ray.

        Args:
            o, d: (N, 3) origins and unit directions, world frame.
            object_mask: optional per-object flags; only flagged objects are considered (layers).
            options: how to trace [self.options]; the result does not depend on it beyond float rounding.
        """
        options = self.options if options is None else options
        if not options.compile:  # eager tracing: one path, on (3, N) rows
            return self.intersect_rows(component_rows(o), component_rows(d), object_mask, options=options)
        external = self._external(options, object_mask, o, d)
        if external is not None:
            return Hit(*external.nearest(component_rows(o), component_rows(d), self.ray_epsilon))
        n = o.shape[0]
        o_p, d_p, _, plan = self._packets(o, d, None, options, object_mask)
        t_best = torch.full(o_p.shape[:2], float("inf"), dtype=o.dtype, device=o.device)
        obj = torch.full(o_p.shape[:2], -1, dtype=torch.long, device=o.device)
        aux = torch.zeros(o_p.shape[:2], dtype=torch.long, device=o.device)
        # One graph per shape class: gather every packet rather than none.
        plan = [(k, self._all_packets(o_p) if sel is None else sel) for k, sel in plan]
        for k, sel in plan:
            rows = self._compiled(k, _nearest, options, (o_p, d_p, sel, self.ray_epsilon, t_best, obj, aux,
                                                         torch.tensor(k, device=o.device)))
            t_best, obj, aux = _merged((t_best, obj, aux), rows, sel)
        return Hit(t_best.view(-1)[:n], obj.view(-1)[:n], aux.view(-1)[:n])

    def intersect_rows(self, o: torch.Tensor, d: torch.Tensor, object_mask: list[bool] | None = None, *,
                       options: TraceOptions | None = None) -> Hit:
        """`intersect` for (3, N) component rows o, d (eager tracing; see `Shape.intersect_soa`)."""
        options = self.options if options is None else options
        external = self._external(options, object_mask, o, d)
        if external is not None:
            return Hit(*external.nearest(o, d, self.ray_epsilon))
        n = o.shape[1]
        o_p, d_p, _, plan = self._packets(o, d, None, options, object_mask, rows=True)
        t_best = torch.full(o_p.shape[1:], float("inf"), dtype=o.dtype, device=o.device)
        obj = torch.full(o_p.shape[1:], -1, dtype=torch.long, device=o.device)
        aux = torch.zeros(o_p.shape[1:], dtype=torch.long, device=o.device)
        for k, sel in plan:
            rows = _nearest_eager(self.objects[k].shape, o_p, d_p, sel, self.ray_epsilon, t_best, obj, aux, k)
            t_best, obj, aux = _merged((t_best, obj, aux), rows, sel)
        return Hit(t_best.view(-1)[:n], obj.view(-1)[:n], aux.view(-1)[:n])

    def answers_shadow_rays(self, options: TraceOptions | None, *rays: torch.Tensor) -> bool:
        """Whether our own tracer answers `visibility_rows` for these rays (o, d, t_max), not an external
        intersector: only then does it use `leaving`."""
        return self._external(self.options if options is None else options, None, *rays) is None

    def visibility_rows(self, o: torch.Tensor, d: torch.Tensor, t_max: torch.Tensor, *,
                        options: TraceOptions | None = None, leaving: torch.Tensor | None = None) -> torch.Tensor:
        """(N,) 1 where nothing opaque lies on o + t·d for t in (ε, t_max), else 0; o, d (3, N) component
        rows. Every object must be opaque (see `shadow` for transparent ones)."""
        options = self.options if options is None else options
        external = self._external(options, None, o, d, t_max)
        if external is not None:
            return external.visible(o, d, t_max, self.ray_epsilon)
        n = o.shape[1]
        o_p, d_p, t_p, plan = self._packets(o, d, t_max, options, None, leaving, rows=True)
        vis = torch.ones(o_p.shape[1:], dtype=o.dtype, device=o.device)
        for k, sel in plan:
            rows = _blocked_eager(self.objects[k].shape, o_p, d_p, sel, self.ray_epsilon, t_p, vis, None)
            (vis,) = _merged((vis,), (rows,), sel)
        return vis.view(-1)[:n]

    def transmittance(self, o: torch.Tensor, d: torch.Tensor, t_max: torch.Tensor, *,
                      options: TraceOptions | None = None) -> torch.Tensor:
        """(N, 3) fraction of light reaching o from o + t_max·d: opaque blockers give 0, transparent ones
        multiply by their transmit · colour (each object counted once)."""
        return self.shadow(o, d, t_max, options=options).expand(o.shape[0], 3).contiguous()

    def shadow(self, o: torch.Tensor, d: torch.Tensor, t_max: torch.Tensor, *,
               options: TraceOptions | None = None, leaving: torch.Tensor | None = None) -> torch.Tensor:
        """`transmittance` as (N, 1) when every object is opaque (visibility 0 or 1), else (N, 3).

        Args:
            leaving: optional (N,) id of an object each ray cannot meet (−1 for none), from
                `self_shadow_free`.
        """
        options = self.options if options is None else options
        table = self.materials(o)
        opaque = not bool(table.shadow_transmittance.any())
        external = self._external(options, None, o, d, t_max) if opaque else None
        if external is not None:
            return external.visible(component_rows(o), component_rows(d), t_max, self.ray_epsilon)[:, None]
        n = o.shape[0]
        o_p, d_p, t_p, plan = self._packets(o, d, t_max, options, None, leaving)
        rows_shape = o_p.shape[:2] if options.compile else o_p.shape[1:]
        trans = torch.ones(rows_shape if opaque else (*rows_shape, 3), dtype=o.dtype, device=o.device)
        eps = self.ray_epsilon
        if options.compile:
            plan = [(k, self._all_packets(o_p) if sel is None else sel) for k, sel in plan]
        for k, sel in plan:
            if not options.compile:
                rows = _blocked_eager(self.objects[k].shape, o_p, d_p, sel, eps, t_p, trans,
                                      None if opaque else table.shadow_transmittance[k])
            elif opaque:
                rows = self._compiled(k, _occluded, options, (o_p, d_p, sel, eps, t_p, trans))
            else:
                rows = self._compiled(k, _attenuated, options, (o_p, d_p, sel, eps, t_p, trans,
                                                                table.shadow_transmittance[k]))
            if sel is None:
                trans = rows
            else:
                trans.index_copy_(0, sel, rows)
        return trans.reshape(-1, 1)[:n] if opaque else trans.reshape(-1, 3)[:n]


def _merged(state: tuple, rows: tuple, sel):
    """A shape's per-packet results written into the running state: all packets (sel None) replace it,
    selected packets are copied into their rows."""
    if sel is None:
        return tuple(rows)
    for dst, src in zip(state, rows):
        dst.index_copy_(0, sel, src)
    return state


def _warm_up(shape, like: torch.Tensor) -> bool:
    """Run the shape's intersection and surface eagerly once on like's device and dtype (fills its parameter
    cache, `Shape._param`); True."""
    p = torch.zeros(2, 3, dtype=like.dtype, device=like.device)
    shape.intersect(p, p, 0.0)
    shape.surface(p, torch.zeros(2, dtype=torch.long, device=p.device))
    return True


def _surface_of(shape, p, aux):
    return shape.surface(p, aux)


def packet_candidates(o_p: torch.Tensor, d_p: torch.Tensor, centers: torch.Tensor, radii: torch.Tensor,
                      t_max: torch.Tensor | None = None) -> torch.Tensor:
    """Which packets of rays can meet which spheres (conservative).

    A packet's origins lie in a ball (o_c, ρ) and its unit directions in a cone (axis a, half-angle θ), both
    from the bounding boxes of its origins and directions. If a ray of the packet meets the sphere (c, r),
    the ray with the same direction from o_c meets the sphere (c, r + ρ), so its direction is within
    α = asin((r + ρ)/|c − o_c|) of c − o_c, and the angle φ between c − o_c and a is at most θ + α.
    With t_max, the sphere must also start within the longest ray: |c − o_c| − (r + ρ) ≤ max t_max.

    Args:
        o_p, d_p: (B, P, 3) packets of origins and unit directions; centers (K, 3), radii (K,) spheres.
        t_max: optional (B, P) ray lengths.
    Returns:
        (B, K) bool, True where the packet must be tested against sphere k.
    """
    o_lo, o_hi = torch.aminmax(o_p, dim=1)
    d_lo, d_hi = torch.aminmax(d_p, dim=1)
    return candidates_from_bounds(o_lo, o_hi, d_lo, d_hi, centers, radii, t_max)


def packet_bounds_soa(x_s: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-packet coordinate bounds (lo, hi), each (B, 3), of (3, B, P) component rows (fast in eager torch)."""
    return x_s.amin(-1).T, x_s.amax(-1).T


def candidates_from_bounds(o_lo, o_hi, d_lo, d_hi, centers, radii, t_max=None) -> torch.Tensor:
    """`packet_candidates` from the packets' origin and direction bounds (B, 3) each; t_max (B, P) or None."""
    o_c = (o_lo + o_hi) / 2
    rho = torch.linalg.vector_norm(o_hi - o_lo, dim=-1) / 2
    axis = (d_lo + d_hi) / 2
    spread = torch.linalg.vector_norm(d_hi - d_lo, dim=-1) / 2
    length = torch.linalg.vector_norm(axis, dim=-1)
    # Every direction in the box lies within `spread` of its centre `axis`, so within asin(spread/|axis|).
    theta = torch.where(spread < length, torch.asin((spread / length.clamp_min(1e-30)).clamp(max=1.0)),
                        torch.full_like(length, math.pi))
    axis = axis / length.clamp_min(1e-30)[:, None]
    # v = centre − o_c per packet and sphere, (B, K) per component: (B, K, 3) norms and cross products
    # are slow in eager torch.
    vx, vy, vz = (centers[:, i][None] - o_c[:, i, None] for i in range(3))
    ax, ay, az = (axis[:, i, None] for i in range(3))
    if t_max is not None:
        t_max = t_max.amax(1)
    dist = (vx * vx + vy * vy + vz * vz).sqrt()
    reach = radii * (1 + _RADIUS_SLACK) + rho[:, None]
    cx, cy, cz = vy * az - vz * ay, vz * ax - vx * az, vx * ay - vy * ax
    phi = torch.atan2((cx * cx + cy * cy + cz * cz).sqrt(), vx * ax + vy * ay + vz * az)
    alpha = torch.asin((reach / dist.clamp_min(1e-30)).clamp(max=1.0))
    ok = (dist <= reach) | (phi <= theta[:, None] + alpha + _ANGLE_SLACK)
    if t_max is not None:
        ok &= dist - reach <= t_max[:, None]
    return ok
