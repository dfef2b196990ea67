"""Where one GPU render's time goes: kernel launches, GPU-busy time and the costliest operators.

The issue-11 speed scene (512×512, 16 spp, thin lens, shadow rays) rendered on CUDA with torch.profiler,
warm (one render first), for each chunk size given. The question it answers: is the GPU busy (kernel time
close to wall time, so faster kernels would pay) or waiting on Python and launches (kernel time far below
wall time, so fewer, bigger or fused kernels would pay)?

    python benchmarks/history/profile_gpu.py --out benchmarks/results/profile_gpu   # needs a CUDA device
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import time

import torch
from torch.profiler import ProfilerActivity, profile

from renderer import render
from renderer.scene.file import load_scene

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SCENE = os.path.join(ROOT, "benchmarks", "scenes", "speed_thin_lens.json")


def _wall(fn, repeats):
    times = []
    for _ in range(repeats):
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        fn()
        torch.cuda.synchronize()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def profile_chunk(scene, chunk_rays: int, repeats: int) -> dict:
    run = lambda: render(scene, device="cuda", chunk_rays=chunk_rays)  # noqa: E731
    run()
    wall = _wall(run, repeats)
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        run()
        torch.cuda.synchronize()
    events = prof.key_averages()
    kernels = [e for e in prof.events() if e.device_type == torch.autograd.DeviceType.CUDA]
    busy_s = sum(e.time_range.elapsed_us() for e in kernels) * 1e-6
    top = sorted(events, key=lambda e: e.device_time_total, reverse=True)[:12]
    return {"chunk_rays": chunk_rays, "median_wall_s": wall, "kernel_launches": len(kernels),
            "gpu_busy_s": busy_s, "peak_memory_gb": torch.cuda.max_memory_allocated() / 2**30,
            "top_ops": [{"name": e.key, "calls": e.count, "gpu_ms": e.device_time_total * 1e-3} for e in top]}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--chunks", default="15,18,20,22,24", help="log2 of chunk_rays, comma separated")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", default=os.path.join(ROOT, "benchmarks", "results", "profile_gpu"))
    args = ap.parse_args(argv)
    if not torch.cuda.is_available():
        raise SystemExit("profile_gpu: no CUDA device")
    scene = load_scene(SCENE, [f"image.width={args.size}", f"image.height={args.size}"])
    rows = []
    for k in (int(c) for c in args.chunks.split(",")):
        torch.cuda.reset_peak_memory_stats()
        rows.append(profile_chunk(scene, 1 << k, args.repeats))
        print(f"chunk 2^{k}: {rows[-1]['median_wall_s']:.3f} s", flush=True)
    res = {"gpu": torch.cuda.get_device_name(), "torch": torch.__version__, "size": args.size,
           "spp": scene.image.spp, "rows": rows}
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    with open(args.out + ".json", "w") as f:
        json.dump(res, f, indent=1)
    lines = [f"# One GPU render of the issue-11 speed scene ({args.size}×{args.size}, {scene.image.spp} spp)", "",
             f"{res['gpu']}, torch {res['torch']}. Command: `python benchmarks/history/profile_gpu.py "
             f"--chunks {args.chunks}`. Wall: median of {args.repeats} warm renders; kernel counts and GPU-busy "
             "time from one profiled render (the profiler adds its own overhead to that render).", "",
             "| chunk_rays | median wall (s) | kernel launches | GPU busy (s) | busy / wall | peak memory (GB) |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| 2^{r['chunk_rays'].bit_length() - 1} | {r['median_wall_s']:.3f} | {r['kernel_launches']} "
                     f"| {r['gpu_busy_s']:.3f} | {r['gpu_busy_s'] / r['median_wall_s']:.2f} "
                     f"| {r['peak_memory_gb']:.2f} |")
    big = rows[-1]
    lines += ["", f"Costliest operators at chunk 2^{big['chunk_rays'].bit_length() - 1} (GPU time of one render):", "",
              "| operator | calls | GPU ms |", "|---|---|---|"]
    lines += [f"| `{t['name']}` | {t['calls']} | {t['gpu_ms']:.2f} |" for t in big["top_ops"]]
    with open(args.out + ".md", "w") as f:
        f.write("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
