"""Issue 11 speed scene with intersection by Embree (Mitsuba 3 / Dr.Jit) and cameras and shading in torch.

Same scene and timing protocol as `bench_speed_mitsuba.py` (whose `Mitsuba` and `time_modes` it uses): in
one run, ours with its defaults, ours with `intersector="mitsuba"` (`renderer.mitsuba.intersect`) at
several `chunk_rays`, and Mitsuba's own full render (`llvm_ad_rgb`, `direct` integrator); warm-up apart,
then interleaved repeats, medians of wall and CPU time (CPU time counts every thread of this process:
Dr.Jit's thread pool included). Then:
- image agreement of each mode with ours (same seed): mean |difference| and the fraction of pixels whose
  largest channel difference exceeds 1e-3;
- where the time goes with the new intersector, one instrumented render per chunk size (wall time:
  Dr.Jit works on its own threads): rays handed to Dr.Jit, tracing Dr.Jit's IR (ray set-up, look-ups),
  the kernel (Embree and the look-ups; `dr.eval` followed by a sync), the results handed back to torch;
  everything else (samples, camera rays, shading, accumulation) is torch; and, for comparison, our own
  intersection and shadow rays timed the same way in an instrumented render with the torch intersector;
- the cost of the torch <-> Dr.Jit hand-over alone (DLPack, zero-copy) against copying the same array.

    python benchmarks/history/bench_embree.py           # -> benchmarks/results/speed_thin_lens_embree.{json,md}
    python benchmarks/history/bench_embree.py --size 128 --repeats 3 --out /tmp/embree
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import statistics
import sys
import time

import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from benchmarks.renderer.bench_speed_mitsuba import SCENE, Mitsuba, add_speed_scene_options, time_modes  # noqa: E402
from benchmarks.results_io import add_output_options, markdown_only, save  # noqa: E402

from renderer import render  # noqa: E402
from renderer.mitsuba import intersect as mi_intersect  # noqa: E402
from renderer.scene.model import Scene  # noqa: E402
from renderer.scene.file import load_scene  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
# "ours defaults": our own intersection in one process (`render`'s defaults before `intersector="auto"` and
# `workers=None`; bench_speed_mitsuba.py times those); every mode names its intersector and workers.
OURS, ONE = {"intersector": "torch", "workers": 1}, {"intersector": "mitsuba", "workers": 1}
MODES = {"ours defaults": OURS, "ours chunk 2^17": {**OURS, "chunk_rays": 1 << 17},
         "embree chunk 2^15": {**ONE, "chunk_rays": 1 << 15},
         "embree": ONE,  # its default chunk_rays, EMBREE_CHUNK_RAYS = 2^17
         "embree chunk 2^19": {**ONE, "chunk_rays": 1 << 19},
         # threads=None: render leaves the thread settings alone, so torch keeps this process's one thread
         # (set in main) and Dr.Jit its own pool (all cores) instead of render's one thread for both.
         "embree jit pool": {**ONE, "threads": None},
         "ours workers2": {**OURS, "workers": 2},
         "embree workers2": {**ONE, "workers": 2}}
DEFAULT_MODES = ("ours defaults,ours chunk 2^17,embree chunk 2^15,embree,embree chunk 2^19,embree jit pool,"
                 "ours workers2,embree workers2")


class _Clock:
    """Wall-time accumulators around callables (inclusive)."""

    def __init__(self):
        self.t: dict = {}

    def wrap(self, name, fn):
        def timed(*args, **kwargs):
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                self.t[name] = self.t.get(name, 0.0) + time.perf_counter() - t0
        return timed


class _SyncedDr:
    """drjit with `eval` timed and followed by a sync, so the kernel's time is counted where it runs."""

    def __init__(self, dr, clock):
        self._dr = dr
        self.eval = clock.wrap("kernel (Embree + look-ups)", lambda *a: (dr.eval(*a), dr.sync_thread()))

    def __getattr__(self, name):
        return getattr(self._dr, name)


def _timed_render(scene, chunk_rays: int, options: dict, clock) -> tuple[float, float]:
    """Wall seconds of one render with `options`, and the part `clock` timed as nearest hits and shadow rays."""
    t0 = time.perf_counter()
    render(scene, chunk_rays=chunk_rays, **options)
    total = time.perf_counter() - t0
    return total, clock.t.get("nearest hits", 0) + clock.t.get("shadow rays", 0)


