"""Where the time of one render goes: per-stage wall time and torch kernel counts on the issue-11 speed scene.

Wraps the render loop's stages with CPU-time timers (process time, less disturbed than wall time by other
programs on the cores; inclusive times; the nesting is shown by indentation in the
report) and counts the torch operator calls per stage with torch.profiler. One torch thread, warm (one
render first), median of `--repeats`.

    python benchmarks/history/profile_fig6.py                       # prints a markdown table
    python benchmarks/history/profile_fig6.py --set image.width=256 --kwargs "dict(chunk_rays=1<<16)"
"""
from __future__ import annotations

import argparse
import collections
import os
import statistics
import time

import torch

import importlib

from renderer.tracing import direct
from renderer.tracing import integrator
from renderer.scene.model import Scene
from renderer.scene.file import load_scene

render_mod = importlib.import_module("renderer.tracing.render")

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SCENE = os.path.join(ROOT, "benchmarks", "scenes", "speed_thin_lens.json")

_TIMES: collections.Counter = collections.Counter()
_CALLS: collections.Counter = collections.Counter()
_STACK: list[str] = []


def _wrap(owner, name: str, label: str):
    fn = getattr(owner, name)

    def timed(*args, **kwargs):
        _STACK.append(label)
        t0 = time.process_time()
        try:
            return fn(*args, **kwargs)
        finally:
            _TIMES[" / ".join(_STACK)] += time.process_time() - t0
            _CALLS[" / ".join(_STACK)] += 1
            _STACK.pop()

    setattr(owner, name, timed)
    return fn


def instrument(scene):
    """Time the stages of `renderer.render` / `renderer.tracing.integrator` and each shape kind's intersect."""
    _wrap(render_mod.Sampler, "pixel_block", "samples")
    _wrap(render_mod, "camera_samples", "camera samples")
    for cam in {type(scene.camera)}:
        _wrap(cam, "generate_rays", "ray generation")
    _wrap(render_mod, "trace", "trace")
    _wrap(Scene, "intersect", "intersect")
    _wrap(Scene, "intersect_rows", "intersect (3, N)")
    _wrap(Scene, "visibility_rows", "shadow rays (3, N)")
    _wrap(direct.NormalTables, "normals", "normals (3, N)")
    _wrap(integrator.direct, "trace_direct", "direct-light fast path")
    _wrap(Scene, "shadow", "shadow rays")
    _wrap(Scene, "_packets", "packet culling")
    _wrap(integrator, "_group_by_object", "group hits by object")
    _wrap(integrator, "_surface", "normals+uv")
    _wrap(integrator, "_albedo", "albedo/texture")
    _wrap(integrator, "direct_light", "shading")
    _wrap(render_mod, "_pixel_estimates", "accumulation")
    for kind in {type(o.shape) for o in scene.objects}:
        _wrap(kind, "intersect", f"{kind.type_name} intersect")
        if kind.soa_native:
            _wrap(kind, "intersect_soa", f"{kind.type_name} intersect (3, N)")
    _wrap(integrator, "_to_light", "to light")
    _wrap(integrator, "_lambert", "lambert")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default=SCENE)
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    ap.add_argument("--kwargs", default="{}", help="keyword arguments of render(), a Python expression")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    scene = load_scene(args.scene, args.overrides)
    kwargs = eval(args.kwargs)  # noqa: S307 - a benchmark's own command line
    render_mod.render(scene, **kwargs)
    plain = []
    for _ in range(args.repeats):
        t0 = time.process_time()
        render_mod.render(scene, **kwargs)
        plain.append(time.process_time() - t0)
    instrument(scene)
    _TIMES.clear()
    _CALLS.clear()
    t0 = time.process_time()
    render_mod.render(scene, **kwargs)
    total = time.process_time() - t0
    times, calls = dict(_TIMES), dict(_CALLS)
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
        render_mod.render(scene, **kwargs)
    ops = sum(e.count for e in prof.key_averages() if e.key.startswith("aten::"))
    W, H, spp = scene.camera.width, scene.camera.height, scene.image.spp if "spp" not in kwargs else kwargs["spp"]
    rays = W * H * spp
    print(f"render {W}x{H}x{spp}, kwargs {kwargs}: median CPU {statistics.median(plain):.3f} s "
          f"({rays / statistics.median(plain) / 1e6:.2f} M camera rays/s); instrumented {total:.3f} s; "
          f"{ops} aten calls per render")
    print("| stage (inclusive; nested under /) | s | % of render | ns per camera ray | calls |")
    print("|---|---|---|---|---|")
    for key in sorted(times):
        t = times[key]
        print(f"| {key} | {t:.3f} | {100 * t / total:.1f} | {1e9 * t / rays:.0f} | {calls[key]} |")
    print()
    print("Top aten operators (self CPU time):")
    print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=25))


if __name__ == "__main__":
    main()
