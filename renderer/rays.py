"""Ray batches and hit records: the tensors every stage of the tracer passes along."""
from __future__ import annotations

from dataclasses import dataclass

import torch


_EYE = torch.eye(3)


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
        """Rays given in a local frame moved to the world: x_world = R x_local + t."""
        if (not torch.compiler.is_compiling() and world_from_local.shape == (3, 3)
                and bool((world_from_local == _EYE.to(world_from_local)).all())):
            # The identity rotation (a camera looking along +z): skip two (N, 3) x (3, 3) products (eager
            # only: the check is data-dependent, a graph break for torch.compile).
            return Rays(self.origin + local_origin_in_world, self.direction, self.valid, self.weight)
        return Rays(
            self.origin @ world_from_local.transpose(-1, -2) + local_origin_in_world,
            self.direction @ world_from_local.transpose(-1, -2),
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


def normalize(v: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """Unit vectors along the last axis; zero vectors stay zero instead of turning into NaN."""
    return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True).clamp_min(eps)
