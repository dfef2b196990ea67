"""Pinhole (perspective) camera: every ray starts at the camera centre and passes through its pixel.

| key | unit | default | meaning |
|---|---|---|---|
| `screen_distance` | scene | 1 | q3, distance of the screen from the viewpoint |
| `screen_size` | scene | — | [width, height] of the screen; or give `fov_deg` (horizontal) |
"""
from __future__ import annotations

import torch

from renderer.core.rays import Rays, unit_vectors_from_rows, vectors_from_rows
from .base import Camera
from .registry import SCREEN_PARAMS, register_camera


@register_camera("pinhole", SCREEN_PARAMS)
class PinholeCamera(Camera):
    """Perspective projection: ray from the origin of the camera frame through the screen point q."""

    def rays_in_camera(self, uv_px: torch.Tensor, lens_uv: torch.Tensor) -> Rays:
        # Per component, as the thin lens (whose d = 0 limit is bit for bit this).
        x, y, z = self.screen.plane_rows(uv_px)
        zero = torch.zeros_like(x)
        valid = torch.ones(x.shape, dtype=torch.bool, device=x.device)
        return Rays(vectors_from_rows(zero, zero, zero), unit_vectors_from_rows(x, y, z), valid, torch.ones_like(x))

    project = Camera.project_central
