"""Whether a shortcut in `Rays.transformed` for the identity rotation (a camera looking along +z; it tested R
against the identity on every batch until issue 21) pays: the speed scene rendered with `transformed` as it is
(the general (3, 3) products, which give the same bits for finite rays: checked here) and with the shortcut
patched in, interleaved in one process, one thread, medians of wall time.

    python benchmarks/history/bench_identity_rotation.py     # -> benchmarks/results/identity_rotation.md
"""
from __future__ import annotations

import datetime
import os
import statistics
import time

import torch

import renderer.core.rays as rays
from renderer import render
from renderer.scene.file import load_scene

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
REPEATS = 7


GENERAL = rays.Rays.transformed


def _with_shortcut(self, world_from_local, local_origin_in_world):
    """The removed shortcut: skip the products where R is the identity (a data-dependent test per batch)."""
    if world_from_local.shape == (3, 3) and bool((world_from_local == torch.eye(3).to(world_from_local)).all()):
        return rays.Rays(self.origin + local_origin_in_world, self.direction, self.valid, self.weight)
    return GENERAL(self, world_from_local, local_origin_in_world)


def _timed(scene, intersector: str, shortcut: bool):
    rays.Rays.transformed = _with_shortcut if shortcut else GENERAL
    try:
        start = time.perf_counter()
        image = render(scene, workers=1, intersector=intersector).image
        return time.perf_counter() - start, image
    finally:
        rays.Rays.transformed = GENERAL


def main():
    torch.set_num_threads(1)
    scene = load_scene(os.path.join(ROOT, "benchmarks", "scenes", "speed_thin_lens.json"),
                       ["image.width=256", "image.height=256"])
    rows = []
    for intersector in ("torch", "mitsuba"):
        _timed(scene, intersector, True)  # warm-up: Embree scene, caches
        times = {True: [], False: []}
        images = {}
        for _ in range(REPEATS):
            for shortcut in (True, False):
                t, images[shortcut] = _timed(scene, intersector, shortcut)
                times[shortcut].append(t)
        same = torch.equal(images[True], images[False])
        with_, without = statistics.median(times[True]), statistics.median(times[False])
        rows.append(f"| {intersector} | {with_:.3f} | {without:.3f} | {without / with_:.3f} | {same} |")
    load = os.getloadavg()[0]
    text = "\n".join([
        "# Identity-rotation shortcut in `Rays.transformed`", "",
        f"{datetime.datetime.now():%Y-%m-%d %H:%M}, load {load:.1f} on {os.cpu_count()} cores; speed scene 256×256, "
        f"16 spp, one process, one thread, median of {REPEATS} interleaved renders.", "",
        "    python benchmarks/history/bench_identity_rotation.py", "",
        "| intersector | with shortcut (s) | without (s) | without / with | same image |",
        "|---|---|---|---|---|", *rows, ""])
    out = os.path.join(ROOT, "benchmarks", "results", "identity_rotation.md")
    with open(out, "w", encoding="utf-8") as f:
        f.write(text)
    print(text)


if __name__ == "__main__":
    main()
