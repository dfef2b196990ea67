"""Materials (Whitted-style: diffuse, Phong specular, mirror, refraction) and textures.

Shading model for a surface point with albedo c (the `color` or the texture):
    L = (1 − reflect − transmit) · [diffuse · c/π · Σ_lights E_l  +  specular · Phong]  + ambient · c
        + reflect · L(reflected ray)  +  transmit · c · L(refracted ray)
where E_l = I_l · max(0, n·l) / r² · (shadow transmittance) for a point light of intensity I_l.
Total internal reflection sends the transmitted share along the reflected ray.
"""
from __future__ import annotations

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
    texture: CheckerTexture | ImageTexture | None = None


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