def profile(scene, chunk_rays: int) -> dict:
    """Wall seconds per stage of one warm render with the Mitsuba intersector at `chunk_rays`."""
    clock = _Clock()
    eng = mi_intersect.engine(scene)
    saved = (mi_intersect._to_torch, eng.dr, eng._ray, eng.nearest, eng.visible)
    mi_intersect._to_torch = clock.wrap("results to torch", mi_intersect._to_torch)
    eng.dr = _SyncedDr(eng.dr, clock)
    eng._ray = clock.wrap("rays to Dr.Jit", eng._ray)
    eng.nearest = clock.wrap("nearest hits", eng.nearest)
    eng.visible = clock.wrap("shadow rays", eng.visible)
    try:
        total, inter = _timed_render(scene, chunk_rays, ONE, clock)
    finally:
        mi_intersect._to_torch, eng.dr, eng._ray, eng.nearest, eng.visible = saved
    for name in ("_ray", "nearest", "visible"):
        eng.__dict__.pop(name, None)
    out = {"total": total, **clock.t}
    out["Dr.Jit IR tracing and the rest of the calls"] = inter - sum(
        clock.t.get(k, 0) for k in ("rays to Dr.Jit", "kernel (Embree + look-ups)", "results to torch"))
    out["torch: samples, camera rays, shading, accumulation"] = total - inter
    return out


def profile_ours(scene, chunk_rays: int) -> dict:
    """Wall seconds of our own nearest hits and shadow rays in one warm render (fast path, (3, N) rows)."""
    clock = _Clock()
    saved = (Scene.intersect_rows, Scene.visibility_rows)
    Scene.intersect_rows = clock.wrap("nearest hits", Scene.intersect_rows)
    Scene.visibility_rows = clock.wrap("shadow rays", Scene.visibility_rows)
    try:
        total, inter = _timed_render(scene, chunk_rays, OURS, clock)
    finally:
        Scene.intersect_rows, Scene.visibility_rows = saved
    return {"total": total, **clock.t, "torch: samples, camera rays, shading, accumulation": total - inter}


def handover(mi, dr, n: int, repeats: int = 200) -> dict:
    """Median microseconds: torch -> Dr.Jit (mi.Float(tensor)), Dr.Jit -> torch (.torch()), and a torch copy
    of the same (n,) float32 array, for scale."""
    x = torch.rand(n)
    y = mi.Float(x) + 1.0
    dr.eval(y)
    dr.sync_thread()

    def med(fn):
        ts = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            fn()
            ts.append(time.perf_counter() - t0)
        return 1e6 * statistics.median(ts)

    return {"n": n, "to_drjit_us": med(lambda: mi.Float(x)), "to_torch_us": med(lambda: y.torch()),
            "torch_clone_us": med(lambda: x.clone()),
            "zero_copy": mi.Float(x).torch().data_ptr() == x.data_ptr()}


def agreement(a: torch.Tensor, b: torch.Tensor) -> dict:
    diff = (a - b).abs()
    return {"mean_abs_diff": float(diff.mean()), "frac_pixels_over_1e-3": float((diff.amax(-1) > 1e-3).float().mean()),
            "max_abs_diff": float(diff.max())}


