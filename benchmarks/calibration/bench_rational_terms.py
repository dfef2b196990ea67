"""Which rational model with fewer terms fills the gap between opencv5 and the eight-term rational model (issue 22):
on the GoPro subsets where the automatic choice refuses the rational model (coefficients undetermined), each
candidate's K-fold held-out error (lens and board refitted without the scored views, as the selection scores it)
and its worst projection σ over the image; industrial_ds1 as a check that nothing changes there. Candidates:
rational5 (k1 k2 p1 p2 k4, offered by tiltfit) and rational6 (k1 k2 p1 p2 k3 k4: a first-order denominator with
opencv5's numerator; defined here only, for the comparison). And each against OpenCV's calibrateCamera with the
same terms (CALIB_RATIONAL_MODEL with k3/k5/k6 fixed, square pixels, flat board) on the same corners.

Writes benchmarks/results/rational_terms.{json,md}. Usage: python benchmarks/calibration/bench_rational_terms.py
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import sys
import time

import cv2

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
import renderer.cameras.distortion as _distortion  # noqa: E402

# The benchmark-only candidate, placed by its number of terms before tiltfit reads the model list.
_terms = dict(_distortion.MODEL_TERMS)
_distortion.MODEL_TERMS.clear()
for _name, _t in _terms.items():
    _distortion.MODEL_TERMS[_name] = _t
    if _name == "rational5":
        _distortion.MODEL_TERMS["rational6"] = ("k1", "k2", "p1", "p2", "k3", "k4")
_distortion.MODELS = tuple(_distortion.MODEL_TERMS)

from tests.real_detections import REAL, observations  # noqa: E402
from benchmarks.results_io import RESULTS, write_lines  # noqa: E402

from tiltfit.files.calib import calib_dict  # noqa: E402
from tiltfit.calibrate.flow import calibrate  # noqa: E402
from tiltfit.calibrate.fit import FitError, FitOptions, without_blur  # noqa: E402
from tiltfit.detect.imaging import torch_threads  # noqa: E402
from tiltfit.detect.opencv import opencv_calibrate  # noqa: E402
from tiltfit.select.held_out import held_out_rms  # noqa: E402

FOLDS = 5
MODELS = ("opencv5", "rational5", "rational6", "rational")
FLAGS = {"opencv5": 0, "rational5": cv2.CALIB_RATIONAL_MODEL | cv2.CALIB_FIX_K3 | cv2.CALIB_FIX_K5 | cv2.CALIB_FIX_K6,
         "rational6": cv2.CALIB_RATIONAL_MODEL | cv2.CALIB_FIX_K5 | cv2.CALIB_FIX_K6,
         "rational": cv2.CALIB_RATIONAL_MODEL}


def ours(obs, model, board, held=True) -> dict:
    t0 = time.perf_counter()
    opts = FitOptions(distortion=model, board=board, free_principal_point=True)
    try:
        res = calibrate(obs, "unified", options=opts)
    except FitError as e:
        return {"error": str(e)}
    d = calib_dict(res)
    out = {"f_px": d["w_mm"] / d["pixel_pitch_mm"], "sigma_f_px": d["sigma"]["w_mm"] / d["pixel_pitch_mm"],
           "principal_point_px": d["principal_point_px"], "sigma_principal_point_px": d["sigma"].get("principal_point_px"),
           "coefficients": d["distortion"]["coefficients"], "sigma_coefficients": d["sigma"]["distortion"],
           "projection_worst_px": d["projection_uncertainty"]["worst_px"]}
    if held:
        bd = res.board.model if res.board is not None else None
        out["held_out_rms_px"] = held_out_rms(without_blur(obs), opts, FOLDS, board=bd)["rms_px"]
    out["wall_s"] = time.perf_counter() - t0
    return out


def opencv(obs, model) -> dict:
    f0 = 600.0 if obs.image_size_px[0] < 2000 and obs.pixel_pitch_mm == 0.005 else 3000.0
    rms, K, _ = opencv_calibrate(obs, FLAGS[model], focal_px=f0)
    return {"f_px": float(K[0, 0]), "principal_point_px": [float(K[0, 2]), float(K[1, 2])], "rms_px": float(rms)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=os.path.join(RESULTS, "rational_terms"),
                    help="output path without extension (.json and .md are written)")
    args = ap.parse_args(argv)
    gopro, _ = observations(os.path.join(REAL, "gopro_wide"), 0.005)
    ind, _ = observations(os.path.join(REAL, "industrial_ds1"), 0.0048)
    sets = [("gopro_wide", "first 12 photos", gopro.subset(list(range(12))), "free")]
    sets += [("gopro_wide", f"views {g}, {g + 3}, … (every third)", gopro.subset(list(range(g, gopro.n_views, 3))), "free")
             for g in range(3)]
    sets += [("gopro_wide", "all", gopro, "free"), ("industrial_ds1", "all", ind, "flat"),
             ("industrial_ds1", "all", ind, "free")]
    rows = []
    with torch_threads(1):
        for data, label, obs, board in sets:
            obs = without_blur(obs)
            for m in MODELS:
                row = {"data": data, "set": label, "views": obs.n_views, "board": board, "model": m,
                       **ours(obs, m, board)}
                if (board == "flat" or label == "first 12 photos" or data == "gopro_wide") and label in (
                        "all", "first 12 photos"):
                    row["flat"] = dict(row) if board == "flat" else ours(obs, m, "flat", held=False)
                    row["opencv"] = opencv(obs, m)
                rows.append(row)
                print(data, label, board, m, {k: row.get(k) for k in ("held_out_rms_px", "projection_worst_px", "f_px",
                                                                      "error")}, file=sys.stderr, flush=True)
    out = {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
           "machine": platform.platform(), "folds": FOLDS, "rows": rows}
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    with open(args.out + ".json", "w", encoding="utf-8") as f:
        json.dump(out, f, indent=1, default=lambda o: None)
        f.write("\n")
    lines = ["# Rational models with fewer terms (issue 22)", "",
             "Per model, principal point free: the K-fold held-out error (lens and board refitted without the scored "
             f"views, {FOLDS} folds), the worst projection σ over the image (CALIB.json's "
             "`projection_uncertainty.worst_px`), focal length and the largest σ/|k| of the radial coefficients. "
             "rational5: k1 k2 p1 p2 k4; rational6: k1 k2 p1 p2 k3 k4 (measured here only). OpenCV: "
             "`cv2.calibrateCamera` with `CALIB_FIX_ASPECT_RATIO` and the same terms (rational5: `CALIB_RATIONAL_MODEL "
             "| CALIB_FIX_K3 | CALIB_FIX_K5 | CALIB_FIX_K6`; rational6: without FIX_K3) on the same corners with the "
             f"flat board; Δf/σ: ours (flat board) minus OpenCV's, in our σ. `{out['date']}`. Reproduce: "
             "`python benchmarks/calibration/bench_rational_terms.py`.", "",
             "| data | views | board | model | held-out px | worst σ px | f px | largest σ/|k| | flat f px | OpenCV f px | Δf/σ | Δ(cx, cy) px |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    names = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
    for r in rows:
        head = f"| {r['data']} | {r['set']} ({r['views']}) | {r['board']} | {r['model']} |"
        if "error" in r:
            lines.append(f"{head} refused: {r['error'][:120]} | | | | | | | |")
            continue
        rel = max(((s / abs(c)) if c else float("inf"), n) for c, s, n in
                  zip(r["coefficients"], r["sigma_coefficients"], names) if s and n not in ("p1", "p2"))
        cmp = " | | |"
        fl, cv = r.get("flat"), r.get("opencv")
        if fl and cv and "error" not in fl:
            cmp = (f" {fl['f_px']:.2f} ± {fl['sigma_f_px']:.2f} | {cv['f_px']:.2f} | {(fl['f_px'] - cv['f_px']) / fl['sigma_f_px']:+.2f} | "
                   f"{fl['principal_point_px'][0] - cv['principal_point_px'][0]:+.2f}, "
                   f"{fl['principal_point_px'][1] - cv['principal_point_px'][1]:+.2f} |")
        elif fl and "error" in fl:
            cmp = f" refused (flat) | {cv['f_px']:.2f} | | |"
        lines.append(f"{head} {r['held_out_rms_px']:.4f} | {r['projection_worst_px']:.3g} | {r['f_px']:.1f} ± "
                     f"{r['sigma_f_px']:.1f} | {rel[0]:.2g} ({rel[1]}) |" + cmp)
    write_lines(args.out + ".md", lines + [""])
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
