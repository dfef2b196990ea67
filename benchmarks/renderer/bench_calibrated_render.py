"""Rendering the target through a calibration (issue 30): ours against Mitsuba 3 with the same camera, same run.

For each shipped real set, the board (`target` shape: squares, margin, exact edges) seen by view 0 of the set's
calibration (tests/data/calibrations/SET.json: distortion, principal point, blur U and d where the calibration
has them) at the calibration's full image size, under ambient light (the image is the print's albedo), as
`tiltfit report` renders it. Ours: `renderer.render` with its defaults. Mitsuba: the same scene through
`renderer.mitsuba.to_mitsuba` (our thin-lens sensor plugin with the calibrated distortion; the print as a
nearest-texel bitmap), llvm variant where it runs.

Timing: a warm-up render each (reported apart: our first call, Mitsuba's JIT), then `--repeats` renders each,
interleaved, medians of wall time; the ratio is ours / Mitsuba. Agreement: mean |ours − Mitsuba| over the
board, in units of the print's contrast (0.76), on the last images.

    .venv/bin/python benchmarks/renderer/bench_calibrated_render.py         # writes benchmarks/results/calibrated_render.*
"""
from __future__ import annotations

import os
import statistics
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))  # the repository root: benchmarks.results_io
from benchmarks.results_io import ROOT, run_benchmark, write_lines  # noqa: E402

SETS = ("industrial_ds1", "gopro_wide")
REFLECTANCE = (0.04, 0.8)


def scene_of(name: str, spp: int):
    from renderer.scene.file import load_scene

    return load_scene({
        "image": {"spp": spp},
        "camera": {"type": "calibrated", "file": os.path.join(ROOT, "tests", "data", "calibrations", f"{name}.json"),
                   "view": 0},
        "lights": [{"type": "ambient", "intensity": [1, 1, 1]}],
        "objects": [{"name": "board", "shape": {"type": "target",
                                                "file": os.path.join(ROOT, "data", "real", name, "target.json"),
                                                "reflectance": list(REFLECTANCE)}}]})


def measure(args) -> dict:
    import drjit as dr

    from renderer import render
    from renderer.mitsuba import load_mitsuba, to_mitsuba
    from renderer.mitsuba.export import develop
    from renderer.mitsuba.variants import DEFAULT_VARIANT

    mi = load_mitsuba(DEFAULT_VARIANT)
    out = {"spp": args.spp, "repeats": args.repeats, "mitsuba_variant": mi.variant(), "sets": {},
           "load_average_start": list(os.getloadavg())}
    for name in SETS:
        scene = scene_of(name, args.spp)
        ms_dict, dropped = to_mitsuba(scene, args.spp)
        ms_scene = mi.load_dict(ms_dict)

        def ours():
            return render(scene, spp=args.spp, progress=False).image.numpy()

        def mitsuba(seed):
            img = mi.render(ms_scene, seed=seed, spp=args.spp)
            dr.eval(img)
            dr.sync_thread()
            return develop(scene, img)  # the ambient term comes as an albedo AOV

        warm = {}
        t0 = time.perf_counter()
        ours()
        warm["ours"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        mitsuba(0)
        warm["mitsuba"] = time.perf_counter() - t0
        wall = {"ours": [], "mitsuba": []}
        for r in range(args.repeats):
            for who in ("ours", "mitsuba"):
                t0 = time.perf_counter()
                img = ours() if who == "ours" else mitsuba(r + 1)
                wall[who].append(time.perf_counter() - t0)
                if who == "ours":
                    a = img[..., 0]
                else:
                    b = img[..., 0]
            print(f"{name}: repeat {r + 1}/{args.repeats}", file=sys.stderr, flush=True)
        board = (a > 0) | (b > 0)
        med = {k: statistics.median(v) for k, v in wall.items()}
        W, H = scene.image.width, scene.image.height
        out["sets"][name] = {
            "image": [W, H], "dropped_by_mitsuba": dropped, "warmup_s": warm, "wall_s": wall, "median_wall_s": med,
            "ratio_ours_over_mitsuba": med["ours"] / med["mitsuba"],
            "camera_rays_per_s": {k: W * H * args.spp / v for k, v in med.items()},
            "mean_abs_diff_over_contrast": float(np.abs(a - b)[board].mean() / (REFLECTANCE[1] - REFLECTANCE[0])),
            "board_pixels": int(board.sum()),
        }
    return out


def write_markdown(path: str, res: dict) -> None:
    lines = ["# Rendering the target through a calibration: ours against Mitsuba 3 (same camera, same run)", "",
             f"`python benchmarks/renderer/bench_calibrated_render.py` — view 0 of each shipped set's calibration "
             f"(tests/data/calibrations), full size, {res['spp']} spp, ambient light; medians of {res['repeats']} "
             f"interleaved renders; Mitsuba {res['mitsuba_variant']}. Load average at start: "
             f"{', '.join(f'{v:.1f}' for v in res['load_average_start'])} (2 cores).", "",
             "| set | image | ours (s) | Mitsuba (s) | ours / Mitsuba | warm-up ours / Mitsuba (s) | mean abs diff / contrast |",
             "|---|---|---|---|---|---|---|"]
    for name, r in res["sets"].items():
        m, w = r["median_wall_s"], r["warmup_s"]
        lines.append(f"| {name} | {r['image'][0]}×{r['image'][1]} | {m['ours']:.2f} | {m['mitsuba']:.2f} | "
                     f"{r['ratio_ours_over_mitsuba']:.2f} | {w['ours']:.1f} / {w['mitsuba']:.1f} | "
                     f"{r['mean_abs_diff_over_contrast']:.4f} |")
    lines += ["", "Differences are at the squares' edges (independent sampling of the pixel area in each renderer, "
              "and Mitsuba's print is a nearest-texel bitmap of 1/64 of a square), not in the geometry."]
    write_lines(path, lines)


if __name__ == "__main__":
    raise SystemExit(run_benchmark(__doc__, "calibrated_render", measure, write_markdown, spp=4, repeats=3))
