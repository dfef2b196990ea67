"""`renderer animate`: the camera moves along its view direction; one image per frame and a timing table.

    renderer animate SCENE.json --method beam|trace [--frames N] [--step D] -o DIR [--set key.path=value ...]

Frame k (from 0) puts the camera at position + k·D·view (view the unit view direction; `look_at` moves with
it, `up` is kept). `--frames` and `--step` default to the scene's `animation: {frames, step}`.
Writes DIR/frame_0000.png ... (8-bit sRGB) and DIR/frames.csv with the columns

| column | meaning |
|---|---|
| `frame` | frame number from 0 |
| `seconds` | wall time of the frame: segmentation + region rendering (beam) or ray tracing (trace) |
| `regions` | screen regions (beam; empty for trace) |
| `redetermined` | 1 when the viewpoint crossed a polygon plane, so visible polygons and mirroring order were
re-determined (always 1 for frame 0; empty for trace) |
| `segment_seconds` | the segmentation part of `seconds` (beam; empty for trace) |

`beam` is the improved beam tracer (`renderer.beam`, numpy and shapely on the CPU; `--device` applies to
`trace` only): pinhole camera, polyhedron/csg objects; it shades one
sample at each pixel centre. `trace` renders each frame with the ray tracer at the scene's `image.spp` and
`sampler` (the shipped beam scenes use 1 spp at the pixel centre, so both show the same image).
"""
from __future__ import annotations

import csv
import os
import sys
import time

import numpy as np

from .io import write_image
from .params import SceneError
from .scenefile import load_scene, parse_animation, read_scene_json

METHODS = ("beam", "trace")
COLUMNS = ("frame", "seconds", "regions", "redetermined", "segment_seconds")


def animation_defaults(path: str, overrides=()) -> dict:
    """The scene file's validated `animation` section after overrides ({} when it has none)."""
    from .scenefile import apply_override

    cfg = read_scene_json(path)
    try:
        for text in overrides:
            apply_override(cfg, text)
        return parse_animation(cfg)
    except SceneError as e:
        raise SceneError(f"{path}: {e}") from None


def animate(path: str, method: str, frames: int, step: float, out_dir: str, overrides=(), *, device="cpu",
            progress: bool = True) -> list[dict]:
    """Render the frames (see the module docstring) and write them and frames.csv into out_dir.

    Returns:
        One row per frame: {frame, seconds, regions, redetermined, segment_seconds} (None where empty).
    """
    if method not in METHODS:
        raise SceneError(f"--method: expected one of {', '.join(METHODS)}, got {method!r}")
    scene = load_scene(path, overrides)
    position = scene.camera.transform.position.numpy()
    view = scene.camera.transform.world_from_camera[:, 2].numpy()
    os.makedirs(out_dir, exist_ok=True)
    rows = []
    tracer = None
    if method == "beam":
        from .beam import BeamTracer, ScreenCamera

        try:
            tracer = BeamTracer(scene)
        except SceneError as e:
            raise SceneError(f"{path}: {e}") from None
        base = ScreenCamera.of(scene.camera)
    for k in range(frames):
        start = time.perf_counter()
        if tracer is not None:
            frame = tracer.frame(base.moved(k * step))
            image = tracer.render(frame)
            row = {"frame": k, "regions": len(frame.regions), "redetermined": int(frame.redetermined),
                   "segment_seconds": frame.seconds}
            seconds = time.perf_counter() - start + frame.polygon_seconds
        else:
            from .render import render

            p = position + k * step * view
            moved = [f"camera.position={list(map(float, p))}", f"camera.look_at={list(map(float, p + view))}"]
            frame_scene = load_scene(path, list(overrides) + moved)
            start = time.perf_counter()
            image = render(frame_scene, device=device).image.cpu().numpy()
            seconds = time.perf_counter() - start
            row = {"frame": k, "regions": None, "redetermined": None, "segment_seconds": None}
        row["seconds"] = seconds
        write_image(os.path.join(out_dir, f"frame_{k:04d}.png"), np.asarray(image, dtype=np.float32))
        rows.append(row)
        if progress:
            extra = "" if row["regions"] is None else (f", {row['regions']} regions"
                                                       f"{', re-determined' if row['redetermined'] else ''}")
            print(f"animate: frame {k + 1}/{frames} {seconds:.3f} s{extra}", file=sys.stderr, flush=True)
    with open(os.path.join(out_dir, "frames.csv"), "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(COLUMNS)
        for r in rows:
            w.writerow(["" if r[c] is None else (f"{r[c]:.6f}" if isinstance(r[c], float) else r[c])
                        for c in COLUMNS])
    return rows
