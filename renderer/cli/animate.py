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

On a cluster (`--cluster auto|ADDRESS`, `renderer.tracing.distributed`): `trace` renders each frame as one Ray task
(the scene description shipped once; every frame built from it as here). `beam` reuses work from frame to
frame, which is sequential, so the frames are cut into one contiguous run per CPU of the cluster, each a
task with its own tracer: the run's first frame pays the full segmentation (plus the shadow polygons, and,
for a run not starting at frame 0, one extra segmentation of the frame before it, which is not rendered but
gives the run the reuse state, and `redetermined`, of one unbroken sequence). The driver writes the frames in
order as they come back. The frames and frames.csv are those of a run here, bit for bit, except the timing
columns (`seconds`, `segment_seconds`).
"""
from __future__ import annotations

import csv
import os
import sys
import time

import numpy as np

from renderer.tracing.distributed import imap_on_cluster
from camio.files import write_image
from renderer.core.params import SceneError
from renderer.scene.file import load_scene, parse_animation, read_scene_json, require_objects

METHODS = ("beam", "trace")
COLUMNS = ("frame", "seconds", "regions", "redetermined", "segment_seconds")


def animation_defaults(path: str, overrides=()) -> dict:
    """The scene file's validated `animation` section after overrides ({} when it has none)."""
    from renderer.scene.file import apply_override

    cfg = read_scene_json(path)
    try:
        for text in overrides:
            apply_override(cfg, text)
        return parse_animation(cfg)
    except SceneError as e:
        raise SceneError(f"{path}: {e}") from None


