"""Materials (Whitted-style: diffuse, Phong specular, mirror, refraction) and textures.

Shading model for a surface point with albedo c (the `color` or the texture):
    L = (1 − reflect − transmit) · [diffuse · c/π · Σ_lights E_l  +  specular · Phong]  + ambient · c
        + reflect · L(reflected ray)  +  transmit · c · L(refracted ray)
where E_l = I_l · max(0, n·l) / r² · (shadow transmittance) for a point light of intensity I_l.
Total internal reflection sends the transmitted share along the reflected ray.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch


@dataclass(frozen=True)
class CheckerTexture:
    """Procedural checker in the shape's uv coordinates (scene units): cells of `size`, two colours."""

    size: float
    colors: tuple[tuple[float, float, float], tuple[float, float, float]]

    def evaluate(self, uv: torch.Tensor) -> torch.Tensor:
        """(N, 2) uv -> (N, 3) linear RGB albedo."""
        cell = torch.floor(uv / self.size).long().sum(-1) % 2
        cols = torch.tensor(self.colors, dtype=uv.dtype, device=uv.device)
        return cols[cell]

    @property
    def palette(self) -> tuple[tuple[float, float, float], ...]:
        """The colours `palette_index` picks from: the two of the checker."""
        return self.colors

    def palette_index(self, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """`evaluate` on component rows: (N,) long index into `palette` of the points with texture coordinates
        u, v ((N,) each). Float arithmetic only, no integer casts (one fused loop under torch.compile); the
        same cells as `evaluate` while |cell| < 2^24."""
        cell = torch.floor(u / self.size) + torch.floor(v / self.size)
        half = cell * 0.5  # odd cells: half an integer (exact)
        return (half != half.floor()).long()


@dataclass(frozen=True)
class ImageTexture:
    """Image mapped onto the shape's uv coordinates, one copy per `size` (scene units), repeated.

    The image is read once through OpenImageIO and decoded to linear RGB (8-bit files are sRGB).
    """

    file: str
    size: tuple[float, float]
    pixels: np.ndarray = field(repr=False, compare=False, default=None)  # (H, W, 3) linear float32
    # No few colours to index (`CheckerTexture.palette`): the fast paths shade its hits with `evaluate`.
    palette = None

    def evaluate(self, uv: torch.Tensor) -> torch.Tensor:
        """(N, 2) uv -> (N, 3) linear RGB, bilinear between texel centres and wrapping at the tile edges.

        Bilinear (not the nearest texel) so the colour is continuous in uv: rendered edges are not quantised
        to texels and gradients with respect to anything that moves the hit point are non-zero.
        """
        img = torch.as_tensor(self.pixels, dtype=uv.dtype, device=uv.device)
        h, w = img.shape[:2]
        # Texel (i, j) has its centre at s = (i + 0.5) / w; fx in [0, w) measured from texel 0's centre.
        fx = torch.remainder(uv[..., 0] / self.size[0], 1.0) * w - 0.5
        fy = torch.remainder(uv[..., 1] / self.size[1], 1.0) * h - 0.5
        x0, y0 = torch.floor(fx), torch.floor(fy)
        ax, ay = (fx - x0)[..., None], (fy - y0)[..., None]
        x0, y0 = x0.long(), y0.long()
        xa, xb = torch.remainder(x0, w), torch.remainder(x0 + 1, w)
        ya, yb = torch.remainder(y0, h), torch.remainder(y0 + 1, h)
        top = img[ya, xa] * (1 - ax) + img[ya, xb] * ax
        bottom = img[yb, xa] * (1 - ax) + img[yb, xb] * ax
        return top * (1 - ay) + bottom * ay


@dataclass(frozen=True, eq=False)
class GridTexture:
    """A piecewise-constant albedo on axis-aligned cells in uv (scene units): exact edges at any distance, for
    prints made of rectangles (a calibration target's squares and markers).

    Attributes:
        xs: (nx + 1,) ascending cell boundaries along u; ys: (ny + 1,) along v.
        cells: (ny, nx) palette indices of the cells (row j between ys[j] and ys[j + 1]).
        colors: the palette, linear RGB.
        outside: the palette index beyond the boundaries.
    """

    xs: np.ndarray
    ys: np.ndarray
    cells: np.ndarray
    colors: tuple[tuple[float, float, float], ...]
    outside: int = 0

    def __post_init__(self):
        xs, ys = np.asarray(self.xs, np.float64), np.asarray(self.ys, np.float64)
        cells = np.asarray(self.cells, np.int64)
        if xs.ndim != 1 or ys.ndim != 1 or cells.shape != (len(ys) - 1, len(xs) - 1) or \
                np.any(np.diff(xs) <= 0) or np.any(np.diff(ys) <= 0):
            raise ValueError("grid texture: expected ascending boundaries xs (nx + 1), ys (ny + 1) and cells (ny, nx)")
        if cells.size and not (0 <= cells.min() and cells.max() < len(self.colors)) or \
                not 0 <= self.outside < len(self.colors):
            raise ValueError(f"grid texture: palette indices must be 0 to {len(self.colors) - 1}")
        # The table with a border of `outside` cells: index 0 and n + 1 along each axis lie beyond the grid.
        table = np.full((cells.shape[0] + 2, cells.shape[1] + 2), self.outside, np.int64)
        table[1:-1, 1:-1] = cells
        object.__setattr__(self, "xs", xs)
        object.__setattr__(self, "ys", ys)
        object.__setattr__(self, "cells", cells)
        object.__setattr__(self, "_table", torch.as_tensor(table.ravel()))

    @property
    def palette(self) -> tuple[tuple[float, float, float], ...]:
        """The colours `palette_index` picks from."""
        return self.colors

    def palette_index(self, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """(N,) long palette index of the points with texture coordinates u, v ((N,) each)."""
        xs = torch.as_tensor(self.xs, dtype=u.dtype, device=u.device)
        ys = torch.as_tensor(self.ys, dtype=v.dtype, device=v.device)
        i = torch.searchsorted(xs, u.contiguous(), right=True)  # 0: before xs[0]; nx + 1: at or after xs[-1]
        j = torch.searchsorted(ys, v.contiguous(), right=True)
        return self._table.to(u.device)[j * (len(self.xs) + 1) + i]

    def evaluate(self, uv: torch.Tensor) -> torch.Tensor:
        """(N, 2) uv -> (N, 3) linear RGB albedo."""
        cols = torch.tensor(self.colors, dtype=uv.dtype, device=uv.device)
        return cols[self.palette_index(uv[..., 0], uv[..., 1])]

    def raster(self, texel: float, max_side: int = 8192) -> tuple[np.ndarray, tuple[float, float], tuple[float, float]]:
        """The texture sampled at texel centres over its grid (for renderers without it: Mitsuba's bitmap):
        ((H, W, 3) float32 linear RGB, origin (u0, v0), size (su, sv)), texels of `texel` scene units or
        coarser so that neither side exceeds `max_side`."""
        u0, u1, v0, v1 = self.xs[0], self.xs[-1], self.ys[0], self.ys[-1]
        t = max(texel, (u1 - u0) / max_side, (v1 - v0) / max_side)
        W, H = max(1, int(math.ceil((u1 - u0) / t))), max(1, int(math.ceil((v1 - v0) / t)))
        u = torch.as_tensor(u0 + (np.arange(W) + 0.5) * (u1 - u0) / W)
        v = torch.as_tensor(v0 + (np.arange(H) + 0.5) * (v1 - v0) / H)
        V, U = torch.meshgrid(v, u, indexing="ij")
        idx = self.palette_index(U.reshape(-1), V.reshape(-1)).numpy()
        return (np.asarray(self.colors, np.float32)[idx].reshape(H, W, 3), (float(u0), float(v0)),
                (float(u1 - u0), float(v1 - v0)))


@dataclass(frozen=True)
class Material:
    """Surface appearance. All weights are dimensionless; colours are linear RGB albedos.

    Attributes:
        color: albedo [0.8, 0.8, 0.8]; also tints transmitted light.
        diffuse: Lambertian weight [1].
        specular: Phong highlight weight [0], `shininess` its exponent [32].
        reflect: mirror reflection weight [0].
        transmit: transparency weight [0]; refracted with index `ior` [1].
        texture: optional CheckerTexture or ImageTexture replacing `color`.
    """

    color: tuple[float, float, float] = (0.8, 0.8, 0.8)
    diffuse: float = 1.0
    specular: float = 0.0
    shininess: float = 32.0
    reflect: float = 0.0
    transmit: float = 0.0
    ior: float = 1.0
    texture: CheckerTexture | ImageTexture | GridTexture | None = None


class MaterialTable:
    """Per-object material properties stacked into tensors so shading is one gather by object id."""

    def __init__(self, materials: list[Material], device, dtype):
        def col(name):
            return torch.tensor([getattr(m, name) for m in materials], dtype=dtype, device=device)

        self.color = torch.tensor([m.color for m in materials], dtype=dtype, device=device).reshape(-1, 3)
        self.diffuse, self.specular, self.shininess = col("diffuse"), col("specular"), col("shininess")
        self.reflect, self.transmit, self.ior = col("reflect"), col("transmit"), col("ior")
        self.textured = [i for i, m in enumerate(materials) if m.texture is not None]
        self.textures = {i: materials[i].texture for i in self.textured}
        # Shadow rays pass a transparent object attenuated by transmit · colour (a lighter, tinted shadow).
        self.shadow_transmittance = self.transmit[:, None] * self.color
