"""The default model choice on small GoPro sets (issue 22): `tiltfit calibrate`'s defaults (distortion auto, board
auto) against what they chose before on the first 12 photos (rational distortion, free board), on the same corners
(tiltfit's cached detections, tests/real_detections.py): the first 12 photos, and the 35 views dealt into
three interleaved groups (about 12 views each).

Per set and configuration: the models, focal length and principal point, the K-fold held-out error (lens and
board refitted without the scored views), the distortion coefficients with σ, the worst projection σ over the
image (CALIB.json's `projection_uncertainty.worst_px`), and the paired difference of the held-out mean square
error (defaults minus rational/free, over the same views and folds) in standard errors.

Writes benchmarks/results/selection.{json,md}. Usage: python benchmarks/calibration/bench_selection.py
"""
from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import platform
import sys
import time
from dataclasses import replace

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from tests.real_detections import REAL, observations  # noqa: E402
from benchmarks.results_io import RESULTS, write_lines  # noqa: E402

from tiltfit.files.calib import calib_dict  # noqa: E402
from tiltfit.calibrate.flow import calibrate  # noqa: E402
from tiltfit.calibrate.fit import FitError, FitOptions, without_blur  # noqa: E402
from tiltfit.detect.imaging import torch_threads  # noqa: E402
from tiltfit.select.held_out import held_out_rms  # noqa: E402

FOLDS = 5
CONFIGS = {"defaults": FitOptions(distortion="auto", board="auto"),
           "rational, free board": FitOptions(distortion="rational", board="free")}


def run(obs, opts) -> dict:
    t0 = time.perf_counter()
    try:
        res = calibrate(obs, "unified", options=opts)
    except FitError as e:
        return {"error": str(e)}
    seconds = time.perf_counter() - t0
    data = calib_dict(res)
    geo = without_blur(obs)
    held = held_out_rms(geo, replace(opts, distortion=res.distortion_model, free_principal_point=res.free_principal_point),
                        FOLDS, board=res.board.model if res.board is not None else None)
    return {"distortion": res.distortion_model, "board": res.board.model if res.board is not None else "flat",
            "f_px": data["w_mm"] / data["pixel_pitch_mm"], "sigma_f_px": data["sigma"]["w_mm"] / data["pixel_pitch_mm"],
            "principal_point_px": data["principal_point_px"], "rms_px": data["rms_reprojection_px"],
            "held_out_rms_px": held["rms_px"], "held_out_per_view_px": held["per_view_px"],
            "coefficients": data["distortion"]["coefficients"], "sigma_coefficients": data["sigma"]["distortion"],
            "projection_worst_px": data["projection_uncertainty"]["worst_px"],
            "projection_median_px": data["projection_uncertainty"]["median_px"], "wall_s": seconds}


def paired_z(n, a, b) -> float:
    d = n * (np.array(a) ** 2 - np.array(b) ** 2)
    return float(d.sum() / (math.sqrt(len(d)) * d.std(ddof=1)))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=os.path.join(RESULTS, "selection"),
                    help="output path without extension (.json and .md are written)")
    args = ap.parse_args(argv)
    obs, _ = observations(os.path.join(REAL, "gopro_wide"), 0.005)
    sets = {"first 12 photos": list(range(12))} | {f"views {g}, {g + 3}, … (every third)": list(range(g, obs.n_views, 3))
                                                   for g in range(3)}
    rows = []
    with torch_threads(1):
        for label, idx in sets.items():
            sub = obs.subset(idx)
            row = {"set": label, "views": len(idx), **{k: run(sub, o) for k, o in CONFIGS.items()}}
            a, b = row["defaults"], row["rational, free board"]
            if "error" not in a and "error" not in b:
                row["paired_z"] = paired_z(sub.corner_mask.sum(-1).numpy(), a["held_out_per_view_px"],
                                           b["held_out_per_view_px"])
            rows.append(row)
            print(label, json.dumps({k: {kk: v[kk] for kk in ("distortion", "board", "held_out_rms_px", "projection_worst_px")}
                                     if "error" not in v else v for k, v in row.items() if k in CONFIGS}),
                  f"z {row.get('paired_z')}", file=sys.stderr, flush=True)
    out = {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
           "machine": platform.platform(), "folds": FOLDS, "rows": rows}
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    with open(args.out + ".json", "w", encoding="utf-8") as f:
        json.dump(out, f, indent=1)
        f.write("\n")
    names = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
    lines = ["# The default model choice on small GoPro sets (issue 22)", "",
             "`tiltfit calibrate`'s defaults (distortion auto, board auto) against what they chose before on the first "
             "12 photos (rational, free board), on tiltfit's cached corners and blur widths of data/real/gopro_wide. "
             f"Held-out: {FOLDS}-fold, lens and board refitted without the scored views (views dealt round-robin). "
             "z: the held-out mean square error of the defaults minus that of rational/free, paired over the same "
             "views, in standard errors (positive: the defaults predict worse). Worst σ: the projection's σ at the "
             f"worst place in the image (CALIB.json's `projection_uncertainty.worst_px`). `{out['date']}`. "
             "Reproduce: `python benchmarks/calibration/bench_selection.py`.", "",
             "| views | configuration | distortion | board | f px | cx, cy | held-out px | worst σ px | largest σ/|k| | z |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        for k in CONFIGS:
            x = r[k]
            if "error" in x:
                lines.append(f"| {r['set']} ({r['views']}) | {k} | refused: {x['error']} | | | | | | | |")
                continue
            rel = max((s / abs(c), n) for c, s, n in zip(x["coefficients"], x["sigma_coefficients"], names)
                      if s and n not in ("p1", "p2"))
            lines.append(f"| {r['set']} ({r['views']}) | {k} | {x['distortion']} | {x['board']} | {x['f_px']:.1f} ± "
                         f"{x['sigma_f_px']:.1f} | {x['principal_point_px'][0]:.1f}, {x['principal_point_px'][1]:.1f} | "
                         f"{x['held_out_rms_px']:.4f} | {x['projection_worst_px']:.3g} | {rel[0]:.3g} ({rel[1]}) | "
                         + (f"{r['paired_z']:+.2f}" if k == "defaults" and "paired_z" in r else "") + " |")
    write_lines(args.out + ".md", lines + [""])
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
