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

from renderer.core.params import MAX_SPP, SAMPLERS  # noqa: F401 - the names, declared without torch for the command line

_M32 = 0xFFFFFFFF


def _hash32(x: torch.Tensor) -> torch.Tensor:
    """Integer hash (lowbias32) of int64 tensors holding values < 2³²; returns values in [0, 2³²)."""
    x = x & _M32
    x = x ^ (x >> 16)
    x = (x * 0x7FEB352D) & _M32
    x = x ^ (x >> 15)
    x = (x * 0x846CA68B) & _M32
    return x ^ (x >> 16)


def _chain(h, key):
    """One step of the key chain behind `uniform_hash` (works on ints and int64 tensors alike)."""
    return _hash32(key + h * 0x9E3779B1)


def uniform_hash(*keys: torch.Tensor | int) -> torch.Tensor:
    """Uniform float64 numbers in [0, 1) from integer keys (broadcast together).

    The keys are chained left to right, so shaping them to broadcast progressively (per pixel, then per
    sample, then per dimension) hashes each prefix once instead of once per output element.
    """
    h = torch.zeros((), dtype=torch.int64)
    for k in keys:
        h = _chain(h, torch.as_tensor(k, dtype=torch.int64))
    return h.to(torch.float64) / 2.0**32


def _unit(h: torch.Tensor) -> torch.Tensor:
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
        if not 1 <= spp <= MAX_SPP:
            raise ValueError(f"spp: expected an integer in 1..{MAX_SPP}, got {spp}")
        self.name, self.spp, self.seed = name, spp, seed
        # The seed's first links of the key chains, as 0-dim tensors: the same numbers as the ints (the chain
        # keeps the low 32 bits), but a compiled caller (`renderer.tracing.fused`) takes them as inputs instead of
        # constants, so a new seed does not compile its stages again.
        self._keys = [torch.tensor(_chain(0, seed + offset), dtype=torch.int64) for offset in (0, 1, 7919)]
        if name == "sobol":
            engine = torch.quasirandom.SobolEngine(4, scramble=True, seed=seed)
            self._points = engine.draw(spp, dtype=torch.float64)

    @property
    def sobol_points(self) -> torch.Tensor:
        """`sobol`: the (spp, 4) float64 point set every pixel shifts (`pixel_block`)."""
        return self._points

    @property
    def sobol_shift_key(self) -> torch.Tensor:
        """`sobol`: the first link (0-dim int64) of the key chain that hashes a pixel's shift (`pixel_block`)."""
        return self._keys[2]

    def pixel_samples(self, pixel: torch.Tensor) -> torch.Tensor:
        """All spp samples of each pixel: (n, spp, 4) float64, equal to samples(pixel[i], s) for s < spp.

        Args:
            pixel: (n,) long pixel indices (row · width + column).
        """
        spp = self.spp
        if self.name == "center":
            return torch.full((pixel.shape[0], spp, 4), 0.5, dtype=torch.float64)
        pix = pixel[:, None, None]
        sample = torch.arange(spp)[None, :, None]
        dims = torch.arange(4)
        if self.name == "independent":
            return uniform_hash(self.seed, pix, sample, dims)
        if self.name == "sobol":
            return torch.remainder(self._points + uniform_hash(self.seed + 7919, pix, dims), 1.0)
        return self._stratified(pix, sample, dims)

    def pixel_columns(self, pixel: torch.Tensor) -> list[torch.Tensor]:
        """All spp samples of each pixel as four (n, spp) float64 columns (pixel jitter x, y; lens u, v),
        equal to `pixel_samples(pixel)[..., i]`: the rows of `pixel_block`."""
        return list(self.pixel_block(pixel).unbind(0))

    def pixel_block(self, pixel: torch.Tensor) -> torch.Tensor:
        """All spp samples of each pixel as one new (4, n, spp) float64 tensor on pixel's device, rows pixel
        jitter x, y, lens u, v: block[i] equals `pixel_samples(pixel)[..., i]`. Keys shared by a pixel's
        samples are hashed once per pixel, and each step runs once over the whole block."""
        n, spp = pixel.shape[0], self.spp
        if self.name == "center":
            return torch.full((4, n, spp), 0.5, dtype=torch.float64, device=pixel.device)
        dims = torch.arange(4, device=pixel.device)
        sample = torch.arange(spp, device=pixel.device)
        if self.name == "sobol":
            h = _chain(self._keys[2].to(pixel.device), pixel)  # (n,)
            shift = _unit(_chain(h, dims[:, None]))  # (4, n)
            v = self._points.to(pixel.device).T[:, None, :] + shift[:, :, None]  # in [0, 2)
            return v.frac_()  # v − 1 where v >= 1 (exact): torch.remainder(v, 1.0) of `pixel_samples`
        h = _chain(_chain(self._keys[0].to(pixel.device), pixel[:, None]), sample)  # (n, spp)
        jitter = _unit(_chain(h, dims[:, None, None]))
        if self.name == "independent":
            return jitter
        nx, ny = _grid(spp)
        lens_stratum = permute(sample, spp, _chain(self._keys[1].to(pixel.device), pixel[:, None]))
        return torch.stack([(sample % nx + jitter[0]) / nx, (sample // nx + jitter[1]) / ny,
                            (lens_stratum % nx + jitter[2]) / nx, (lens_stratum // nx + jitter[3]) / ny])

    def samples(self, pixel: torch.Tensor, sample: torch.Tensor) -> torch.Tensor:
        """Samples for matching (n,) pixel and sample indices: (n, 4) float64."""
        dims = torch.arange(4)
        if self.name == "center":
            return torch.full((pixel.shape[0], 4), 0.5, dtype=torch.float64)
        if self.name == "independent":
            return uniform_hash(self.seed, pixel[:, None], sample[:, None], dims)
        if self.name == "sobol":
            shift = uniform_hash(self.seed + 7919, pixel[:, None], dims)
            return torch.remainder(self._points[sample] + shift, 1.0)
        return self._stratified(pixel[:, None], sample[:, None], dims)

    def _stratified(self, pixel, sample, dims):
        """Stratified samples; pixel and sample broadcast against each other and against dims (4,)."""
        nx, ny = _grid(self.spp)
        jitter = uniform_hash(self.seed, pixel, sample, dims)
        lens_stratum = permute(sample, self.spp, _chain(_chain(0, self.seed + 1), pixel))
        px = (sample % nx + jitter[..., 0:1]) / nx
        py = (sample // nx + jitter[..., 1:2]) / ny
        lx = (lens_stratum % nx + jitter[..., 2:3]) / nx
        ly = (lens_stratum // nx + jitter[..., 3:4]) / ny
        return torch.cat(torch.broadcast_tensors(px, py, lx, ly), -1)


def camera_samples(sampler: Sampler, pixel: torch.Tensor, width: int, dtype: torch.dtype):
    """Pixel positions (n·spp, 2) (x = column, y = row) and lens samples (n·spp, 2) in [0, 1)² for all
    samples of the pixels `pixel` (n,), the samples of a pixel consecutive. Both are (n·spp, 2) views of one
    (4, n·spp) block of rows x, y, u, v (the cameras read them row by row), made in float64 and rounded to
    `dtype` once."""
    block = sampler.pixel_block(pixel)  # (4, n, spp), ours to write to
    block[0] += ((pixel % width).to(torch.float64) - 0.5)[:, None]
    block[1] += ((pixel // width).to(torch.float64) - 0.5)[:, None]
    rows = block.to(dtype).view(4, -1)
    return rows[:2].T, rows[2:].T


def permute(index: torch.Tensor, n: int, key: torch.Tensor) -> torch.Tensor:
    """Element `index` of a pseudo-random permutation of range(n) chosen by the 32-bit `key` (broadcast).

    Kensler's hash-based permutation ("Correlated Multi-Jittered Sampling", 2013), the one pbrt uses:
    a bijection on the next power of two, applied again while the result falls outside range(n) (cycle
    walking), so every key gives a true permutation and no table is stored. Stratified sampling uses one per
    pixel to pair lens strata with pixel strata without correlating them.
    """
    w = n - 1
    for shift in (1, 2, 4, 8, 16):
        w |= w >> shift
    p = torch.as_tensor(key, dtype=torch.int64) & _M32
    i, p = torch.broadcast_tensors(torch.as_tensor(index, dtype=torch.int64), p)
    i, p = i.clone(), p.clone()
    todo = torch.ones_like(i, dtype=torch.bool)
    for _ in range(64):  # each round leaves a value outside range(n) with probability < 1/2
        j = i.clone()
        j = j ^ p
        j = (j * 0xE170893D) & _M32
        j = j ^ (p >> 16)
        j = j ^ ((j & w) >> 4)
        j = j ^ (p >> 8)
        j = (j * 0x0929EB3F) & _M32
        j = j ^ (p >> 23)
        j = j ^ ((j & w) >> 1)
        j = (j * (1 | (p >> 27))) & _M32
        j = (j * 0x6935FA69) & _M32
        j = j ^ ((j & w) >> 11)
        j = (j * 0x74DCB303) & _M32
        j = j ^ ((j & w) >> 2)
        j = (j * 0x9E501CC3) & _M32
        j = j ^ ((j & w) >> 2)
        j = (j * 0xC860A3DF) & _M32
        j = j & w
        j = j ^ (j >> 5)
        i = torch.where(todo, j, i)
        todo = todo & (i >= n)
        if not bool(todo.any()):
            break
    return (i + p) % n
