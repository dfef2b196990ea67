"""Inverted-perspective camera (paper 000, Osa et al. 2005, section 2, eq. 1–5).

| key | unit | default | meaning |
|---|---|---|---|
| `alpha` | — | required | α: 0 perspective, (0, 1) weaker perspective, 1 parallel, > 1 inverted (far is larger) |
| `pseudo_screen_distance` | scene | required | p3, distance of the pseudo-screen Ξ from the viewpoint (> 0) |
| `screen_distance` | scene | 1 | q3, distance of the screen Π from the viewpoint |
| `screen_size` | scene | — | [width, height] of the screen; or give `fov_deg` (horizontal) |

In the camera frame (the paper's Σ: viewpoint s at the origin, screen Π at z = q3, pseudo-screen Ξ at z = p3)
the pixel's screen point q = (q1, q2, q3) gives
    (1) p = (q1/q3, q2/q3, 1) · p3           where the line s→q meets the pseudo-screen,
    (2) v = α · diag(1, 1, 0) · p            the ray origin, on the plane z = 0,
    (3) w = p − v                            the ray direction (normalised here).
A point a = (a1, a2, a3) is imaged at
    (4)(5) q_k = a_k q3 / (α (p3 − a3) + a3),  k = 1, 2.

Special cases: α = 0 is the pinhole at the viewpoint with the same screen (identical rays); α = 1 is the
orthographic camera with the view window `screen_size`·p3/q3 (identical rays). Points on the pseudo-screen
(a3 = p3) are imaged at a_k q3/p3 whatever α is.

Singularity: for α ≠ 1 every ray passes through the apex (0, 0, α p3/(α − 1)). For α > 1 the apex lies beyond
the pseudo-screen (a hypercentric view); points at the apex depth a3 = α p3/(α − 1) have no image (the
denominator of (4) vanishes) and `project` returns +inf for them. Points beyond the apex are imaged
point-reflected through the image centre, as the formula says.
"""
from __future__ import annotations

import torch

from renderer.core.params import Param, SceneError
from renderer.core.rays import Rays, normalize
from renderer.core.transforms import CameraTransform
from .base import Camera, Screen, screen_from_config
from .registry import SCREEN_PARAMS, register_camera

PARAMS = SCREEN_PARAMS + [
    Param("alpha", "float", doc="α, the inverted-perspective parameter (0 = perspective, 1 = parallel)"),
    Param("pseudo_screen_distance", "float", doc="p3, pseudo-screen distance from the viewpoint, scene units"),
]


def inverted_rays(p: torch.Tensor, alpha: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays of eq. (2), (3) through pseudo-screen points, in the viewpoint's frame Σ.

    Args:
        p: (..., 3) points on the pseudo-screen z = p3, frame Σ (viewpoint at the origin), scene units.
        alpha: α.
    Returns:
        origin v = α·diag(1, 1, 0)·p (..., 3) and unit direction along w = p − v (..., 3), frame Σ.
    """
    keep_xy = torch.tensor([1.0, 1.0, 0.0], dtype=p.dtype, device=p.device)
    v = alpha * keep_xy * p
    return v, normalize(p - v)


def inverted_projection(a: torch.Tensor, alpha: float, p3: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Eq. (4), (5) with q3 = p3: where the ray that sees a point meets the pseudo-screen.

    Args:
        a: (..., 3) points, frame Σ (viewpoint at the origin, pseudo-screen at z = p3), scene units.
    Returns:
        x (..., 2): (a1, a2) · p3 / (α (p3 − a3) + a3), the (x, y) of the pseudo-screen point; 0 where
        `has_image` is False, so that no NaN or inf flows on.
        has_image (...,) bool: False at the singular depth, where the denominator is zero.
    """
    a3 = a[..., 2]
    den = alpha * (p3 - a3) + a3
    has_image = den != 0
    safe = torch.where(has_image, den, torch.ones_like(den))
    x = a[..., :2] * (p3 / safe)[..., None]
    return torch.where(has_image[..., None], x, torch.zeros_like(x)), has_image


@register_camera("inverted_perspective", PARAMS)
class InvertedPerspectiveCamera(Camera):
    """Rays from the plane z = 0 through the pseudo-screen, eq. (1)–(3).

    Attributes:
        alpha: α (dimensionless).
        pseudo_screen_distance: p3, scene units.
    """

    def __init__(self, transform: CameraTransform, screen: Screen, alpha: float, pseudo_screen_distance: float):
        super().__init__(transform, screen)
        if not pseudo_screen_distance > 0:
            raise ValueError(f"pseudo_screen_distance: expected a positive distance, got {pseudo_screen_distance}")
        self.alpha = float(alpha)
        self.pseudo_screen_distance = float(pseudo_screen_distance)

    @classmethod
    def from_config(cls, path, cfg, transform, width, height):
        p3 = cfg["pseudo_screen_distance"]
        if not p3 > 0:
            raise SceneError(f"{path}.pseudo_screen_distance: expected a positive distance, got {p3}")
        return cls(transform, screen_from_config(path, cfg, width, height), cfg["alpha"], p3)

    def rays_in_camera(self, uv_px: torch.Tensor, lens_uv: torch.Tensor) -> Rays:
        q = self.screen.to_plane(uv_px)
        p3, q3 = self.pseudo_screen_distance, self.screen.distance
        p = torch.stack([q[..., 0] * (p3 / q3), q[..., 1] * (p3 / q3), torch.full_like(q[..., 0], p3)], -1)  # (1)
        origin, direction = inverted_rays(p, self.alpha)  # (2), (3)
        valid = torch.ones(q.shape[:-1], dtype=torch.bool, device=q.device)
        return Rays(origin, direction, valid, torch.ones_like(q[..., 0]))

    def project(self, p_world: torch.Tensor) -> torch.Tensor:
        """(..., 3) world points -> (..., 2) pixels by eq. (4), (5); +inf at the singular depth."""
        a = self.transform.points_to_camera(p_world)
        x, has_image = inverted_projection(a, self.alpha, self.pseudo_screen_distance)
        uv_px = self.screen.to_pixels(x * (self.screen.distance / self.pseudo_screen_distance))
        return torch.where(has_image[..., None], uv_px, torch.full_like(uv_px, float("inf")))