def animate(path: str, method: str, frames: int, step: float, out_dir: str, overrides=(), *, device="cpu",
            progress: bool = True, seed: int = 0, cluster: str | None = None) -> list[dict]:
    """Render the frames (see the module docstring) and write them and frames.csv into out_dir.

    Args:
        seed: sampler seed of the `trace` renders.
        cluster: None (here), or `auto` / a Ray address: frames rendered as Ray tasks (see "On a cluster"
            in the module docstring); the frames and frames.csv are those of a run here, timing aside.
    Returns:
        One row per frame: {frame, seconds, regions, redetermined, segment_seconds} (None where empty).
    """
    if method not in METHODS:
        raise SceneError(f"--method: expected one of {', '.join(METHODS)}, got {method!r}")
    scene = load_scene(path, overrides)
    require_objects(path, scene)
    _check_travel(scene, frames, step)
    os.makedirs(out_dir, exist_ok=True)
    if method == "beam":
        from renderer.beam import BeamTracer

        try:
            tracer = BeamTracer(scene)
        except SceneError as e:
            raise SceneError(f"{path}: {e}") from None
        job = (scene, step)
        if cluster is None:
            results = _beam_frames(job, (0, frames), tracer)
        else:
            results = _beam_on_cluster(job, frames, cluster)
    else:
        position = scene.camera.transform.position.numpy()
        view = scene.camera.transform.world_from_camera[:, 2].numpy()
        # A task gets the scene description (not the built scene) and builds each frame from it exactly as
        # a run here builds it from the file; relative mesh/texture names resolve against base_dir.
        source = path if cluster is None else read_scene_json(path)
        job = (source, os.path.dirname(os.path.abspath(path)), tuple(overrides), step, position, view,
               device, seed)
        results = (r for _, r in imap_on_cluster(_trace_frame, range(frames), cluster, shared=job))
    rows = []
    for image, row in results:
        k = row["frame"]
        write_image(os.path.join(out_dir, f"frame_{k:04d}.png"), np.asarray(image, dtype=np.float32))
        rows.append(row)
        if progress:
            extra = "" if row["regions"] is None else (f", {row['regions']} regions"
                                                       f"{', re-determined' if row['redetermined'] else ''}")
            print(f"animate: frame {k + 1}/{frames} {row['seconds']:.3f} s{extra}", file=sys.stderr, flush=True)
    with open(os.path.join(out_dir, "frames.csv"), "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(COLUMNS)
        for r in rows:
            w.writerow(["" if r[c] is None else (f"{r[c]:.6f}" if isinstance(r[c], float) else r[c])
                        for c in COLUMNS])
    return rows


def _check_travel(scene, frames: int, step: float) -> None:
    """Refuse a step that moves the camera where float32 (the tracer's precision) no longer tells its
    position from a point one unit further along its view direction."""
    position = scene.camera.transform.position.detach().double().cpu().numpy()
    last = position + (frames - 1) * step * scene.camera.transform.world_from_camera[:, 2].detach().double().cpu().numpy()
    far = float(np.abs(last).max())
    if not far * FLOAT32_EPS * 4 < 1.0:
        raise SceneError(f"--step (animation.step): {step:g} moves the camera to {far:.3g} scene units from the "
                         f"origin by frame "
                         f"{frames - 1}, beyond float32's resolution of a unit step (at most about "
                         f"{1 / (4 * FLOAT32_EPS):.3g})")


FLOAT32_EPS = 2.0 ** -23


def contiguous_runs(frames: int, workers: int) -> list[tuple[int, int]]:
    """[(first, stop), ...]: frames 0..frames-1 cut into at most `workers` contiguous runs of near-equal length."""
    n = max(1, min(frames, workers))
    bounds = [round(i * frames / n) for i in range(n + 1)]
    return [(a, b) for a, b in zip(bounds, bounds[1:])]


def _beam_on_cluster(job, frames: int, cluster: str):
    """(image, row) per frame in frame order: one contiguous run of frames per CPU of the cluster, each a task."""
    from renderer.tracing.distributed import cluster_cpus, cluster_session

    with cluster_session(cluster) as ray:
        runs = contiguous_runs(frames, cluster_cpus(ray))
        for _, run in imap_on_cluster(_beam_run, runs, cluster, shared=job):
            yield from run


def _beam_run(job, run) -> list:
    """One task: the frames of `run` by beam tracing, [(image, row), ...] (see `_beam_frames`)."""
    return list(_beam_frames(job, run))


def _beam_frames(job, run, tracer=None):
    """Frames first..stop-1 (run = (first, stop)) by beam tracing: yields (image (H, W, 3) float64, row).

    A new tracer (or `tracer`, fresh) segments frame 0 of a run from scratch. A run that does not start at
    frame 0 first segments frame first-1 (not rendered), so the reuse between frames, and `redetermined`,
    are those of one unbroken sequence."""
    from renderer.beam import BeamTracer, ScreenCamera

    scene, step = job
    first, stop = run
    tracer = tracer or BeamTracer(scene)
    base = ScreenCamera.of(scene.camera)
    if first > 0:
        tracer.frame(base.moved((first - 1) * step))
    for k in range(first, stop):
        start = time.perf_counter()
        frame = tracer.frame(base.moved(k * step))
        image = tracer.render(frame)
        row = {"frame": k, "regions": len(frame.regions), "redetermined": int(frame.redetermined),
               "segment_seconds": frame.seconds}
        row["seconds"] = time.perf_counter() - start + frame.polygon_seconds
        yield image, row


def _trace_frame(job, k: int):
    """Frame k by ray tracing: (image (H, W, 3) float32 linear RGB, row)."""
    from renderer.tracing.render import render

    source, base_dir, overrides, step, position, view, device, seed = job
    p = position + k * step * view
    moved = [f"camera.position={list(map(float, p))}", f"camera.look_at={list(map(float, p + view))}"]
    frame_scene = load_scene(source, list(overrides) + moved, base_dir=base_dir)
    start = time.perf_counter()
    image = render(frame_scene, device=device, seed=seed).image.cpu().numpy()
    row = {"frame": k, "seconds": time.perf_counter() - start, "regions": None, "redetermined": None,
           "segment_seconds": None}
    return image, row
