"""Pinhole (perspective) camera: every ray starts at the camera centre and passes through its pixel.

| key | unit | default | meaning |
|---|---|---|---|
| `screen_distance` | scene | 1 | q3, distance of the screen from the viewpoint |
| `screen_size` | scene | — | [width, height] of the screen; or give `fov_deg` (horizontal) |
"""
from __future__ import annotations

import torch

from ..rays import Rays, normalize
from . import SCREEN_PARAMS, register_camera
from .base import Camera


@register_camera("pinhole", SCREEN_PARAMS)
class PinholeCamera(Camera):
    """Perspective projection: ray from the origin of the camera frame through the screen point q."""

    def rays_in_camera(self, uv_px: torch.Tensor, lens_uv: torch.Tensor) -> Rays:
        q_cam = self.screen.to_plane(uv_px)
        origin = torch.zeros_like(q_cam)
        valid = torch.ones(q_cam.shape[:-1], dtype=torch.bool, device=q_cam.device)
        return Rays(origin, normalize(q_cam), valid, torch.ones_like(q_cam[..., 0]))

    project = Camera.project_central
