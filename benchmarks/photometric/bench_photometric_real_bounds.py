"""`tiltfit calibrate ... --refine photometric` on a few views of each shipped real set: is the refinement kept, and
where not, what CALIB.json's `photometric.bounds` and `rejected_because` say (issue 30 §5).

The command itself (`tiltfit.cli.main.main`), with its defaults, on the first N photos of each set that have a board;
the detections come from the cache beside the photos (`tests/real_detections.py`: what `tiltfit detect`
finds there, so the run skips 3 s of detection a photo), the photos themselves are read as the command reads them.
No peer: OpenCV has no photometric refinement (bench_photometric_trust.py puts calibrateCamera beside the corner fit
on these sets).

    python benchmarks/photometric/bench_photometric_real_bounds.py [--views 4]

Writes benchmarks/results/photometric_real_bounds.{json,md}.
"""
from __future__ import annotations

import json
import os
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)

from benchmarks.results_io import run_benchmark, write_lines  # noqa: E402

#: Set -> pixel pitch (mm), as bench_photometric_trust.py and bench_real_calib.py take them.
SETS = {"industrial_ds1": 0.0048, "gopro_wide": 0.005}


def run_set(name: str, pitch_mm: float, n_views: int) -> dict:
    from benchmarks.photometric.photometric_start import calibrate_refined_cached

    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "CALIB.json")
        names, argv, status, wall = calibrate_refined_cached(name, pitch_mm, n_views, out)
        calib = json.load(open(out)) if os.path.isfile(out) else {}
    ph = calib.get("photometric") or {}
    return {"set": name, "views": names, "exit_status": status, "wall_s": wall,
            "command": "tiltfit " + " ".join("CALIB.json" if a == out else os.path.relpath(a, ROOT)
                                              if a.startswith(ROOT) else a for a in argv),
            "distortion": (calib.get("distortion") or {}).get("model"),
            "kept": ph.get("kept"), "rejected_because": ph.get("rejected_because"), "bounds": ph.get("bounds"),
            "at_bound": ph.get("at_bound"), "free": ph.get("free"), "held_out": ph.get("held_out"),
            "corner_check": ph.get("corner_check"), "corner_fit": ph.get("corner_fit"),
            "corner_fit_sigma": ph.get("corner_fit_sigma"), "refined": ph.get("refined"),
            "refined_sigma": ph.get("refined_sigma"), "aperture": ph.get("aperture"),
            "left_out": ph.get("left_out"), "rms_linear": ph.get("rms_linear")}


def measure(args) -> dict:
    t0 = time.perf_counter()
    rows = []
    for name, pitch in SETS.items():
        print(f"set {name}", file=sys.stderr, flush=True)
        rows.append(run_set(name, pitch, args.views))
        print(f"  kept {rows[-1]['kept']}: {rows[-1]['rejected_because']}", file=sys.stderr, flush=True)
    return {"command": f"python benchmarks/photometric/bench_photometric_real_bounds.py --views {args.views}",
            "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "sets": rows, "wall_s": time.perf_counter() - t0}


def write_markdown(path: str, res: dict) -> None:
    L = ["# `--refine photometric` on the shipped real sets: kept, or which parameter hit which bound (issue 30 §5)",
         "", f"`{res['command']}`, {res['created']}; the command with its defaults on the first views with a board "
         "(detections from the cache), `photometric` block of CALIB.json.", ""]
    for s in res["sets"]:
        L += [f"## {s['set']} ({len(s['views'])} views: {', '.join(s['views'])})", "",
              f"`{s['command']}` → exit {s['exit_status']}, {s['wall_s']:.0f} s; distortion {s['distortion']}; "
              f"aperture {s['aperture']}; kept: **{s['kept']}**", ""]
        if s["rejected_because"]:
            L += [f"rejected because: {s['rejected_because']}", ""]
        L += ["| parameter | corner fit ± σ | refined ± σ | bound [low, high] | at bound |", "|---|---|---|---|---|"]
        bounds = {b["parameter"]: b for b in s["bounds"] or []}
        for k in ("w_mm", "U_mm", "d_mm", "theta_F_deg", "theta_L_deg"):
            cf, cs = (s["corner_fit"] or {}).get(k), (s["corner_fit_sigma"] or {}).get(k)
            rf, rs = (s["refined"] or {}).get(k), (s["refined_sigma"] or {}).get(k)
            b = bounds.get(k)
            fmt = lambda v: "—" if v is None else f"{v:.6g}"  # noqa: E731
            end = lambda v: "∞" if v is None else f"{v:.6g}"   # noqa: E731  (U's end where 1/U reaches 0)
            L.append(f"| {k} | {fmt(cf)} ± {fmt(cs)} | {fmt(rf)} ± {fmt(rs)} | "
                     + (f"[{end(b['low'])}, {end(b['high'])}] | {'**yes**' if b['at_bound'] else 'no'} |" if b else
                        "not bounded (held or free) | — |"))
        h, cc = s.get("held_out"), s.get("corner_check")
        L.append("")
        if h:
            L.append(f"- held-out pixels ({h['pixels']}): mean Huber cost {h['refined']:.4g} refined, {h['start']:.4g} "
                     "corner fit")
        if cc:
            L.append(f"- corners held out of the photometric fit: RMS {cc['refined_px']:.4f} px refined, "
                     f"{cc['start_px']:.4f} px corner fit (limit {cc['limit_px']:.4f})")
        if s["left_out"]:
            L.append(f"- views left out: {s['left_out']}")
        L.append("")
    write_lines(path, L)


if __name__ == "__main__":
    sys.exit(run_benchmark(__doc__, "photometric_real_bounds", measure, write_markdown, views=4))
