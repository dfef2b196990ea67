"""Pinhole (perspective) camera: every ray starts at the camera centre and passes through its pixel.

| key | unit | default | meaning |
|---|---|---|---|
| `screen_distance` | scene | 1 | q3, distance of the screen from the viewpoint |
| `screen_size` | scene | — | [width, height] of the screen; or give `fov_deg` (horizontal) |
"""
from __future__ import annotations

import torch

from ..rays import Rays, normalize
from . import SCREEN_PARAMS, register_camera, screen_from_config
from .base import Camera


@register_camera("pinhole", SCREEN_PARAMS)
class PinholeCamera(Camera):
    """Perspective projection: ray from the origin of the camera frame through the screen point q."""

    @classmethod
    def from_config(cls, path, cfg, transform, width, height):
        return cls(transform, screen_from_config(path, cfg, width, height))

    def rays_in_camera(self, uv_px: torch.Tensor, lens_uv: torch.Tensor) -> Rays:
        q_cam = self.screen.to_plane(uv_px)
        origin = torch.zeros_like(q_cam)
        valid = torch.ones(q_cam.shape[:-1], dtype=torch.bool, device=q_cam.device)
        return Rays(origin, normalize(q_cam), valid, torch.ones_like(q_cam[..., 0]))

    def project(self, p_world: torch.Tensor) -> torch.Tensor:
        p_cam = self.transform.points_to_camera(p_world)
        q = p_cam[..., :2] * (self.screen.distance / p_cam[..., 2:3])
        return self.screen.to_pixels(q)