def write_markdown(path: str, res: dict) -> None:
    m, t = res["machine"], res["timing"]
    mi_t = t["mitsuba"]
    base = t["ours defaults"]["median_wall_s"] if "ours defaults" in t else None
    lines = [
        "# Issue 11 speed scene: intersection by Embree (Mitsuba 3 / Dr.Jit), cameras and shading in torch",
        "",
        f"Date: {res['date']}. {m['cores']} cores shared with other jobs: load average {m['load_start']} at the start, "
        f"{m['load_end']} at the end (1, 5, 15 min). torch {m['torch']} (one thread while tracing, `render`'s "
        f"default), Mitsuba {m['mitsuba']} `{mi_t['kwargs']['variant']}`. Dr.Jit's thread pool: {m['drjit_threads']} "
        "threads for Mitsuba's full render and the `jit pool` modes; the other Embree modes run it with one thread "
        "(`render(threads=1)`, the default, sets both torch's and Dr.Jit's; workers use one of each).",
        f"Command: `{res['command']}`",
        f"Scene: `{res['scene']}`, {res['size']}×{res['size']}, {res['spp']} spp.",
        "",
        "| renderer / settings | warm-up (s) | median wall (s) | median CPU (s) | wall / Mitsuba | wall / ours defaults "
        "| mean abs diff to ours | pixels > 1e-3 |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, v in t.items():
        ag = res["agreement"].get(name)
        label = f"Mitsuba {mi_t['kwargs']['variant']}, full render" if name == "mitsuba" else name
        lines.append(
            f"| {label} | {v['warmup_s']:.2f} | {v['median_wall_s']:.3f} | {v['median_cpu_s']:.3f} | "
            f"{v['median_wall_s'] / mi_t['median_wall_s']:.2f} | "
            f"{'—' if base is None else format(v['median_wall_s'] / base, '.2f')} | "
            f"{'—' if ag is None else format(ag['mean_abs_diff'], '.2e')} | "
            f"{'—' if ag is None else format(100 * ag['frac_pixels_over_1e-3'], '.4f') + ' %'} |")
    lines += ["", f"Medians of {res['repeats']} interleaved repeats after the warm-up render (the first in the process: for "
              "the Embree modes it includes building the Mitsuba scene and compiling Dr.Jit's kernels). CPU time is "
              "the process's, all threads. Differences to ours: same seed, same samples; Mitsuba's full render "
              "uses its own sampler, so it is not compared pixel by pixel.", "",
              "## Where the time goes with the Embree intersector", "",
              "One instrumented warm render per chunk size, wall seconds (Dr.Jit runs on its own threads; `dr.eval` "
              "is followed by a sync here so that the kernel time is counted where it runs). The last column is our "
              "own intersector in the same process, at 2^15 rays a chunk.", ""]
    prof = res["profile"]
    keys = ["total", "nearest hits", "shadow rays", "rays to Dr.Jit", "Dr.Jit IR tracing and the rest of the calls",
            "kernel (Embree + look-ups)", "results to torch", "torch: samples, camera rays, shading, accumulation"]
    cols = list(prof)
    lines.append("| stage | " + " | ".join(cols) + " |")
    lines.append("|---|" + "---|" * len(cols))
    for k in keys:
        lines.append(f"| {k} | " + " | ".join("—" if k not in prof[c] else f"{prof[c][k]:.3f}" for c in cols) + " |")
    lines += ["", "Hand-over between torch and Dr.Jit alone (median µs per (n,) float32 array; DLPack shares memory):", "",
              "| n | torch -> Dr.Jit | Dr.Jit -> torch | torch clone, for scale |", "|---|---|---|---|"]
    for h in res["handover"]:
        lines.append(f"| {h['n']} | {h['to_drjit_us']:.1f} | {h['to_torch_us']:.1f} | {h['torch_clone_us']:.1f} |")
    lines += [""] + res.get("notes", [])
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_speed_scene_options(ap)
    ap.add_argument("--modes", default=DEFAULT_MODES, help=f"comma-separated, of: {', '.join(MODES)}")
    ap.add_argument("--drjit-threads", type=int, help="Dr.Jit's thread pool outside our renders (Mitsuba's full render, "
                    "the `jit pool` modes) [its default: all cores]")
    add_output_options(ap, "speed_thin_lens_embree")
    args = ap.parse_args(argv)
    if markdown_only(args, write_markdown):
        return
    log = lambda msg: print(msg, file=sys.stderr, flush=True)  # noqa: E731
    torch.set_num_threads(1)  # what render(threads=1) sets anyway; kept by the threads=None modes
    load_start = [round(x, 1) for x in os.getloadavg()]
    scene = load_scene(SCENE, [f"image.width={args.size}", f"image.height={args.size}", f"image.spp={args.spp}"])
    ms = Mitsuba(scene, args.spp, "llvm_ad_rgb")
    import drjit as dr

    if args.drjit_threads:
        dr.set_thread_count(args.drjit_threads)
    unknown = [k for k in args.modes.split(",") if k not in MODES]
    if unknown:
        sys.exit(f"--modes: unknown {unknown} (expected some of: {', '.join(MODES)})")
    modes = {k: MODES[k] for k in args.modes.split(",")}
    res = {"date": datetime.datetime.now().isoformat(timespec="seconds"),
           "command": "python benchmarks/history/bench_embree.py " + " ".join(argv if argv is not None else sys.argv[1:]),
           "scene": os.path.relpath(SCENE, ROOT), "size": args.size, "spp": args.spp, "repeats": args.repeats,
           "machine": {"cores": os.cpu_count(), "torch": torch.__version__, "mitsuba": ms.mi.__version__,
                       "drjit_threads": dr.thread_count(), "load_start": load_start}}
    res["timing"] = time_modes(scene, ms, modes, args.repeats, log)
    ref = render(scene, **OURS).image
    res["agreement"] = {name: agreement(render(scene, **kw).image, ref) for name, kw in modes.items()}
    log("agreement: " + json.dumps(res["agreement"]))
    prof = {f"embree, 2^{c}": profile(scene, 1 << c) for c in (15, 17, 19)}
    prof["ours, 2^15"] = profile_ours(scene, 1 << 15)
    res["profile"] = prof
    log("profile: " + json.dumps(prof))
    res["handover"] = [handover(ms.mi, dr, n) for n in (1 << 15, 1 << 19)]
    res["machine"]["load_end"] = [round(x, 1) for x in os.getloadavg()]
    save(args.out, res, write_markdown)


if __name__ == "__main__":  # the guard matters: workers=2 starts processes that import this module
    main()
