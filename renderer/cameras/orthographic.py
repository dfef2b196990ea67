"""Orthographic (parallel) camera: every ray runs along the camera +z axis from its screen point.

| key | unit | default | meaning |
|---|---|---|---|
| `screen_size` | scene | required | [width, height] of the view window (the area of the z = 0 plane that is seen) |
| `screen_distance` | scene | 1 | accepted for symmetry with the other cameras; has no effect |

Pixel (x, y) sees the ray with origin ((x − cx)·Sx/W, (y − cy)·Sy/H, 0) and direction (0, 0, 1) in the camera
frame, so only points in front of the camera plane z = 0 are seen. This is the inverted-perspective camera
at α = 1 (paper 000, eq. 8, 9) with the window `screen_size`·p3/q3.
"""
from __future__ import annotations

import torch

from renderer.core.params import Param
from renderer.core.rays import Rays
from .base import Camera
from .registry import register_camera

PARAMS = [
    Param("screen_size", "vec2", doc="[width, height] of the view window, scene units"),
    Param("screen_distance", "float", 1.0, "accepted for symmetry with the other cameras; no effect"),
]


@register_camera("orthographic", PARAMS)
class OrthographicCamera(Camera):
    """Parallel projection along the camera z axis; the screen's size is the view window."""

    def rays_in_camera(self, uv_px: torch.Tensor, lens_uv: torch.Tensor) -> Rays:
        q_cam = self.screen.to_plane(uv_px)
        zero, one = torch.zeros_like(q_cam[..., 0]), torch.ones_like(q_cam[..., 0])
        origin = torch.stack([q_cam[..., 0], q_cam[..., 1], zero], dim=-1)
        direction = torch.stack([zero, zero, one], dim=-1)
        valid = torch.ones(q_cam.shape[:-1], dtype=torch.bool, device=q_cam.device)
        return Rays(origin, direction, valid, one)

    def project(self, p_world: torch.Tensor) -> torch.Tensor:
        """(..., 3) world points -> (..., 2) pixels: drop the camera-frame depth.

        Points behind the camera plane (z ≤ 0) are mapped too, although no ray reaches them.
        """
        p_cam = self.transform.points_to_camera(p_world)
        return self.screen.to_pixels(p_cam[..., :2])

