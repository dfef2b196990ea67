"""What raising glibc's mmap threshold (`renderer.core.memory.tune_allocator`) gives: the same work in fresh
processes with RENDERER_MALLOPT=1 (the default) and =0 (glibc's own thresholds), interleaved, medians of
wall, user and system time.

Workloads: the issue-11 speed scene rendered at 256×256, 16 spp (eager, one thread), three times in one
process after a warm-up render; and the photometric refinement of two ray-traced views (the target renderer's
forward-mode Jacobians), one fit.

    python benchmarks/renderer/bench_allocator.py            # -> benchmarks/results/allocator.{json,md}
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import resource
import statistics
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

RENDER = """
import time, torch
from renderer import render
from renderer.scene.file import load_scene
scene = load_scene("benchmarks/scenes/speed_thin_lens.json", ["image.width=256", "image.height=256"])
render(scene)
t = time.perf_counter()
for _ in range(3):
    render(scene)
print(time.perf_counter() - t)
"""

PHOTOMETRIC = """
import sys, time
sys.path.append("tests/tiltfit")
import test_photometric as tp
from tiltfit.photometric import PhotometricOptions, refine_photometric
images, poses, truth = tp._captures(U0_mm=700.0, spp=16, views=(0, 1))
start = tp._camera(tp._perturbed_init(poses, truth, scale=0.5), images, truth["pitch"])
t = time.perf_counter()
refine_photometric(images, tp.BOARD, start, PhotometricOptions(lens_samples=32, max_pixels=600))
print(time.perf_counter() - t)
"""

WORKLOADS = {"render 3x (speed scene 256², 16 spp)": RENDER, "photometric fit (2 views, 600 px)": PHOTOMETRIC}


def run_once(code: str, tuned: bool) -> dict:
    env = dict(os.environ, RENDERER_MALLOPT="1" if tuned else "0", OMP_NUM_THREADS="1", PYTHONPATH=ROOT)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, check=True)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return {"timed_s": float(out.stdout.strip().splitlines()[-1]), "user_s": after.ru_utime - before.ru_utime,
            "sys_s": after.ru_stime - before.ru_stime}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default=os.path.join(ROOT, "benchmarks", "results", "allocator"))
    args = ap.parse_args(argv)
    res = {"date": datetime.datetime.now().isoformat(timespec="seconds"), "load_start": os.getloadavg(),
           "repeats": args.repeats, "workloads": {}}
    for name, code in WORKLOADS.items():
        runs = {"tuned": [], "glibc": []}
        for r in range(args.repeats):
            for key, tuned in (("tuned", True), ("glibc", False)):
                runs[key].append(run_once(code, tuned))
                print(f"{name} {key} {r + 1}/{args.repeats}: {runs[key][-1]['timed_s']:.2f} s", file=sys.stderr,
                      flush=True)
        res["workloads"][name] = {k: {m: statistics.median(x[m] for x in v) for m in ("timed_s", "user_s", "sys_s")}
                                  for k, v in runs.items()}
    res["load_end"] = os.getloadavg()
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out + ".json", "w") as f:
        json.dump(res, f, indent=1)
    lines = ["# glibc's mmap threshold raised (`renderer.core.memory`) against glibc's defaults", "",
             f"Date: {res['date']}; load average {tuple(round(x, 1) for x in res['load_start'])} at the start, "
             f"{tuple(round(x, 1) for x in res['load_end'])} at the end. Command: `python benchmarks/renderer/bench_allocator.py`. "
             f"Fresh processes, interleaved, medians of {args.repeats}; timed = the workload's own timer, user and "
             "system = the whole process (imports and set-up included).", "",
             "| workload | allocator | timed (s) | user (s) | system (s) | timed, glibc / tuned |", "|---|---|---|---|---|---|"]
    for name, w in res["workloads"].items():
        ratio = w["glibc"]["timed_s"] / w["tuned"]["timed_s"]
        for key in ("tuned", "glibc"):
            v = w[key]
            lines.append(f"| {name} | {'raised thresholds' if key == 'tuned' else 'glibc defaults'} | "
                         f"{v['timed_s']:.3f} | {v['user_s']:.2f} | {v['sys_s']:.2f} | "
                         f"{f'{ratio:.2f}' if key == 'tuned' else ''} |")
    with open(args.out + ".md", "w") as f:
        f.write("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
