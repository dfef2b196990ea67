"""Two of this project's throughput settings, measured: the CPU's rays per batch, and writing a 20-Mpx photo.

1. Rays per batch (`render(chunk_rays=...)`) on the issue-11 speed scene (512x512, 16 spp), one torch thread,
   median CPU time of interleaved repeats: what `renderer.tracing.render.CPU_CHUNK_RAYS` is chosen from.
2. A 5472x3648 photograph as `tiltfit reproduce --scale 1` makes it: the sensor model on a numpy array
   against a tensor (`SensorResponse.expose`), and the PNG written from its uint8 levels against the
   former decode-and-re-encode path, at zlib level 3 (`camio.files.PNG_COMPRESSION_LEVEL`) and 6
   (OpenImageIO's default).

    PYTHONPATH=. OMP_NUM_THREADS=1 python benchmarks/renderer/bench_batch_io.py   # -> benchmarks/results/batch_io.{json,md}
"""
from __future__ import annotations

import argparse
import datetime
import os
import statistics
import sys
import tempfile
import time

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from benchmarks.results_io import ROOT, add_output_options, markdown_only, save  # noqa: E402

from camio import files as rio  # noqa: E402
from renderer import load_scene, write_image
from renderer import render  # noqa: E402
from renderer.cameras.sensor import SensorResponse, decode_srgb8  # noqa: E402

SCENE = os.path.join(ROOT, "benchmarks", "scenes", "speed_thin_lens.json")


def batches(repeats: int, log) -> dict:
    scene = load_scene(SCENE)
    sizes = [15, 16, 17, 18]
    for c in sizes:
        render(scene, chunk_rays=1 << c)  # warm-up
    cpu = {c: [] for c in sizes}
    for r in range(repeats):
        for c in sizes:
            t = time.process_time()
            render(scene, chunk_rays=1 << c)
            cpu[c].append(time.process_time() - t)
        log(f"repeat {r + 1}/{repeats}: " + ", ".join(f"2^{c} {cpu[c][-1]:.3f} s" for c in sizes))
    return {f"2^{c}": statistics.median(v) for c, v in cpu.items()}


def photo(repeats: int, log) -> dict:
    h, w = 3648, 5472
    y, x = np.mgrid[0:h, 0:w]
    rad = (np.sin(x / 200.0) * np.cos(y / 150.0) * 0.35 + 0.45)[..., None].repeat(3, -1)
    cam = SensorResponse(vignetting=0.05, read_noise=0.002, full_well=4000.0, encoding="srgb8")
    out = {}

    def timed(name, fn):
        ts = []
        for _ in range(repeats):
            t = time.perf_counter()
            fn()
            ts.append(time.perf_counter() - t)
        out[name] = statistics.median(ts)
        log(f"{name}: {out[name]:.2f} s")

    timed("expose, numpy array", lambda: cam.expose(rad, np.random.default_rng(0)))
    tensor = torch.from_numpy(rad)
    timed(f"expose, CPU tensor ({torch.get_num_threads()} torch threads)",
          lambda: cam.expose(tensor, torch.Generator().manual_seed(0)))
    levels = cam.expose(rad, np.random.default_rng(0))
    with tempfile.TemporaryDirectory() as d:
        path = os.path.join(d, "photo.png")
        level = rio.PNG_COMPRESSION_LEVEL
        try:
            for zlib_level in (6, 3):
                rio.PNG_COMPRESSION_LEVEL = zlib_level
                timed(f"PNG from uint8 levels, zlib {zlib_level}", lambda: write_image(path, levels))
                out[f"PNG size MB, zlib {zlib_level}"] = os.path.getsize(path) / 1e6
            rio.PNG_COMPRESSION_LEVEL = 6
            timed("PNG decoded to linear and re-encoded (former path), zlib 6",
                  lambda: write_image(path, decode_srgb8(levels).astype(np.float32)))
        finally:
            rio.PNG_COMPRESSION_LEVEL = level
    return out


def write_markdown(path: str, res: dict) -> None:
    lines = ["# Rays per batch and 20-Mpx photo writing", "",
             f"Date: {res['date']}. Load average {res['load_start']} at the start, {res['load_end']} at the end "
             "(2 shared cores). Command: `PYTHONPATH=. OMP_NUM_THREADS=1 python benchmarks/renderer/bench_batch_io.py`.", "",
             "## Rays per batch, issue-11 speed scene (512x512, 16 spp), one torch thread", "",
             "| rays per batch | median CPU (s) | / 2^15 |", "|---|---|---|"]
    base = res["batches"]["2^15"]
    for k, v in res["batches"].items():
        lines.append(f"| {k} | {v:.3f} | {v / base:.2f} |")
    lines += ["", "## One 5472x3648 photograph (median wall, s; sizes in MB)", "", "| step | value |", "|---|---|"]
    for k, v in res["photo"].items():
        lines.append(f"| {k} | {v:.2f} |")
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    add_output_options(ap, "batch_io")
    args = ap.parse_args(argv)
    if markdown_only(args, write_markdown):
        return
    log = lambda msg: print(msg, file=sys.stderr, flush=True)  # noqa: E731
    torch.set_num_threads(1)
    res = {"date": datetime.datetime.now().isoformat(timespec="seconds"),
           "load_start": [round(v, 1) for v in os.getloadavg()]}
    res["batches"] = batches(args.repeats, log)
    res["photo"] = photo(args.repeats, log)
    res["load_end"] = [round(v, 1) for v in os.getloadavg()]
    save(args.out, res, write_markdown)


if __name__ == "__main__":
    main()
