"""`tiltfit calibrate` with only the required flags against OpenCV's calibrateCamera, per shipped photo set, on the
same corners (tiltfit's own detections, data/real/SET/detections_tiltfit.json, written by real_detections.py).

Ours: `tiltfit calibrate DET... --target T.json --pixel-pitch-mm P -o CALIB.json` (defaults: distortion auto,
principal point where justified, 5-fold held-out). OpenCV: cv2.calibrateCamera with its default flags (fx and fy
free, principal point free, k1 k2 p1 p2 k3 = our opencv5), and with CALIB_FIX_ASPECT_RATIO (square pixels, our
camera model). RMS per corner (OpenCV's definition, sqrt(mean(dx² + dy²))); held-out: the same 5 folds (views dealt
round-robin), the lens calibrated on the others, each held-out view's pose by solvePnP with that lens.

Writes benchmarks/results/real_defaults.{json,md}. Usage:
    python benchmarks/calibration/bench_real_defaults.py [--sets gopro_wide industrial_ds1] [--out benchmarks/results]
"""
from __future__ import annotations

import argparse
import contextlib
import datetime
import io
import json
import math
import os
import platform
import sys
import tempfile
import time

import cv2
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from tests.real_detections import REAL, read_cache  # noqa: E402

from tiltfit.cli import main as cli  # noqa: E402
from tiltfit.target.layout import load_target  # noqa: E402

# The pitch only scales w, U, d in mm; the pixels (focal length, principal point, RMS) do not depend on it.
PIXEL_PITCH_MM = {"gopro_wide": 0.005, "industrial_ds1": 0.0048}
FOLDS = 5


def corners(folder: str):
    """(names, [(N_v, 3) target points], [(N_v, 2) corners], image size) of the views with a board."""
    target = load_target(os.path.join(folder, "target.json"))
    pts = target.feature_points().astype(np.float32)
    cache = read_cache(folder)
    names, obj, img = [], [], []
    for name in sorted(cache):
        det = cache[name]
        if "no_board" in det:
            continue
        found = [i for i, c in enumerate(det["corners_px"]) if c is not None]
        names.append(name)
        obj.append(pts[found])
        img.append(np.array([det["corners_px"][i] for i in found], dtype=np.float32))
        size = tuple(det["image_size_px"])
    return names, obj, img, size


def opencv(obj, img, size, flags):
    K0 = np.array([[1000.0, 0, (size[0] - 1) / 2], [0, 1000.0, (size[1] - 1) / 2], [0, 0, 1]])
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    rms, K, dist, _, _ = cv2.calibrateCamera(obj, img, size, K0 if flags else None, None, flags=flags,
                                             criteria=crit)
    return rms, K, dist.ravel()


def opencv_held_out(obj, img, size, flags) -> float:
    V = len(obj)
    sq, n = 0.0, 0
    for k in range(FOLDS):
        train = [v for v in range(V) if v % FOLDS != k]
        _, K, dist = opencv([obj[v] for v in train], [img[v] for v in train], size, flags)
        for v in (v for v in range(V) if v % FOLDS == k):
            _, r, t = cv2.solvePnP(obj[v], img[v], K, dist, flags=cv2.SOLVEPNP_ITERATIVE)
            e = cv2.projectPoints(obj[v], r, t, K, dist)[0].reshape(-1, 2) - img[v]
            sq += float((e * e).sum())
            n += len(e)
    return math.sqrt(sq / n)


