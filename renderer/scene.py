"""A scene: objects (shape + material), lights, a camera, image settings and optional layers.

`Scene.intersect` finds the nearest hit for a flat batch of rays. Each bounded shape is tested only
against the rays that can reach its bounding sphere (one (N, K) test, then compaction), so an object
that covers a small part of the screen costs little. `Scene.transmittance` answers shadow rays.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import torch

from .cameras.base import Camera
from .materials import Material, MaterialTable
from .rays import Hit
from .shapes.base import Shape

# Above this fraction of candidate rays, testing every ray is cheaper than compacting.
_COMPACT_BELOW = 0.6


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


@dataclass
class Scene:
    """Everything needed to render. `layers` holds mixed-projection layers (see cameras.layers)."""

    objects: list[SceneObject]
    lights: list[Light]
    camera: Camera
    image: ImageSettings
    layers: list = field(default_factory=list)

    def __post_init__(self):
        self._tables: dict = {}
        names = [o.name for o in self.objects]
        self.index_of = {n: i for i, n in enumerate(names)}
        bounded = [o.shape.bounding_sphere() for o in self.objects]
        self._bounded_ids = [i for i, b in enumerate(bounded) if b is not None]
        self._unbounded_ids = [i for i, b in enumerate(bounded) if b is None]
        if self._bounded_ids:
            self._centers = torch.stack([bounded[i][0].to(torch.float64) for i in self._bounded_ids])
            self._radii = torch.tensor([bounded[i][1] for i in self._bounded_ids], dtype=torch.float64)
        ext = [float(torch.linalg.vector_norm(c)) + r for c, r in (b for b in bounded if b is not None)]
        self.extent = max(ext + [1.0])

    @property
    def ray_epsilon(self) -> float:
        """Offset for secondary-ray origins and the minimum hit distance, relative to the scene size."""
        return 1e-5 * self.extent

    def materials(self, like: torch.Tensor) -> MaterialTable:
        key = (like.device, like.dtype)
        if key not in self._tables:
            self._tables[key] = MaterialTable([o.material for o in self.objects], like.device, like.dtype)
        return self._tables[key]

    def _candidates(self, o, d, t_max=None):
        """(N, Kb) bool: rays that can meet each bounded object's bounding sphere (within t_max)."""
        c = self._centers.to(o)
        r = self._radii.to(o)
        oc = c[None] - o[:, None]  # (N, Kb, 3)
        tca = (oc * d[:, None]).sum(-1)
        d2 = (oc * oc).sum(-1) - tca * tca
        ok = (d2 <= r * r) & (tca + r > 0)
        if t_max is not None:
            ok &= tca - r < t_max[:, None]
        return ok

    def _each_object(self, o, d, object_mask=None, t_max=None):
        """Yield (k, idx) with idx the ray indices (or None for all) worth testing against object k."""
        if self._bounded_ids:
            cand = self._candidates(o, d, t_max)
            frac = cand.float().mean(0)
            for j, k in enumerate(self._bounded_ids):
                if object_mask is not None and not object_mask[k]:
                    continue
                if frac[j] > _COMPACT_BELOW:
                    yield k, None
                else:
                    idx = cand[:, j].nonzero().squeeze(1)
                    if idx.numel():
                        yield k, idx
        for k in self._unbounded_ids:
            if object_mask is None or object_mask[k]:
                yield k, None

    def intersect(self, o: torch.Tensor, d: torch.Tensor, object_mask: list[bool] | None = None) -> Hit:
        """Nearest hit of each ray.

        Args:
            o, d: (N, 3) origins and unit directions, world frame.
            object_mask: optional per-object flags; only flagged objects are considered (layers).
        """
        n = o.shape[0]
        t_best = torch.full((n,), float("inf"), dtype=o.dtype, device=o.device)
        obj = torch.full((n,), -1, dtype=torch.long, device=o.device)
        aux = torch.zeros(n, dtype=torch.long, device=o.device)
        eps = self.ray_epsilon
        for k, idx in self._each_object(o, d, object_mask):
            shape = self.objects[k].shape
            if idx is None:
                t, a = shape.intersect(o, d, eps)
                closer = t < t_best
                t_best = torch.where(closer, t, t_best)
                obj = torch.where(closer, torch.full_like(obj, k), obj)
                aux = torch.where(closer, a, aux)
            else:
                t, a = shape.intersect(o[idx], d[idx], eps)
                closer = t < t_best[idx]
                sel = idx[closer]
                t_best[sel] = t[closer]
                obj[sel] = k
                aux[sel] = a[closer]
        return Hit(t_best, obj, aux)

    def transmittance(self, o: torch.Tensor, d: torch.Tensor, t_max: torch.Tensor) -> torch.Tensor:
        """(N, 3) fraction of light reaching o from o + t_max·d: opaque blockers give 0, transparent ones
        multiply by their transmit · colour (each object counted once)."""
        trans = torch.ones(o.shape[0], 3, dtype=o.dtype, device=o.device)
        table = self.materials(o)
        eps = self.ray_epsilon
        for k, idx in self._each_object(o, d, None, t_max):
            shape = self.objects[k].shape
            if idx is None:
                t, _ = shape.intersect(o, d, eps)
                blocked = t < t_max
                trans = torch.where(blocked[:, None], trans * table.shadow_transmittance[k], trans)
            else:
                t, _ = shape.intersect(o[idx], d[idx], eps)
                blocked = idx[t < t_max[idx]]
                trans[blocked] = trans[blocked] * table.shadow_transmittance[k]
        return trans
