"""The render loop: samples -> camera rays -> trace -> pixel estimates, in chunks of rays."""
from __future__ import annotations

from dataclasses import dataclass

import torch

from .integrator import trace
from .progress import Progress
from .sampling import Sampler
from .scene import Scene


@dataclass
class RenderResult:
    """image: (H, W, 3) linear RGB; coverage: (H, W) fraction of a pixel's samples that had a valid ray."""

    image: torch.Tensor
    coverage: torch.Tensor


def render_passes(scene: Scene):
    """(camera, first-hit object flags or None) from the lowest to the highest priority.

    Without layers this is the scene camera seeing everything. With layers, objects in no layer form a
    default perspective layer drawn first; each layer then overwrites the pixels its first ray hits.
    """
    if not scene.layers:
        return [(scene.camera, None)]
    assigned = set()
    passes = []
    for layer in sorted(scene.layers, key=lambda l: l.priority):
        assigned.update(layer.object_ids)
        flags = [i in layer.object_ids for i in range(len(scene.objects))]
        passes.append((layer.camera, flags))
    rest = [i not in assigned for i in range(len(scene.objects))]
    if any(rest):
        passes.insert(0, (scene.camera, rest))
    return passes


def render(scene: Scene, spp: int | None = None, sampler: str | None = None, *, device="cpu",
           dtype=torch.float32, seed: int = 0, chunk_rays: int = 1 << 18, progress: bool = False,
           max_depth: int | None = None) -> RenderResult:
    """Render the scene's camera image.

    Args:
        spp: samples per pixel [scene.image.spp]; sampler: `independent`, `stratified`, `sobol` or
            `center` [scene.image.sampler].
        device, dtype: where and in what precision to trace (float32 for speed, float64 for checks).
        chunk_rays: camera samples traced at once; bounds memory (about 1 KB per ray at depth 5).
    Returns:
        RenderResult with the (H, W, 3) image and the (H, W) coverage; pixels without any valid ray keep
        the background colour.
    """
    cam = scene.camera
    W, H = cam.width, cam.height
    spp = scene.image.spp if spp is None else spp
    smp = Sampler(sampler or scene.image.sampler, spp, seed)
    passes = render_passes(scene)
    total = W * H * spp
    acc = torch.zeros(W * H, 3, dtype=torch.float64, device=device)
    wsum = torch.zeros(W * H, dtype=torch.float64, device=device)
    count = torch.zeros(W * H, dtype=torch.float64, device=device)
    background = torch.tensor(scene.image.background, dtype=dtype, device=device)
    bar = Progress(total, "render", enabled=progress)
    for start in range(0, total, chunk_rays):
        idx = torch.arange(start, min(start + chunk_rays, total))
        pixel, sample = idx // spp, idx % spp
        u = smp.samples(pixel, sample).to(device=device, dtype=dtype)
        pixel = pixel.to(device)
        uv_px = torch.stack([(pixel % W).to(dtype) + u[:, 0] - 0.5, (pixel // W).to(dtype) + u[:, 1] - 0.5], -1)
        color = background.expand(idx.shape[0], 3)
        weight = None
        for camera, flags in passes:
            rays = camera.generate_rays(uv_px, u[:, 2:])
            rad, found = trace(scene, rays.origin, rays.direction, flags, max_depth)
            take = rays.valid if flags is None else rays.valid & found
            color = torch.where(take[:, None], rad, color)
            if weight is None:
                weight, valid = rays.weight, rays.valid
        w = torch.where(valid, weight, torch.zeros_like(weight)).to(torch.float64)
        acc.index_add_(0, pixel, color.to(torch.float64) * w[:, None])
        wsum.index_add_(0, pixel, w)
        count.index_add_(0, pixel, valid.to(torch.float64))
        bar.update(idx.shape[0])
    covered = wsum > 0
    image = torch.where(covered[:, None], acc / wsum.clamp_min(1e-300)[:, None], background.to(torch.float64))
    return RenderResult(image.reshape(H, W, 3).to(dtype), (count / spp).reshape(H, W).to(dtype))
