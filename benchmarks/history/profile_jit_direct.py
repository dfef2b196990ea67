"""Where the Dr.Jit path's time goes on the speed scene (`renderer.tracing.jit_direct`), against Mitsuba 3's render.

The path traces one batch as a few Dr.Jit kernels; its stages cannot be timed inside the kernel, so each row
evaluates the computation up to the end of a stage (samples; + camera rays; + Embree's nearest hits; + shading;
+ shadow rays and radiance) in a kernel of its own, and the stage's cost is the difference to the row before.
One Dr.Jit thread, CPU time per render (the batches of a 512 x 512, 16-spp render), medians; then the whole
`render(scene, workers=1)` (one thread) and Mitsuba's `llvm_ad_rgb` render on one thread, in the same run.

    python benchmarks/history/profile_jit_direct.py     # -> benchmarks/results/profile_jit_direct.{json,md}
"""
from __future__ import annotations

import argparse
import datetime
import os
import statistics
import sys
import time

import torch

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)
from benchmarks.results_io import add_output_options, markdown_only, save  # noqa: E402
from renderer import render  # noqa: E402
from renderer.mitsuba import load_mitsuba, to_mitsuba  # noqa: E402
from renderer.scene.file import load_scene  # noqa: E402
from renderer.tracing import fused, jit_direct  # noqa: E402
from renderer.tracing.render import _tile_order_cached  # noqa: E402
from renderer.tracing.sampling import Sampler  # noqa: E402

SCENE = os.path.join(ROOT, "benchmarks", "scenes", "speed_thin_lens.json")
STAGES = ["samples", "camera rays", "Embree nearest hits", "shading", "shadow rays and radiance", "pixel sums"]


def _upto(scene, k, sampler, pixel, stage: int):
    """The Dr.Jit arrays of the computation up to the end of STAGES[stage] (not evaluated)."""
    mi, dr = k.mi, k.dr
    xs, ys, u, v = jit_direct._samples(k, sampler, pixel, scene.camera.width)
    if stage == 0:
        return [xs, ys, u, v]
    o, d = jit_direct._camera_rays(k, xs, ys, u, v, fused._camera_constants(scene.camera))
    if stage == 1:
        return o + d
    eps = scene.ray_epsilon
    t, obj, aux = k.engine.jit_nearest(k.engine.jit_ray(o, d, eps), eps, mi.Int32)
    if stage == 2:
        return [t, obj, aux]
    found, origin, shadow, ambient, unshadowed = jit_direct._shade(k, o, d, t, obj, aux)
    if stage == 3:
        return origin + [c for l, reach in shadow for c in (*l, reach)] + [c for term in unshadowed for c in term]
    rad = None
    for (l, reach), term in zip(shadow, unshadowed):
        vis = k.engine.jit_visible(k.engine.jit_ray(origin, l, eps, reach))
        rad = [term[i] * vis + (0 if rad is None else rad[i]) for i in range(3)]
    if stage == 4:
        return rad
    dr.eval(*rad)
    return [dr.block_sum(r, sampler.spp) for r in rad]


def profile(size: int, spp: int, repeats: int) -> dict:
    scene = load_scene(SCENE, [f"image.width={size}", f"image.height={size}", f"image.spp={spp}"])
    render(scene, workers=1)
    k = jit_direct._kernel(scene)
    dr = k.dr
    dr.set_thread_count(1)
    sampler = Sampler(scene.image.sampler, spp, 0)
    order = _tile_order_cached(size, size)
    chunk = jit_direct.CHUNK_RAYS // spp
    chunks = [order[a:a + chunk] for a in range(0, order.shape[0], chunk)]

    def run(stage):
        c0 = time.process_time()
        for pixel in chunks:
            dr.eval(*_upto(scene, k, sampler, pixel, stage))
        return time.process_time() - c0

    mi = load_mitsuba("llvm_ad_rgb")
    scene_dict, _ = to_mitsuba(scene, spp)
    mscene = mi.load_dict(scene_dict)

    def mitsuba():
        c0 = time.process_time()
        img = mi.render(mscene, seed=1)
        dr.eval(img)
        dr.sync_thread()
        return time.process_time() - c0

    def whole():
        c0 = time.process_time()
        render(scene, workers=1)
        return time.process_time() - c0

    runs = {**{s: lambda s=s: run(STAGES.index(s)) for s in STAGES}, "render": whole, "mitsuba": mitsuba}
    for fn in runs.values():
        fn()
    times = {name: [] for name in runs}
    for _ in range(repeats):
        for name, fn in runs.items():
            times[name].append(fn())
    med = {name: statistics.median(v) for name, v in times.items()}
    stages, before = {}, 0.0
    for s in STAGES:
        stages[s] = med[s] - before
        before = med[s]
    return {"cumulative_s": {s: med[s] for s in STAGES}, "stage_s": stages, "render_s": med["render"],
            "mitsuba_s": med["mitsuba"], "chunks": len(chunks)}


def write_markdown(path: str, res: dict) -> None:
    p = res["profile"]
    lines = ["# Where the Dr.Jit path's time goes (speed scene)", "",
             f"Date: {res['date']}, load average {res['load_start']} at the start, {res['load_end']} at the end "
             f"(2 shared cores). Command: `{res['command']}`. {res['size']}x{res['size']}, {res['spp']} spp, "
             f"{p['chunks']} batch(es); one Dr.Jit thread; CPU seconds per render, medians of {res['repeats']}.", "",
             "| stage | CPU s | evaluated up to here |", "|---|---|---|"]
    for s in STAGES:
        lines.append(f"| {s} | {p['stage_s'][s]:.3f} | {p['cumulative_s'][s]:.3f} |")
    lines += [f"| `render(scene, workers=1)` (Python, tables, copies included) | | {p['render_s']:.3f} |",
              f"| Mitsuba 3 `llvm_ad_rgb` render, one thread | | {p['mitsuba_s']:.3f} |", "",
              f"Ours / Mitsuba in CPU time: {p['render_s'] / p['mitsuba_s']:.2f}x. A stage's cost is the difference "
              "between evaluating the computation up to its end and up to the end of the stage before (each row "
              "its own kernel), so the rows include what a split kernel writes and reads back.", ""]
    with open(path, "w") as f:
        f.write("\n".join(lines))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--repeats", type=int, default=5)
    add_output_options(ap, "profile_jit_direct")
    args = ap.parse_args(argv)
    if markdown_only(args, write_markdown):
        return
    torch.set_num_threads(1)
    load_start = [round(x, 1) for x in os.getloadavg()]
    prof = profile(args.size, args.spp, args.repeats)
    res = {"date": datetime.datetime.now().isoformat(timespec="minutes"), "size": args.size, "spp": args.spp,
           "repeats": args.repeats, "load_start": load_start, "load_end": [round(x, 1) for x in os.getloadavg()],
           "command": "python benchmarks/history/profile_jit_direct.py " + " ".join(argv if argv is not None else sys.argv[1:]),
           "profile": prof}
    save(args.out, res, write_markdown)


if __name__ == "__main__":
    main()
