"""The speed scene as a new user gets it: with and without Mitsuba's llvm variant (libLLVM >= 16), against Mitsuba.

A fresh Debian 12 machine has libLLVM 14 and 15 only; Mitsuba's `llvm_ad_rgb` needs 16 or newer (the Makefile
installs Debian's libllvm19 where it can). Without it `render(scene)`'s default `intersector="auto"` traces with
our pure-torch code, and Mitsuba itself can only run `scalar_rgb`. Both situations are measured here in the same
run, the missing library simulated with `RENDERER_HIDE_MITSUBA_JIT=1` (renderer.mitsuba.variants.HIDE_JIT_ENV):

- `ours_llvm`: `render(scene)` with the llvm variant running (Embree hits, and for this scene the whole batch as
  Dr.Jit kernels beside them on Dr.Jit's pool, `renderer.tracing.jit_direct`);
- `ours_llvm_eager`: the same with `TraceOptions.jit_kernels=False`: shading in eager torch between the Embree
  calls, in worker processes as `workers=None` picks them (the defaults before issue 32's change);
- `ours_no_llvm`: `render(scene)` with it hidden (pure torch);
- `mitsuba_llvm`, `mitsuba_scalar`: Mitsuba 3 on the exported scene (`renderer.mitsuba.to_mitsuba`) in each variant.

Each configuration runs in its own fresh process (one warm-up render, then `--repeats` timed renders, median);
the processes are run `--rounds` times in turn and the medians of the rounds reported, with ratios to Mitsuba's
llvm variant (what a user with the library gets from the peer). Each process gets an empty Dr.Jit kernel cache
(`HOME` a new temporary folder: Dr.Jit keeps its compiled kernels in `~/.drjit`), so the warm-up (the first
render) includes compiling every kernel, for Mitsuba as for ours, as on a new machine; the process's start to
its first image (imports included) is reported beside it.

    python benchmarks/renderer/bench_fresh_machine.py     # -> benchmarks/results/fresh_machine_speed.{json,md}
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time

START = time.perf_counter()  # the child's start, before its imports

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))  # the repository root: benchmarks.results_io
from benchmarks.results_io import add_output_options, markdown_only, save  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SCENE = os.path.join(ROOT, "benchmarks", "scenes", "speed_thin_lens.json")
# name -> (renderer, libLLVM hidden, our Dr.Jit kernels on)
CONFIGS = {"ours_llvm": ("ours", False, True), "ours_llvm_eager": ("ours", False, False),
           "ours_no_llvm": ("ours", True, True), "mitsuba_llvm": ("mitsuba", False, True),
           "mitsuba_scalar": ("mitsuba", True, True)}


def _child(renderer_name: str, size: int, spp: int, repeats: int, eager: bool) -> None:
    """In a child process: warm-up and timed renders of one configuration; prints one JSON line."""
    from dataclasses import replace

    from renderer import render
    from renderer.mitsuba import load_mitsuba, to_mitsuba
    from renderer.scene.file import load_scene

    scene = load_scene(SCENE, [f"image.width={size}", f"image.height={size}", f"image.spp={spp}"])
    if renderer_name == "ours":
        if eager:
            scene.options = replace(scene.options, jit_kernels=False)
        run = lambda seed: render(scene, seed=seed).image  # noqa: E731 - the user's call, nothing else
        engine = "auto"
    else:
        import drjit as dr

        mi = load_mitsuba("llvm_ad_rgb")  # scalar_rgb where the llvm variant does not run (or is hidden)
        scene_dict, dropped = to_mitsuba(scene, spp)
        assert not dropped, f"the speed scene should carry over exactly, dropped {dropped}"
        mscene = mi.load_dict(scene_dict)

        def run(seed):
            img = mi.render(mscene, seed=seed)
            dr.eval(img)
            dr.sync_thread()
            return img
        engine = mi.variant()
    t0 = time.perf_counter()
    run(0)
    first_image = time.perf_counter()
    warmup = first_image - t0
    walls = []
    for r in range(repeats):
        t0 = time.perf_counter()
        run(r + 1)
        walls.append(time.perf_counter() - t0)
    if renderer_name == "ours":
        from renderer.mitsuba.intersect import llvm_available

        engine = ("embree, eager torch shading" if eager else "embree + Dr.Jit kernels") if llvm_available() else "torch"
    print(json.dumps({"warmup_s": warmup, "median_s": statistics.median(walls), "walls": walls, "engine": engine,
                      "start_to_image_s": first_image - START}))


def measure(config: str, size: int, spp: int, repeats: int) -> dict:
    renderer_name, hidden, kernels = CONFIGS[config]
    env = dict(os.environ)
    env.pop("RENDERER_HIDE_MITSUBA_JIT", None)
    if hidden:
        env["RENDERER_HIDE_MITSUBA_JIT"] = "1"
    with tempfile.TemporaryDirectory(prefix="fresh_home_") as home:  # an empty ~/.drjit: no compiled kernels
        env["HOME"] = home
        out = subprocess.run([sys.executable, os.path.abspath(__file__), "--child", renderer_name, "--size",
                              str(size), "--spp", str(spp), "--repeats", str(repeats)] + ([] if kernels else ["--eager"]),
                             capture_output=True, text=True, env=env)
    if out.returncode != 0:
        raise SystemExit(f"bench_fresh_machine: {config} failed: {out.stderr.strip().splitlines()[-1:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def write_markdown(path: str, res: dict) -> None:
    ref = res["configs"]["mitsuba_llvm"]["median_s"]
    lines = [
        "# The speed scene with and without libLLVM >= 16 (what a fresh machine gives), against Mitsuba 3",
        "",
        f"Date: {res['date']}. {res['machine']['cores']} cores, load average {res['machine']['load_start']} at the start, "
        f"{res['machine']['load_end']} at the end. Scene `benchmarks/scenes/speed_thin_lens.json` at "
        f"{res['size']}x{res['size']}, {res['spp']} spp. Each configuration in a fresh process, {res['repeats']} timed "
        f"renders after one warm-up, {res['rounds']} rounds in turn; medians. No libLLVM >= 16 simulated with "
        "`RENDERER_HIDE_MITSUBA_JIT=1`. Command: `python benchmarks/renderer/bench_fresh_machine.py`.",
        "",
        "| configuration | engine | median render (s) | / Mitsuba llvm | / Mitsuba in the same situation "
        "| warm-up: first render (s) | process start to first image (s) |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, v in res["configs"].items():
        peer = res["configs"]["mitsuba_scalar" if name.endswith("no_llvm") or name == "mitsuba_scalar" else "mitsuba_llvm"]
        start = v.get("start_to_image_s")
        lines.append(f"| {name} | {v['engine']} | {v['median_s']:.3f} | {v['median_s'] / ref:.2f}x | "
                     f"{v['median_s'] / peer['median_s']:.2f}x | {v['warmup_s']:.2f} | "
                     f"{'' if start is None else f'{start:.2f}'} |")
    lines += ["", f"Without libLLVM >= 16 our default render is {res['configs']['ours_no_llvm']['median_s'] / res['configs']['ours_llvm']['median_s']:.2f}x "
              "slower than with it; the Makefile therefore installs Debian's libllvm19 as root, and says so in one line "
              "where it cannot.", ""]
    with open(path, "w") as f:
        f.write("\n".join(lines))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--eager", action="store_true", help=argparse.SUPPRESS)  # the child: jit_kernels=False
    add_output_options(ap, "fresh_machine_speed")
    args = ap.parse_args(argv)
    if args.child:
        return _child(args.child, args.size, args.spp, args.repeats, args.eager)
    if markdown_only(args, write_markdown):
        return
    load_start = round(os.getloadavg()[0], 2)
    runs = {name: [] for name in CONFIGS}
    for r in range(args.rounds):
        for name in CONFIGS:
            runs[name].append(measure(name, args.size, args.spp, args.repeats))
            print(f"round {r + 1}/{args.rounds} {name}: {runs[name][-1]['median_s']:.3f} s ({runs[name][-1]['engine']})",
                  file=sys.stderr, flush=True)
    configs = {name: {"engine": v[0]["engine"], "median_s": statistics.median(x["median_s"] for x in v),
                      "warmup_s": statistics.median(x["warmup_s"] for x in v),
                      "start_to_image_s": statistics.median(x["start_to_image_s"] for x in v), "rounds": v}
               for name, v in runs.items()}
    res = {"date": datetime.datetime.now().isoformat(timespec="minutes"), "size": args.size, "spp": args.spp,
           "repeats": args.repeats, "rounds": args.rounds, "configs": configs,
           "machine": {"cores": os.cpu_count(), "cpu": platform.processor(), "load_start": load_start,
                       "load_end": round(os.getloadavg()[0], 2)}}
    save(args.out, res, write_markdown)


if __name__ == "__main__":
    main()
