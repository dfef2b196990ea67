"""The Dr.Jit path (`renderer.tracing.jit_direct`, the default since issue 32) against the eager Embree path it
replaced (`TraceOptions.jit_kernels=False`), on every scene it takes: the speed scene and the shipped scenes.

Both render with the same samples (the same seeds); they differ by float rounding (Dr.Jit's own sine and cosine,
operation order), which can move a ray grazing an edge to another hit. Whether that changes the images as
estimates: the RMSE of each against a high-spp reference of the eager path (so the reference, if anything,
favours the old path), per seed, and the pixels where the two differ.

    python benchmarks/history/jit_kernels_rmse.py     # -> benchmarks/results/jit_kernels_rmse.{json,md}
"""
from __future__ import annotations

import argparse
import datetime
import glob
import json
import os
import statistics
import sys
from dataclasses import replace

import torch

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)
from benchmarks.results_io import add_output_options, markdown_only, save  # noqa: E402
from renderer import render  # noqa: E402
from renderer.scene.file import load_scene  # noqa: E402
from renderer.scene.model import TraceOptions  # noqa: E402
from renderer.tracing import jit_direct  # noqa: E402


def scenes(width: int) -> dict:
    """name -> scene (at `width` pixels wide, the file's aspect) of every scene the Dr.Jit path takes."""
    paths = [os.path.join(ROOT, "benchmarks", "scenes", "speed_thin_lens.json")]
    paths += sorted(glob.glob(os.path.join(ROOT, "renderer", "scenes", "*.json")))
    out = {}
    for path in paths:
        with open(path) as f:
            cfg = json.load(f)
        if not isinstance(cfg, dict):
            continue  # the gallery's list
        scene = load_scene(path)
        height = max(1, round(width * scene.camera.height / scene.camera.width))
        scene = load_scene(path, [f"image.width={width}", f"image.height={height}"])
        if jit_direct.applies(scene, TraceOptions(intersector="mitsuba"), "cpu", torch.float32):
            out[os.path.basename(path)[:-5]] = scene
    return out


def compare(scene, seeds: int, ref_spp: int) -> dict:
    eager = replace(scene.options, jit_kernels=False)
    new_options = scene.options

    def image(options, **kw):
        scene.options = options
        return render(scene, intersector="mitsuba", workers=1, **kw).image

    ref = image(eager, spp=ref_spp, seed=1000)
    rows = []
    for seed in range(seeds):
        old, new = image(eager, seed=seed), image(new_options, seed=seed)
        diff = (new - old).abs().amax(-1)
        rows.append({"seed": seed, "rmse_old": float(((old - ref) ** 2).mean().sqrt()),
                     "rmse_new": float(((new - ref) ** 2).mean().sqrt()), "max_abs_diff": float(diff.max()),
                     "pixels_over_1e-4": int((diff > 1e-4).sum()), "pixels_over_1e-2": int((diff > 1e-2).sum()),
                     "mean_old": float(old.mean()), "mean_new": float(new.mean())})
    scene.options = new_options
    return {"size": [scene.camera.width, scene.camera.height], "spp": scene.image.spp, "ref_spp": ref_spp,
            "seeds": rows, "median_rmse_old": statistics.median(r["rmse_old"] for r in rows),
            "median_rmse_new": statistics.median(r["rmse_new"] for r in rows)}


def write_markdown(path: str, res: dict) -> None:
    lines = ["# The Dr.Jit path against the eager Embree path it replaced (issue 32)", "",
             f"Date: {res['date']}. Command: `{res['command']}`. Each scene at its own spp, seeds 0 to "
             f"{res['seeds'] - 1}; reference: the eager path at {res['ref_spp']} spp, seed 1000. RMSE over all "
             "pixels and channels, medians over the seeds; pixels counted where the largest channel difference "
             "between the two paths exceeds the threshold (same seed).", "",
             "| scene | size | spp | RMSE eager (before) | RMSE Dr.Jit (now) | now / before | max difference | "
             "pixels > 1e-4 | pixels > 1e-2 | mean before | mean now |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, v in res["scenes"].items():
        worst = max(v["seeds"], key=lambda r: r["max_abs_diff"])
        px = v["size"][0] * v["size"][1]
        lines.append(f"| {name} | {v['size'][0]}×{v['size'][1]} | {v['spp']} | {v['median_rmse_old']:.6f} | "
                     f"{v['median_rmse_new']:.6f} | {v['median_rmse_new'] / v['median_rmse_old']:.4f} | "
                     f"{worst['max_abs_diff']:.2e} | "
                     f"{max(r['pixels_over_1e-4'] for r in v['seeds'])} of {px} | "
                     f"{max(r['pixels_over_1e-2'] for r in v['seeds'])} | "
                     f"{statistics.mean(r['mean_old'] for r in v['seeds']):.6f} | "
                     f"{statistics.mean(r['mean_new'] for r in v['seeds']):.6f} |")
    lines += ["", "Pixel counts are the largest over the seeds. The scenes not listed (pinhole and inverted "
              "cameras, cones, CSG, layers) do not take the Dr.Jit path and render bit for bit as before.", ""]
    with open(path, "w") as f:
        f.write("\n".join(lines))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--width", type=int, default=256)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--ref-spp", type=int, default=512)
    add_output_options(ap, "jit_kernels_rmse")
    args = ap.parse_args(argv)
    if markdown_only(args, write_markdown):
        return
    torch.set_num_threads(1)
    res = {"date": datetime.datetime.now().isoformat(timespec="minutes"), "seeds": args.seeds, "ref_spp": args.ref_spp,
           "command": "python benchmarks/history/jit_kernels_rmse.py " + " ".join(argv if argv is not None else sys.argv[1:]),
           "scenes": {}}
    for name, scene in scenes(args.width).items():
        res["scenes"][name] = compare(scene, args.seeds, args.ref_spp)
        v = res["scenes"][name]
        print(f"{name}: RMSE {v['median_rmse_old']:.6f} -> {v['median_rmse_new']:.6f}", file=sys.stderr, flush=True)
    save(args.out, res, write_markdown)


if __name__ == "__main__":
    main()