def ours(folder: str, set_name: str, tmp: str):
    cache = read_cache(folder)
    paths = []
    for name in sorted(cache):
        if "no_board" not in cache[name]:
            p = os.path.join(tmp, os.path.splitext(name)[0] + ".json")
            with open(p, "w", encoding="utf-8") as f:
                json.dump(cache[name], f)
            paths.append(p)
    out = os.path.join(tmp, "calib.json")
    err = io.StringIO()
    t0 = time.perf_counter()
    with contextlib.redirect_stderr(err):
        rc = cli.main(["calibrate", *paths, "--target", os.path.join(folder, "target.json"), "--pixel-pitch-mm",
                       str(PIXEL_PITCH_MM[set_name]), "-o", out])
    seconds = time.perf_counter() - t0
    if rc != 0:
        raise RuntimeError(f"{set_name}: tiltfit calibrate failed: {err.getvalue()}")
    with open(out, encoding="utf-8") as f:
        data = json.load(f)
    rc_export = cli.main(["export", out, "--to", "opencv", "-o", os.path.join(tmp, "cam.yml"), "-q"])
    return data, err.getvalue(), seconds, rc_export == 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sets", nargs="+", default=sorted(PIXEL_PITCH_MM))
    ap.add_argument("--out", default=os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "benchmarks", "results"))
    args = ap.parse_args(argv)
    say = lambda m: print(f"[bench_real_defaults] {m}", file=sys.stderr, flush=True)  # noqa: E731
    rows = []
    for s in args.sets:
        folder = os.path.join(REAL, s)
        names, obj, img, size = corners(folder)
        with tempfile.TemporaryDirectory() as tmp:
            data, log, seconds, exported = ours(folder, s, tmp)
        f_px = data["w_mm"] / data["pixel_pitch_mm"]
        row = {"set": s, "views": len(names), "corners": int(sum(len(c) for c in img)),
               "tiltfit": {"fx_px": f_px, "fy_px": f_px, "cx_px": data["principal_point_px"][0],
                           "cy_px": data["principal_point_px"][1], "rms_px": data["rms_reprojection_px"],
                           "held_out_rms_px": (data.get("held_out") or {}).get("rms_px"),
                           "distortion_model": data["distortion_model"],
                           "distortion": data["distortion"]["coefficients"][:5],
                           "principal_point": data["model_selection"].get("principal_point"),
                           "theta_F_test": data["model_selection"].get("theta_F"),
                           "selection": data["distortion_selection"], "warnings": data["warnings"],
                           "notes": data["notes"], "undetermined": data["undetermined"],
                           "U_mm": data["U_mm"], "d_mm": data["d_mm"], "exported": exported,
                           "wall_s": seconds}}
        for label, flags in (("opencv", 0), ("opencv_square", cv2.CALIB_FIX_ASPECT_RATIO)):
            rms, K, dist = opencv(obj, img, size, flags)
            row[label] = {"fx_px": K[0, 0], "fy_px": K[1, 1], "cx_px": K[0, 2], "cy_px": K[1, 2], "rms_px": rms,
                          "held_out_rms_px": opencv_held_out(obj, img, size, flags), "distortion": dist.tolist()}
        rows.append(row)
        say(f"{s}: ours f {f_px:.2f} px, RMS {row['tiltfit']['rms_px']:.4f}, held-out "
            f"{row['tiltfit']['held_out_rms_px']:.4f} ({data['distortion_model']}); OpenCV fx {row['opencv']['fx_px']:.2f}, "
            f"RMS {row['opencv']['rms_px']:.4f}, held-out {row['opencv']['held_out_rms_px']:.4f}")
    out = {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
           "machine": platform.platform(), "opencv": cv2.__version__, "folds": FOLDS, "sets": rows}
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "real_defaults.json"), "w", encoding="utf-8") as f:
        json.dump(out, f, indent=1)
        f.write("\n")
    lines = ["# `tiltfit calibrate` defaults against OpenCV on the shipped photos (same corners)", "",
             "Corners and blur widths: tiltfit's own detector (`tests/real_detections.py`). Ours: only the "
             "required flags (`--target`, `--pixel-pitch-mm`). OpenCV: `cv2.calibrateCamera` with its default flags "
             "(fx, fy, principal point free; k1 k2 p1 p2 k3), and with `CALIB_FIX_ASPECT_RATIO` (square pixels, "
             "our camera model). RMS per corner, OpenCV's definition sqrt(mean(dx² + dy²)); held-out: the same "
             f"{FOLDS} folds of views, lens from the other views, pose refitted. `{out['date']}`, OpenCV "
             f"{cv2.__version__}. Reproduce: `python benchmarks/calibration/bench_real_defaults.py`.", "",
             "| set | who | model | fx | fy | cx | cy | RMS px | held-out px |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        for label, who, model in (("tiltfit", "tiltfit defaults", r["tiltfit"]["distortion_model"]),
                                  ("opencv", "OpenCV defaults", "opencv5, fx ≠ fy"),
                                  ("opencv_square", "OpenCV FIX_ASPECT_RATIO", "opencv5, fx = fy")):
            x = r[label]
            lines.append(f"| {r['set']} ({r['views']} views) | {who} | {model} | {x['fx_px']:.2f} | {x['fy_px']:.2f} | "
                         f"{x['cx_px']:.1f} | {x['cy_px']:.1f} | {x['rms_px']:.4f} | {x['held_out_rms_px']:.4f} |")
    lines.append("")
    for r in rows:
        t = r["tiltfit"]
        o = r["opencv"]
        lines += [f"## {r['set']}", "",
                  f"- focal length {100 * (t['fx_px'] / o['fx_px'] - 1):+.2f} % against OpenCV's fx, "
                  f"{100 * (t['fy_px'] / o['fy_px'] - 1):+.2f} % against its fy; RMS {t['rms_px'] / o['rms_px']:.3f}× "
                  f"OpenCV's; held-out {t['held_out_rms_px'] / o['held_out_rms_px']:.3f}× OpenCV's.",
                  f"- principal point: {json.dumps({k: v for k, v in (t['principal_point'] or {}).items() if k in ('justified', 'fitted', 'lr_statistic')})}",
                  "- θF test: " + ("not run (the blur model does not describe the lens)" if not t["theta_F_test"] else
                                   f"justified {t['theta_F_test'].get('justified')}, θF {t['theta_F_test'].get('theta_F_deg_full', float('nan')):.2f}° "
                                   f"when freed (Λ = {t['theta_F_test'].get('lr_statistic', float('nan')):.3g})"),
                  f"- undetermined: {t['undetermined']}; U {t['U_mm']}, d {t['d_mm']}; `tiltfit export` accepts the "
                  f"file: {t['exported']}; wall time of the calibration {t['wall_s']:.0f} s (one run, shared machine).",
                  "- distortion auto (per model: fit RMS, held-out or why refused):"]
        for e in t["selection"]:
            why = (f"held-out {e['held_out_rms_px']:.4f} px" if "held_out_rms_px" in e else
                   f"refused: {e['refused']}" if "refused" in e else f"held-out not computed: {e.get('held_out_skipped')}")
            lines.append(f"  - {e['model']}" + (f" (board {e['board']})" if e.get("board") else "")
                         + f"{' **(chosen)**' if e.get('chosen') else ''}: "
                         + (f"RMS {e['rms_px']:.4f} px, " if "rms_px" in e else "") + why)
        lines += [f"- {n}" for n in t["notes"] + [f"warning: {w}" for w in t["warnings"]]] + [""]
    with open(os.path.join(args.out, "real_defaults.md"), "w", encoding="utf-8") as f:
        f.write("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
