"""Where two worker processes lose time against one on the issue-11 speed scene (the defaults' path).

Times, interleaved and warm, `render(scene)` in one process (`workers=1`) and in two worker processes
(`workers=2`), both with Embree (`intersector="mitsuba"`), and for the two-worker render the jobs as the
workers see them: the time each job takes inside its worker (busy), against the render's wall time. The
difference between the render's wall time and the busiest worker is the cost of handing jobs out and the
results back; the difference between the summed busy time and one process's time is what the two processes
lose running side by side (memory traffic of two eager tracers on 2 cores).

    python benchmarks/history/bench_workers.py        # -> benchmarks/results/workers.{json,md}
"""
from __future__ import annotations

import argparse
import datetime
import hashlib
import importlib
import os
import pickle
import statistics
import sys
import time

import torch

from renderer import render
from renderer.scene.file import load_scene
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))  # the repository root: benchmarks.results_io
from benchmarks.results_io import add_output_options, markdown_only, save  # noqa: E402

render_mod = importlib.import_module("renderer.tracing.render")
ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SCENE = os.path.join(ROOT, "benchmarks", "scenes", "speed_thin_lens.json")


def timed_job(*args):
    """One render job in a worker, with the worker's own clock around it."""
    t0 = time.perf_counter()
    out = render_mod._worker_render(*args)
    return out, t0, time.perf_counter()


def _jobs_as_workers_see_them(scene, spp: int, workers: int) -> dict:
    """The jobs of one `render(scene, workers=workers, intersector="mitsuba")`, submitted as `render` does,
    each timed inside its worker: wall, per-job busy times."""
    options = render_mod._resolve_intersector(scene, scene.options, "cpu", torch.float32)
    assert options.intersector == "mitsuba", "Mitsuba's llvm variant does not run here"
    blob = pickle.dumps(scene)
    digest = hashlib.sha1(blob).hexdigest()
    pool = render_mod._pool(workers)
    chunk = render_mod.EMBREE_CHUNK_RAYS
    job_rays = render_mod._job_rays(scene, spp, workers, chunk)
    t0 = time.perf_counter()
    futures = [pool.submit(timed_job, digest, blob, pixel, n, spp, scene.image.sampler, 0, options, torch.float32,
                           None, chunk, True)
               for pixel, n in render_mod._chunks(scene, spp, options, job_rays)]
    results = [f.result() for f in futures]
    wall = time.perf_counter() - t0
    return {"wall": wall, "busy": [b - a for _, a, b in results]}


def write_markdown(path: str, res: dict) -> None:
    r = res["summary"]
    lines = [
        "# Two worker processes against one, issue-11 speed scene (Embree, eager)", "",
        f"Date: {res['date']}. {res['cores']} cores, load average {res['load_start']} at the start, "
        f"{res['load_end']} at the end. Command: `{res['command']}`.",
        f"Scene: `{res['scene']}`, {res['size']}×{res['size']}, {res['spp']} spp; medians of {res['repeats']} "
        "interleaved repeats, warm.", "",
        "| measure | seconds |", "|---|---|",
        f"| one process (`workers=1`), wall | {r['one_process_s']:.3f} |",
        f"| two workers (`workers=2`, the defaults here), wall | {r['two_workers_s']:.3f} |",
        f"| two workers, jobs submitted as `render` does, wall | {r['jobs_wall_s']:.3f} |",
        f"| ... summed busy time inside the workers | {r['busy_sum_s']:.3f} |",
        f"| ... per worker (half the sum) | {r['busy_per_worker_s']:.3f} |", "",
        f"- Speed-up of two workers over one process: {r['one_process_s'] / r['two_workers_s']:.2f}x (2x is the "
        "ceiling on 2 cores).",
        f"- Handing out jobs and gathering results: {r['jobs_wall_s'] - r['busy_per_worker_s']:.3f} s of the "
        "render's wall time (wall minus the busy time per worker).",
        f"- Running side by side: the jobs' summed busy time is {r['busy_sum_s'] / r['one_process_s']:.2f}x one "
        "process's time for the same work.", ""]
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--repeats", type=int, default=7)
    add_output_options(ap, "workers")
    args = ap.parse_args(argv)
    if markdown_only(args, write_markdown):
        return
    load_start = [round(x, 1) for x in os.getloadavg()]
    scene = load_scene(SCENE, [f"image.width={args.size}", f"image.height={args.size}", f"image.spp={args.spp}"])
    kw = {"intersector": "mitsuba"}
    render(scene, workers=1, **kw)
    render(scene, workers=2, **kw)
    _jobs_as_workers_see_them(scene, args.spp, 2)
    one, two, jobs_wall, busy = [], [], [], []
    for r in range(args.repeats):
        t = time.perf_counter()
        render(scene, workers=1, **kw)
        one.append(time.perf_counter() - t)
        t = time.perf_counter()
        render(scene, workers=2, **kw)
        two.append(time.perf_counter() - t)
        j = _jobs_as_workers_see_them(scene, args.spp, 2)
        jobs_wall.append(j["wall"])
        busy.append(sum(j["busy"]))
        print(f"repeat {r + 1}/{args.repeats}: one {one[-1]:.3f} s, two {two[-1]:.3f} s, jobs {j['wall']:.3f} s "
              f"(busy {busy[-1]:.3f} s)", file=sys.stderr, flush=True)
    med = statistics.median
    res = {"date": datetime.datetime.now().isoformat(timespec="seconds"), "cores": os.cpu_count(),
           "command": "python benchmarks/history/bench_workers.py " + " ".join(argv if argv is not None else sys.argv[1:]),
           "scene": os.path.relpath(SCENE, ROOT), "size": args.size, "spp": args.spp, "repeats": args.repeats,
           "load_start": load_start, "load_end": [round(x, 1) for x in os.getloadavg()],
           "one_process": one, "two_workers": two, "jobs_wall": jobs_wall, "busy_sum": busy,
           "summary": {"one_process_s": med(one), "two_workers_s": med(two), "jobs_wall_s": med(jobs_wall),
                       "busy_sum_s": med(busy), "busy_per_worker_s": med(busy) / 2}}
    save(args.out, res, write_markdown)


if __name__ == "__main__":
    main()
