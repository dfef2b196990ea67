"""Blur widths under a 1e-6 px move of the corners they are measured at, on the shipped real photos (issue 32 §1).

A width should be a smooth function of its corner: a move of 1e-6 px should move it by a negligible share of its
σ. For every photo with a board (every `--every`-th), the corners of tiltfit's cached detections
(data/real/SET/detections_tiltfit.json, /work/shared/data/real/sony_small through benchmarks/small_sets) are moved
by 1e-6 px (seeded normal, per coordinate) and `tiltfit.detect.blur.measure_blur` is run at both; counted: widths
moved by more than 0.01, 1 and 3 σ (σ at the unmoved corners), widths with σ = 0, widths measured in one run
and not the other.

Run from a checkout (the `tiltfit` imported is the one on sys.path first), so an older commit is measured with the
same script: `cd /tmp/old && python /work/main/benchmarks/detection/bench_blur_smoothness.py --out
/work/main/benchmarks/results/blur_smoothness_8c1f30a`.

    python benchmarks/detection/bench_blur_smoothness.py [--every 1] [--out STEM]
"""
from __future__ import annotations

import glob
import json
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # the repository root
sys.path.insert(0, os.getcwd())  # the checkout measured
sys.path.insert(1, HERE)

from benchmarks.results_io import run_benchmark, write_lines  # noqa: E402

SETS = {"gopro_wide": (os.path.join(HERE, "data/real/gopro_wide"), None),
        "industrial_ds1": (os.path.join(HERE, "data/real/industrial_ds1"), None),
        "sony_small": ("/work/shared/data/real/sony_small", os.path.join(HERE, "benchmarks/small_sets/sony_small"))}
MOVE_PX = 1e-6


def _corners(det: dict) -> np.ndarray:
    return np.array([[np.nan, np.nan] if c is None else c for c in det["corners_px"]], dtype=np.float64)


def _photos(photos_dir, cache_dir, every):
    """(name, corners) of the set's photos with a board: the cache beside the target, else detected here."""
    from camio.files import read_image
    from tiltfit.detect.chessboard import detect
    from tiltfit.target.layout import load_target

    target = load_target(os.path.join(cache_dir or photos_dir, "target.json"))
    cache = os.path.join(photos_dir, "detections_tiltfit.json")
    if os.path.exists(cache):
        with open(cache, encoding="utf-8") as f:
            dets = {k: _corners(v) for k, v in json.load(f).items() if "corners_px" in v}
    else:  # sony_small: no cache shipped beside the photos
        dets = {}
        for p in sorted(glob.glob(os.path.join(photos_dir, "*.jpg"))):
            det = detect(read_image(p), target, measure_blur=False)
            if det.grid_found:
                dets[os.path.basename(p)] = det.corners_px
    names = sorted(dets)[::every]
    return target, [(n, dets[n]) for n in names]


def measure(args) -> dict:
    import torch

    import tiltfit
    from camio.files import read_image
    from tiltfit.detect.blur import measure_blur
    from tiltfit.detect.imaging import to_gray

    torch.set_num_threads(1)
    rows = []
    for set_name, (photos_dir, cache_dir) in SETS.items():
        target, photos = _photos(photos_dir, cache_dir, args.every)
        moved, widths, zero, lost, cpu = [], 0, 0, 0, []
        for k, (name, corners) in enumerate(photos):
            gray = to_gray(read_image(os.path.join(photos_dir, name)))
            t0 = time.process_time()
            b0, s0 = measure_blur(gray, target, corners)
            cpu.append(time.process_time() - t0)
            shift = MOVE_PX * np.random.default_rng(k).standard_normal(corners.shape)
            b1, _ = measure_blur(gray, target, corners + shift)
            both = np.isfinite(b0) & np.isfinite(b1)
            lost += int(np.sum(np.isfinite(b0) != np.isfinite(b1)))
            zero += int(np.sum(s0[np.isfinite(b0)] == 0))
            widths += int(both.sum())
            with np.errstate(divide="ignore", invalid="ignore"):
                moved.append(np.abs(b1 - b0)[both] / s0[both])
            print(f"[bench_blur_smoothness] {set_name} {name}: worst {np.max(moved[-1]):.3g} σ", file=sys.stderr,
                  flush=True)
        m = np.concatenate(moved) if moved else np.zeros(0)
        rows.append({"set": set_name, "images": len(photos), "widths": widths,
                     "moved_over_0.01_sigma": int(np.sum(m > 0.01)), "moved_over_1_sigma": int(np.sum(m > 1)),
                     "moved_over_3_sigma": int(np.sum(m > 3)), "worst_sigma": float(np.max(m)) if m.size else None,
                     "images_all_within_0.01_sigma": int(sum(np.max(x) <= 0.01 for x in moved)),
                     "sigma_zero": zero, "measured_in_one_run_only": lost,
                     "cpu_per_image_s": float(np.median(cpu)) if cpu else None})
    return {"rows": rows, "move_px": MOVE_PX, "every": args.every, "tiltfit": os.path.dirname(tiltfit.__file__)}


def write_markdown(path, res):
    lines = ["# Blur widths under a 1e-6 px move of their corners", "",
             f"`python benchmarks/detection/bench_blur_smoothness.py --every {res['every']}` (tiltfit from "
             f"`{res['tiltfit']}`): the cached corners of every {res['every']}. photo with a board moved by "
             f"{res['move_px']:g} px; widths moved by more than 0.01 / 1 / 3 σ (σ at the unmoved corners), widths "
             "with σ = 0, widths measured in one run only; CPU time of one `measure_blur`, median.", "",
             "| set | images | widths | > 0.01 σ | > 1 σ | > 3 σ | worst (σ) | images all ≤ 0.01 σ | σ = 0 | "
             "one run only | CPU a photo (s) |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in res["rows"]:
        lines.append(f"| {r['set']} | {r['images']} | {r['widths']} | {r['moved_over_0.01_sigma']} | "
                     f"{r['moved_over_1_sigma']} | {r['moved_over_3_sigma']} | {r['worst_sigma']:.3g} | "
                     f"{r['images_all_within_0.01_sigma']} | {r['sigma_zero']} | {r['measured_in_one_run_only']} | "
                     f"{r['cpu_per_image_s']:.2f} |")
    write_lines(path, lines + [""])


if __name__ == "__main__":
    sys.exit(run_benchmark(__doc__, "blur_smoothness", measure, write_markdown, every=1))
