"""Board detection on the shipped real photographs (data/real/gopro_wide, 36 GoPro wide-angle JPEGs of an
8 × 6-corner board) against OpenCV, in the same run on the same files.

Peers:
- `ours`: tiltfit.detect.chessboard.detect (corners only, measure_blur=False, like the OpenCV peers) on the image decoded
  to linear by camio.files.read_image; its blur measurement is timed separately (`ours_blur_s`).
- `sb`: cv2.findChessboardCornersSB (NORMALIZE_IMAGE | EXHAUSTIVE | ACCURACY) + cv2.cornerSubPix (5 × 5) on the
  8-bit grey image (cv2.imread).
- `classic`: cv2.findChessboardCorners (ADAPTIVE_THRESH | NORMALIZE_IMAGE) + cv2.cornerSubPix (11 × 11).
Time per image: the median over `--repeats` runs of each method on that image (file decoding excluded); the
table gives the median over the images and the ratio ours / peer of those medians.
Corner agreement: distance between our corners and a peer's on the views both find, after matching the
labelling (the board looks the same turned by 180°: the peer's order as is, or reversed, whichever fits);
`labelling_same` counts the views where the peer's labelling already equals ours.

Writes benchmarks/results/real_detect.{json,md}. Usage:
    python benchmarks/detection/bench_real_detect.py [--repeats 3 | --quick] [--out benchmarks/results]
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import platform
import statistics
import sys
import time

import cv2
import numpy as np
import torch

from camio.files import read_image
from tiltfit.detect.blur import measure_blur
from tiltfit.detect.chessboard import detect, to_gray
from tiltfit.detect.imaging import build_pyramid
from tiltfit.detect.opencv import match_labelling, sb_corners
from tiltfit.target.layout import load_target

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))  # the repository root: benchmarks.results_io
from benchmarks.results_io import timed  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
DATA = os.path.join(ROOT, "data", "real", "gopro_wide")
PATTERN = (8, 6)


def opencv_sb(gray8):
    return sb_corners(gray8, PATTERN)


def opencv_classic(gray8):
    ok, c = cv2.findChessboardCorners(gray8, PATTERN, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
    if not ok:
        return None
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 1e-3)
    return cv2.cornerSubPix(gray8, c, (11, 11), (-1, -1), crit).reshape(-1, 2).astype(np.float64)


def agreement(ours, theirs):
    """(distances on our found corners after matching the labelling, whether the labelling was the same)."""
    e, is_same = match_labelling(ours, theirs)
    return e[np.isfinite(e)], is_same


def stats(e):
    e = np.asarray(e)
    if e.size == 0:
        return {}
    return {"n_corners": int(e.size), "median_px": round(float(np.median(e)), 4),
            "p95_px": round(float(np.percentile(e, 95)), 4), "max_px": round(float(e.max()), 4)}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="one run per image (--repeats 1)")
    ap.add_argument("--out", default=os.path.join(ROOT, "benchmarks", "results"))
    args = ap.parse_args(argv)
    if args.quick:
        args.repeats = 1
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    target = load_target(os.path.join(DATA, "target.json"))
    paths = sorted(glob.glob(os.path.join(DATA, "*.jpg")))
    rows, errs = [], {"sb": [], "classic": [], "sb_vs_classic": []}
    for path in paths:
        linear = read_image(path)
        gray8 = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
        det, t_ours = timed(lambda: detect(linear, target, measure_blur=False), args.repeats)[:2]
        sb, t_sb = timed(lambda: opencv_sb(gray8), args.repeats)[:2]
        cl, t_cl = timed(lambda: opencv_classic(gray8), args.repeats)[:2]
        row = {"image": os.path.basename(path), "ours_found": bool(det.grid_found),
               "ours_corners": int(det.found.sum()), "sb_found": sb is not None, "classic_found": cl is not None,
               "ours_s": round(t_ours, 4), "sb_s": round(t_sb, 4), "classic_s": round(t_cl, 4)}
        if det.grid_found:
            g = to_gray(linear)
            t0 = time.perf_counter()
            measure_blur(g, target, det.corners_px, levels=build_pyramid(g))
            row["ours_blur_s"] = round(time.perf_counter() - t0, 4)
        for name, peer in (("sb", sb), ("classic", cl)):
            if det.grid_found and peer is not None:
                e, same = agreement(det.corners_px, peer)
                errs[name].append(e)
                row[f"{name}_median_px"] = round(float(np.median(e)), 4)
                row[f"{name}_max_px"] = round(float(e.max()), 4)
                row[f"{name}_labelling_same"] = same
        if sb is not None and cl is not None:
            e, _ = agreement(sb, cl)
            errs["sb_vs_classic"].append(e)
        rows.append(row)
        print(f"{row['image']}: ours {row['ours_corners']} corners {t_ours:.3f} s, SB {row['sb_found']} "
              f"{t_sb:.3f} s, classic {row['classic_found']} {t_cl:.3f} s", flush=True)

    def med(key, cond):
        v = [r[key] for r in rows if cond(r)]
        return round(statistics.median(v), 4) if v else None

    summary = {
        "images": len(rows),
        "found": {"ours": sum(r["ours_found"] for r in rows), "sb": sum(r["sb_found"] for r in rows),
                  "classic": sum(r["classic_found"] for r in rows)},
        "ours_corners_total": sum(r["ours_corners"] for r in rows),
        "time_median_s": {"ours": med("ours_s", lambda r: True), "sb": med("sb_s", lambda r: True),
                          "classic": med("classic_s", lambda r: True),
                          "ours_blur": med("ours_blur_s", lambda r: "ours_blur_s" in r)},
        "agreement": {k: stats(np.concatenate(v)) if v else {} for k, v in errs.items()},
        "labelling_same_as_ours": {k: sum(bool(r.get(f"{k}_labelling_same")) for r in rows) for k in ("sb", "classic")},
        "views_both": {k: sum(f"{k}_median_px" in r for r in rows) for k in ("sb", "classic")},
    }
    t = summary["time_median_s"]
    summary["time_ratio_ours_over"] = {k: round(t["ours"] / t[k], 3) for k in ("sb", "classic")}
    result = {"summary": summary, "rows": rows, "repeats": args.repeats,
              "machine": {"platform": platform.platform(), "python": platform.python_version(),
                          "torch": torch.__version__, "opencv": cv2.__version__, "threads": 1,
                          "cpu_count": os.cpu_count()}}
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "real_detect.json"), "w") as f:
        json.dump(result, f, indent=1)
    a = summary["agreement"]
    md = [f"# Detection on the shipped real photos ({len(rows)} GoPro images, 8 × 6 corners) against OpenCV",
          "",
          "`python benchmarks/detection/bench_real_detect.py` (1 thread each; time = median over images of the median of "
          f"{args.repeats} runs; file decoding excluded)",
          "",
          "| method | boards found | corners | time / image (median) | ours / peer time |",
          "|---|---|---|---|---|",
          f"| ours (`tiltfit.detect.chessboard`, corners) | {summary['found']['ours']} / {len(rows)} | "
          f"{summary['ours_corners_total']} | {t['ours']:.3f} s | 1 |",
          f"| OpenCV `findChessboardCornersSB` + `cornerSubPix` | {summary['found']['sb']} / {len(rows)} | "
          f"{48 * summary['found']['sb']} | {t['sb']:.3f} s | {summary['time_ratio_ours_over']['sb']} |",
          f"| OpenCV `findChessboardCorners` + `cornerSubPix` | {summary['found']['classic']} / {len(rows)} | "
          f"{48 * summary['found']['classic']} | {t['classic']:.3f} s | {summary['time_ratio_ours_over']['classic']} |",
          "",
          f"Our blur measurement (not done by OpenCV) adds {t['ours_blur']} s per image (median).",
          "",
          "| corner agreement (views both find, labelling matched) | views | corners | median | 95 % | max |",
          "|---|---|---|---|---|---|"]
    for k, label in (("sb", "ours vs SB + cornerSubPix"), ("classic", "ours vs classic + cornerSubPix"),
                     ("sb_vs_classic", "SB vs classic (OpenCV against itself)")):
        s = a[k]
        views = summary["views_both"].get(k, len(errs[k]))
        if s:
            md.append(f"| {label} | {views} | {s['n_corners']} | {s['median_px']} px | {s['p95_px']} px | "
                      f"{s['max_px']} px |")
    md += ["", f"Labelling: the board looks the same turned by 180°; ours puts corner 0 nearer the image's top-left. "
               f"SB's labelling equals ours on {summary['labelling_same_as_ours']['sb']} of "
               f"{summary['views_both']['sb']} views, the classic detector's on "
               f"{summary['labelling_same_as_ours']['classic']} of {summary['views_both']['classic']}.", ""]
    with open(os.path.join(args.out, "real_detect.md"), "w") as f:
        f.write("\n".join(md))
    print("\n".join(md))


if __name__ == "__main__":
    main()
