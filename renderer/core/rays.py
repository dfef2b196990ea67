"""Ray batches and hit records: the tensors every stage of the tracer passes along."""
from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class Rays:
    """A batch of rays in the world frame.

    Attributes:
        origin: (..., 3) ray origins, world frame, scene units.
        direction: (..., 3) unit directions, world frame.
        valid: (...,) bool; False where the camera produces no ray (the pixel then receives nothing).
        weight: (...,) float; the sample's weight in the pixel estimate (1 for ordinary cameras).
    """

    origin: torch.Tensor
    direction: torch.Tensor
    valid: torch.Tensor
    weight: torch.Tensor

    @property
    def shape(self) -> torch.Size:
        return self.origin.shape[:-1]

    def reshape(self, *shape: int) -> "Rays":
        return Rays(
            self.origin.reshape(*shape, 3),
            self.direction.reshape(*shape, 3),
            self.valid.reshape(*shape),
            self.weight.reshape(*shape),
        )

    def transformed(self, world_from_local: torch.Tensor, local_origin_in_world: torch.Tensor) -> "Rays":
        """Rays given in a local frame moved to the world: x_world = R x_local + t. No test of R's values per
        batch: for the identity the products give x + t exactly (finite rays)."""
        o, d = self.origin, self.direction
        o_rows, d_rows = o.movedim(-1, 0), d.movedim(-1, 0)
        if world_from_local.shape == (3, 3) and o_rows.is_contiguous() and d_rows.is_contiguous():
            # (..., 3) views of (3, ...) rows (the thin lens makes them): transform the rows, keep the layout.
            shape = o_rows.shape
            o_new = torch.addmm(local_origin_in_world[:, None], world_from_local, o_rows.reshape(3, -1))
            d_new = world_from_local @ d_rows.reshape(3, -1)
            return Rays(o_new.reshape(shape).movedim(0, -1), d_new.reshape(shape).movedim(0, -1), self.valid,
                        self.weight)
        return Rays(
            o @ world_from_local.transpose(-1, -2) + local_origin_in_world,
            d @ world_from_local.transpose(-1, -2),
            self.valid,
            self.weight,
        )


@dataclass
class Hit:
    """The nearest intersection of each ray of a flat batch (N rays).

    Attributes:
        t: (N,) ray parameter of the hit, +inf where the ray hits nothing.
        object_id: (N,) long index into the scene's objects, -1 on a miss.
        aux: (N,) long per-shape detail (face or triangle index) the shape needs for its normal.
    """

    t: torch.Tensor
    object_id: torch.Tensor
    aux: torch.Tensor

    @property
    def found(self) -> torch.Tensor:
        return self.object_id >= 0


def component_rows(x: torch.Tensor) -> torch.Tensor:
    """(N, 3) vectors -> (3, N) contiguous component rows, the layout of the tracer's row code
    (`Shape.intersect_soa`, `Scene.intersect_rows`, `renderer.tracing.direct`): the transposed view where x already is
    a view of such rows (free; `vectors_from_rows` makes them), else a stack of its three columns (several
    times faster than `x.T.contiguous()` in eager torch)."""
    rows = x.T
    return rows if rows.is_contiguous() else torch.stack(x.unbind(-1))


def vectors_from_rows(x, y, z) -> torch.Tensor:
    """(..., 3) vectors from their three (...,) components, as a view of (3, ...) rows: the tracer's row code
    (`Scene.intersect_rows`, `renderer.tracing.direct`) then takes them without a transposing copy."""
    return torch.stack(torch.broadcast_tensors(x, y, z)).movedim(0, -1)


def unit_vectors_from_rows(x, y, z, eps: float = 1e-12) -> torch.Tensor:
    """`normalize` of the vectors with components x, y, z, as `vectors_from_rows` lays them out."""
    inv = torch.rsqrt(x * x + y * y + z * z).clamp_max(1.0 / eps)
    return vectors_from_rows(x * inv, y * inv, z * inv)


def normalize_rows_(v: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """(3, ...) vector rows made unit length in place, as `unit_vectors_from_rows` computes them (the same
    bits); returns v. For tensors that need no gradient."""
    norm2 = v[0] * v[0]
    norm2 += v[1] * v[1]
    norm2 += v[2] * v[2]
    return v.mul_(norm2.rsqrt_().clamp_max_(1.0 / eps))


def normalize(v: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """Unit vectors along the last axis; zero vectors stay zero instead of turning into NaN."""
    return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True).clamp_min(eps)
