"""Samplers over pixel × lens: 4 uniform numbers per sample (pixel jitter x, y; lens u, v).

Samplers are stateless functions of (pixel index, sample index, seed), so a render split into chunks gives
the same image as one done at once, and the caller owns the randomness.
- `independent`: uniform random numbers (hashed counters).
- `stratified`: jittered strata; the pixel square and the lens square are each split into an nx × ny grid
  (nx · ny = spp, as square as possible), with the lens strata permuted against the pixel strata per pixel.
- `sobol`: Owen-scrambled Sobol points (torch's SobolEngine), one point set for all pixels, decorrelated
  between pixels by a random toroidal shift (Cranley–Patterson rotation) per pixel.
- `center`: pixel centres and the lens centre (deterministic; for tests and previews).
"""
from __future__ import annotations

import math

import torch

SAMPLERS = ("independent", "stratified", "sobol", "center")

_M32 = 0xFFFFFFFF


def _hash32(x: torch.Tensor) -> torch.Tensor:
    """Integer hash (lowbias32) of int64 tensors holding values < 2³²; returns values in [0, 2³²)."""
    x = x & _M32
    x = x ^ (x >> 16)
    x = (x * 0x7FEB352D) & _M32
    x = x ^ (x >> 15)
    x = (x * 0x846CA68B) & _M32
    return x ^ (x >> 16)


def uniform_hash(*keys: torch.Tensor | int) -> torch.Tensor:
    """Uniform float64 numbers in [0, 1) from integer keys (broadcast together)."""
    h = torch.zeros((), dtype=torch.int64)
    for k in keys:
        h = _hash32(torch.as_tensor(k, dtype=torch.int64) + h * 0x9E3779B1)
    return h.to(torch.float64) / 2.0**32


def _grid(n: int) -> tuple[int, int]:
    nx = int(math.isqrt(n))
    while n % nx:
        nx -= 1
    return n // nx, nx


class Sampler:
    """samples(pixel, sample) -> (n, 4) float64 in [0, 1): pixel jitter (x, y) then lens (u, v)."""

    def __init__(self, name: str, spp: int, seed: int = 0):
        if name not in SAMPLERS:
            raise ValueError(f"sampler: expected one of {', '.join(SAMPLERS)}, got {name!r}")
        if spp < 1:
            raise ValueError(f"spp: expected a positive integer, got {spp}")
        self.name, self.spp, self.seed = name, spp, seed
        if name == "sobol":
            engine = torch.quasirandom.SobolEngine(4, scramble=True, seed=seed)
            self._points = engine.draw(spp, dtype=torch.float64)

    def samples(self, pixel: torch.Tensor, sample: torch.Tensor) -> torch.Tensor:
        dims = torch.arange(4)
        if self.name == "center":
            return torch.full((pixel.shape[0], 4), 0.5, dtype=torch.float64)
        if self.name == "independent":
            return uniform_hash(self.seed, pixel[:, None], sample[:, None], dims)
        if self.name == "sobol":
            shift = uniform_hash(self.seed + 7919, pixel[:, None], dims)
            return torch.remainder(self._points[sample] + shift, 1.0)
        # stratified
        nx, ny = _grid(self.spp)
        jitter = uniform_hash(self.seed, pixel[:, None], sample[:, None], dims)
        offset = (uniform_hash(self.seed + 1, pixel) * self.spp).long()
        lens_stratum = (sample * _coprime_step(self.spp) + offset) % self.spp
        px = (sample % nx + jitter[:, 0]) / nx
        py = (sample // nx + jitter[:, 1]) / ny
        lx = (lens_stratum % nx + jitter[:, 2]) / nx
        ly = (lens_stratum // nx + jitter[:, 3]) / ny
        return torch.stack([px, py, lx, ly], -1)


def _coprime_step(n: int) -> int:
    """A step coprime with n near 0.618 n, so lens strata visit all cells in a scrambled order."""
    step = max(1, round(0.618 * n))
    while math.gcd(step, n) != 1:
        step += 1
    return step
