"""The render loop: samples -> camera rays -> trace -> pixel estimates, in chunks of whole pixels.

Pixels are visited in screen tiles (`TILE` × `TILE`, row by row inside a tile) with all samples of a pixel
next to each other, so consecutive rays are neighbours on the screen: the scene's packet culling then sees
coherent packets. Every pixel lies in exactly one chunk, so its estimate is a sum over its own samples and
the image does not depend on the chunk size.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch

from .integrator import trace
from .progress import Progress
from .sampling import Sampler
from .scene import Scene, compiled_call

# Side of the square screen tiles, pixels.
TILE = 8


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


def tile_order(width: int, height: int, tile: int = TILE) -> torch.Tensor:
    """(W·H,) long pixel indices (row · W + column) in tile order: tiles of tile × tile pixels left to right,
    top to bottom, and the pixels of a tile row by row (edge tiles are cut to the image)."""
    y, x = torch.arange(height)[:, None], torch.arange(width)[None, :]
    tiles_x = -(-width // tile)
    key = ((y // tile) * tiles_x + x // tile) * tile * tile + (y % tile) * tile + x % tile
    return torch.argsort(key.reshape(-1))


def _camera_samples(sampler: Sampler, pixel: torch.Tensor, width: int, dtype: torch.dtype):
    """Pixel positions (n·spp, 2) (x = column, y = row) and lens samples (n·spp, 2) in [0, 1)² for all
    samples of the pixels `pixel` (n,), the samples of a pixel consecutive."""
    jx, jy, lu, lv = sampler.pixel_columns(pixel)
    x = (pixel % width)[:, None].to(torch.float64) - 0.5 + jx
    y = (pixel // width)[:, None].to(torch.float64) - 0.5 + jy
    return torch.stack([x, y], -1).to(dtype).view(-1, 2), torch.stack([lu, lv], -1).to(dtype).view(-1, 2)


def _pixel_estimates(color, weight, valid, background, spp: int):
    """Weighted mean of each pixel's spp consecutive samples (n, 3) (background where no sample has
    weight), and the fraction of valid samples (n,)."""
    w = torch.where(valid, weight, torch.zeros_like(weight))
    acc = (color * w[:, None]).view(-1, spp, 3).sum(1)
    wsum = w.view(-1, spp).sum(1)
    estimate = torch.where((wsum > 0)[:, None], acc / wsum.clamp_min(1e-30)[:, None], background)
    return estimate, valid.view(-1, spp).sum(1).to(color.dtype) / spp


def render(scene: Scene, spp: int | None = None, sampler: str | None = None, *, device="cpu",
           dtype=torch.float32, seed: int = 0, chunk_rays: int = 1 << 16, progress: bool = False,
           max_depth: int | None = None, culling: bool | None = None, compile: bool | None = None) -> RenderResult:
    """Render the scene's camera image.

    Args:
        spp: samples per pixel [scene.image.spp]; sampler: `independent`, `stratified`, `sobol` or
            `center` [scene.image.sampler].
        device, dtype: where and in what precision to trace (float32 for speed, float64 for checks).
        chunk_rays: camera samples traced at once (rounded to whole pixels); bounds memory (about 1 KB per
            ray at depth 5). The image does not depend on it.
        culling, compile: override scene.options (see `renderer.scene.TraceOptions`); speed only.
    Returns:
        RenderResult with the (H, W, 3) image and the (H, W) coverage; pixels without any valid ray keep
        the background colour.
    """
    cam = scene.camera
    W, H = cam.width, cam.height
    spp = scene.image.spp if spp is None else spp
    options = scene.options
    if culling is not None:
        options = replace(options, culling=culling)
    if compile is not None:
        options = replace(options, compile=compile)
    smp = Sampler(sampler or scene.image.sampler, spp, seed)
    passes = render_passes(scene)
    image = torch.empty(W * H, 3, dtype=dtype, device=device)
    coverage = torch.empty(W * H, dtype=dtype, device=device)
    background = torch.tensor(scene.image.background, dtype=dtype, device=device)
    order = tile_order(W, H)
    # Whole pixels per chunk, and whole culling packets: the last chunk repeats its last pixel to fill up.
    packet = max(1, options.packet_size)
    step = packet // math.gcd(packet, spp)
    pixels_per_chunk = max(step, chunk_rays // spp // step * step)
    bar = Progress(W * H * spp, "render", enabled=progress)
    for start in range(0, W * H, pixels_per_chunk):
        pixel = order[start:start + pixels_per_chunk]
        n = pixel.shape[0]
        if n % step:
            pixel = torch.cat([pixel, pixel[-1:].expand(step - n % step)])
        uv_px, lens_uv = _camera_samples(smp, pixel, W, dtype)
        uv_px, lens_uv = uv_px.to(device), lens_uv.to(device)
        color = weight = valid = None
        for camera, flags in passes:
            rays = compiled_call(options.compile, type(camera).generate_rays, camera, uv_px, lens_uv)
            rad, found = trace(scene, rays.origin, rays.direction, flags, max_depth, options=options)
            take = rays.valid if flags is None else rays.valid & found
            if color is None and bool(take.all()):
                color = rad
            else:
                base = background.expand_as(rad) if color is None else color
                color = torch.where(take[:, None], rad, base)
            if weight is None:
                weight, valid = rays.weight, rays.valid
        estimate, covered = compiled_call(options.compile, _pixel_estimates, color, weight, valid, background, spp)
        pixel = pixel[:n].to(device)
        image.index_copy_(0, pixel, estimate[:n])
        coverage.index_copy_(0, pixel, covered[:n])
        bar.update(n * spp)
    return RenderResult(image.reshape(H, W, 3), coverage.reshape(H, W))
