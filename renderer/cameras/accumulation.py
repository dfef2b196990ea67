"""Accumulation-buffer depth of field (Haeberli & Akeley 1990; Barsky & Pasztor 2004 for a tilted focus).

The comparison method of the tilt-lens paper (Fig. 1). One image per lens point S, each a pinhole at S
whose viewing frustum is built on the plane of focus: every pixel's ray aims from S at the pixel's
in-focus point P_f (the chief ray through the lens centre meets the plane of focus there), and the images
are averaged. P_f is a projective function of the pixel, P_f = (U c, D) in homogeneous coordinates with
c = (x_s, y_s, w) and D = w − y_s tan θF — the 4×3 frustum matrix of the method. A rasteriser can only
use it where D > 0: pixels whose focus point is at infinity (D = 0) or behind the lens (D < 0) have no
frustum, so this camera returns valid = False for them and `RenderResult.coverage` reports them as 0.
Where D > 0 its rays equal those of the distributed-ray-tracing `thin_lens` camera.

Keys: those of `thin_lens` (see `renderer.cameras.thin_lens`). `render_accumulation` renders the method
as the original does (one shared lens point per pass); with `render` the lens point varies per sample.
"""
from __future__ import annotations

import copy

import torch

from renderer.core.rays import Rays, normalize
from .registry import register_camera
from .thin_lens import THIN_LENS_PARAMS, ThinLensCamera


@register_camera("thin_lens_accumulation", THIN_LENS_PARAMS)
class AccumulationBufferCamera(ThinLensCamera):
    """Pinhole at the lens point S with a frustum on the plane of focus; invalid where P_f is not in front."""

    def focus_points(self, uv_px: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(..., 3) homogeneous-divided focus points P_f and (...,) validity D > 0 for pixels (..., 2).

        Invalid pixels get the chief direction scaled to depth U instead (finite, never used).
        """
        c = self.screen.to_plane(uv_px)
        wh = self.focus_weight(c)  # homogeneous weight D / U of P_f = c / wh
        valid = wh > 0
        p_f = c / torch.where(valid, wh, torch.ones_like(wh))[..., None]
        return p_f, valid

    def frustum_corners(self) -> tuple[torch.Tensor, bool]:
        """(4, 3) focus points of the image corners (top-left, top-right, bottom-right, bottom-left) and
        whether all four exist, i.e. whether the original method can set up its frustum at all."""
        W, H = self.width, self.height
        uv = torch.tensor([[-0.5, -0.5], [W - 0.5, -0.5], [W - 0.5, H - 0.5], [-0.5, H - 0.5]],
                          dtype=torch.float64)
        p_f, valid = self.focus_points(uv)
        return p_f, bool(valid.all())

    def rays_in_camera(self, uv_px: torch.Tensor, lens_uv: torch.Tensor) -> Rays:
        p_f, valid = self.focus_points(uv_px)
        s = self.lens_points(lens_uv.to(p_f))
        direction = torch.where(valid[..., None], p_f - s, p_f)
        return Rays(s, normalize(direction), valid, torch.ones_like(p_f[..., 0]))


class _FixedLensPoint:
    """A camera wrapper that gives every pixel the same lens sample (one accumulation-buffer pass)."""

    def __init__(self, camera: ThinLensCamera, lens_uv: torch.Tensor):
        self.camera, self.lens_uv = camera, lens_uv
        self.screen, self.transform = camera.screen, camera.transform
        self.width, self.height = camera.width, camera.height

    def generate_rays(self, uv_px, lens_uv=None):
        return self.camera.generate_rays(uv_px, self.lens_uv.to(uv_px).expand_as(uv_px))


def render_accumulation(scene, lens_uv: torch.Tensor, spp: int = 1, **render_kwargs):
    """Render with the accumulation-buffer method: one pinhole pass per lens point, averaged.

    Args:
        scene: a Scene whose camera is an `AccumulationBufferCamera` (or a `ThinLensCamera`, which then
            renders every pixel).
        lens_uv: (n, 2) lens samples in [0, 1)², one per pass, shared by all pixels (the caller owns them).
        spp: samples per pixel within a pass (pixel antialiasing); further keyword arguments go to `render`.
    Returns:
        RenderResult: the mean image and the mean coverage over the passes.
    """
    from renderer.tracing.render import RenderResult, render

    if lens_uv.ndim != 2 or lens_uv.shape[-1] != 2 or lens_uv.shape[0] < 1:
        raise ValueError(f"lens_uv: expected shape (n, 2) with n >= 1, got {tuple(lens_uv.shape)}")
    image = coverage = None
    for uv in lens_uv:
        one = copy.copy(scene)  # shallow: shares the objects and any acceleration structures
        one.camera = _FixedLensPoint(scene.camera, uv)
        res = render(one, spp=spp, **render_kwargs)
        image = res.image if image is None else image + res.image
        coverage = res.coverage if coverage is None else coverage + res.coverage
    n = lens_uv.shape[0]
    return RenderResult(image / n, coverage / n)
