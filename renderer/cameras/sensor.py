"""What a camera's sensor records for the linear radiance the renderer computes.

One model for every simulated capture (`tiltfit.experiments.synth`, `tiltfit reproduce`, the stability studies) and for
the photometric fit, so a capture and its re-rendering age the same way:

    recorded = Q( gain · falloff(x, y) · radiance + black + noise )

- falloff(x, y) = 1 − v ρ², ρ the distance of the pixel from the centre (the image centre unless given)
  over the image's half-diagonal, so 1 − v at the corners: a lens's vignetting to second order.
- noise: Gaussian with variance read_noise² + max(signal, 0) / full_well (shot noise of `full_well`
  photo-electrons at linear value 1, Poisson taken as Gaussian); none where both are 0.
- Q: none (float output), or 8-bit sRGB (round(255 · sRGB(clip(v, 0, 1)))), or 8-bit linear.

The falloff works on numpy arrays and on torch tensors alike (the photometric fit differentiates through it).
`SensorResponse.expose` also takes a torch tensor, and then works where the tensor lives: a 20-Mpx render made
on a GPU is exposed there (noise from a `torch.Generator`) instead of being copied back for single-threaded
numpy (on one CPU thread the tensor path is the slower, so CPU renders keep numpy; docs/speed.md). sRGB's
transfer functions are `camio.files.linear_to_srgb` / `srgb_to_linear`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from camio.files import encode_srgb8, linear_to_srgb, srgb_to_linear  # noqa: F401 - encode_srgb8 re-exported

from .projection import image_centre_px

ENCODINGS = ("float", "srgb8", "linear8")


def radial_falloff(x, y, width: int, height: int, vignetting, centre=None):
    """1 − v ρ² at pixel positions (x, y) (numpy arrays or torch tensors, broadcast together).

    Args:
        x, y: pixel column and row (pixel centres at integers).
        width, height: image size, px; ρ = 1 at the corners of this image.
        vignetting: v (a float or a tensor, so it can be fitted).
        centre: (cx, cy) px of the fall-off [the image centre ((W − 1)/2, (H − 1)/2)].
    """
    hx, hy = image_centre_px(width, height)  # the centre, and the half-diagonal's components
    cx, cy = (hx, hy) if centre is None else centre
    rho2 = ((x - cx) ** 2 + (y - cy) ** 2) / (hx**2 + hy**2)
    return 1.0 - vignetting * rho2


def _encode_srgb8_torch(linear: torch.Tensor) -> torch.Tensor:
    """`encode_srgb8` for a tensor, on its device: uint8 tensor."""
    s = linear_to_srgb(linear.to(torch.float64).clamp(0.0, 1.0))
    return torch.round(s * 255.0).clamp(0, 255).to(torch.uint8)


def decode_srgb8(levels) -> np.ndarray:
    """uint8 (or 0–255 float) sRGB levels back to linear float64 in [0, 1]."""
    return srgb_to_linear(np.clip(np.asarray(levels, dtype=np.float64) / 255.0, 0.0, 1.0))


@dataclass(frozen=True)
class SensorResponse:
    """The sensor's response (see the module docstring for the model).

    Attributes:
        gain: recorded linear value for radiance 1 at the centre [1].
        black: black level added to every pixel, linear [0].
        vignetting: v of the fall-off 1 − v ρ² [0].
        read_noise: σ of the signal-independent noise, linear [0].
        full_well: photo-electrons at linear value 1 (shot-noise variance = signal / full_well); None: no
            shot noise.
        encoding: `float` (no quantisation), `srgb8` or `linear8` (uint8 output).
    """

    gain: float = 1.0
    black: float = 0.0
    vignetting: float = 0.0
    read_noise: float = 0.0
    full_well: float | None = None
    encoding: str = "float"

    def __post_init__(self):
        if self.encoding not in ENCODINGS:
            raise ValueError(f"encoding: expected one of {', '.join(ENCODINGS)}, got {self.encoding!r}")
        if self.full_well is not None and not self.full_well > 0:
            raise ValueError(f"full_well: expected a positive number of electrons, got {self.full_well}")
        if not self.read_noise >= 0:
            raise ValueError(f"read_noise: expected σ >= 0, got {self.read_noise}")

    def signal(self, radiance, centre=None) -> np.ndarray:
        """The noise-free recorded linear image: gain · falloff · radiance + black, for an (H, W) or
        (H, W, C) image; float64."""
        img = np.asarray(radiance, dtype=np.float64)
        h, w = img.shape[:2]
        if self.vignetting:
            fall = radial_falloff(np.arange(w, dtype=np.float64)[None, :], np.arange(h, dtype=np.float64)[:, None],
                                  w, h, self.vignetting, centre)
            img = img * (fall[..., None] if img.ndim == 3 else fall)
        if self.gain != 1.0:
            img = self.gain * img
        if self.black:
            img = img + self.black
        return img

    def expose(self, radiance, rng: np.random.Generator | None = None, centre=None) -> np.ndarray:
        """What the sensor writes for a linear (H, W[, C]) image: float64, or uint8 for the 8-bit encodings.
        `rng` draws the noise (needed where there is noise)."""
        if isinstance(radiance, torch.Tensor):
            return self._expose_tensor(radiance, rng, centre)
        img = self.signal(radiance, centre)
        if self.read_noise or self.full_well is not None:
            if rng is None:
                raise ValueError("expose: a noisy sensor needs an rng")
            if self.full_well is None:
                sd = self.read_noise
            else:
                sd = np.sqrt(np.clip(img, 0.0, None) / self.full_well + self.read_noise**2)
            img = img + sd * rng.standard_normal(img.shape)
        if self.encoding == "srgb8":
            return encode_srgb8(img)
        if self.encoding == "linear8":
            return np.clip(np.round(np.clip(img, 0.0, 1.0) * 255.0), 0, 255).astype(np.uint8)
        return img

    def _expose_tensor(self, radiance: torch.Tensor, rng: torch.Generator | None, centre) -> np.ndarray:
        """`expose` on the tensor's device (float64 there), the result copied to a numpy array; the noise
        comes from `rng`, a torch.Generator on that device (another draw than numpy's for the same seed)."""
        img = radiance.to(torch.float64)
        h, w = img.shape[:2]
        if self.vignetting:
            x = torch.arange(w, dtype=torch.float64, device=img.device)[None, :]
            y = torch.arange(h, dtype=torch.float64, device=img.device)[:, None]
            fall = radial_falloff(x, y, w, h, self.vignetting, centre)
            img = img * (fall[..., None] if img.ndim == 3 else fall)
        img = self.gain * img + self.black
        if self.read_noise or self.full_well is not None:
            if not isinstance(rng, torch.Generator):
                raise ValueError("expose: a noisy sensor exposing a tensor needs a torch.Generator as rng")
            var = torch.full_like(img, self.read_noise**2)
            if self.full_well is not None:
                var = var + img.clamp(min=0.0) / self.full_well
            img = img + var.sqrt() * torch.randn(img.shape, generator=rng, dtype=img.dtype, device=img.device)
        if self.encoding == "srgb8":
            return _encode_srgb8_torch(img).cpu().numpy()
        if self.encoding == "linear8":
            return torch.round(img.clamp(0.0, 1.0) * 255.0).to(torch.uint8).cpu().numpy()
        return img.cpu().numpy()

    def decode(self, recorded) -> np.ndarray:
        """Recorded values back to linear float64 (the inverse of the encoding, not of gain or noise)."""
        if self.encoding == "srgb8":
            return decode_srgb8(recorded)
        if self.encoding == "linear8":
            return np.asarray(recorded, dtype=np.float64) / 255.0
        return np.asarray(recorded, dtype=np.float64)
