"""The fitted board on small boards and its σ (issue 33 §5): our defaults (`board auto`, `distortion auto`) against
OpenCV's calibrateCameraExtended on the same corners, in one run, on disjoint subsets of real sets.

    python benchmarks/calibration/bench_small_boards.py [--sets sony_small,industrial_ds1,gopro_wide] [--out benchmarks/results/small_boards]

Sets and splits (views dealt round-robin, so every subset spans the session):
    sony_small      13 views of a 4×6-corner board (640×480; /work/shared/data/real/sony_small, detections cached in
                    benchmarks/small_sets/sony_small): all, halves.
    industrial_ds1  20 views of 16×10 corners: all, halves, quarters.
    gopro_wide      36 views: thirds (slow: a free board of 54 points over 12 views with rational5).
    charuco_webcam4 4 frames of an inverted ChArUco board (12 corners each, published detections): all (issue 33 §5:
                    a free board gave f = 396 ± 43 px on such a set).
For each subset: f, cx, cy with σ (ours: the reported σ, which holds the spread over the models the automatic choices
could not tell apart, recorded apart as `model_choice`; OpenCV: stdDeviationsIntrinsics), and our choices (board,
distortion). Between the subsets of one split: the spread of each quantity (max − min) and spread/σ pooled over
the pairs, sqrt(mean over pairs (a, b) of Δ² / (σ_a² + σ_b²)) (1 is honest; far above: σ too small; far below: σ
too large). OpenCV fits fx and fy apart, its five distortion terms and the principal point (flags 0).
"""
from __future__ import annotations

import argparse
import itertools
import math
import os
import sys
import time

import cv2
import numpy as np

HERE = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))  # benchmarks/
sys.path.insert(0, os.path.dirname(HERE))
from tests.real_detections import REAL, observations  # noqa: E402
from benchmarks.results_io import save, write_lines  # noqa: E402

from tiltfit.calibrate.flow import calibrate  # noqa: E402
from tiltfit.calibrate.fit import FitOptions  # noqa: E402

SETS = {  # folder with target.json and the detection cache, pixel pitch (mm; sets only w_mm, not f in pixels), splits
    "sony_small": (os.path.join(HERE, "small_sets", "sony_small"), 0.0096, (1, 2)),
    "industrial_ds1": (os.path.join(REAL, "industrial_ds1"), 0.0048, (1, 2, 4)),
    "gopro_wide": (os.path.join(REAL, "gopro_wide"), 0.00155, (3,)),
    # 4 frames of the inverted ChArUco webcam stream, caliscope's published corners (12 a frame; 48 for the free
    # board's 29 parameters): tests/data/charuco_webcam/published_corners_4views.csv; pitch arbitrary (f in px).
    "charuco_webcam4": (os.path.join(os.path.dirname(HERE), "tests", "data", "charuco_webcam"), 0.003, (1,)),
}
KEYS = ("f_px", "cx_px", "cy_px")


def ours(obs) -> dict:
    """Our defaults (the CLI's: unified fit, distortion auto, board auto)."""
    t = time.perf_counter()
    r = calibrate(obs, "unified", options=FitOptions(distortion="auto", board="auto"))
    p = obs.pixel_pitch_mm
    v, s = r.values, r.sigma
    return {"f_px": v["w_mm"] / p, "cx_px": v["principal_point_px"][0], "cy_px": v["principal_point_px"][1],
            "sigma": {"f_px": s["w_mm"] / p, "cx_px": s["principal_point_px"][0], "cy_px": s["principal_point_px"][1]},
            "board": r.board.model if r.board is not None else "flat", "distortion": r.distortion_model,
            "board_choice": [{k: e[k] for k in ("model", "held_out_rms_px", "gain_z", "sigma_ratio", "not_chosen",
                                                 "chosen") if k in e} for e in r.board_selection],
            "model_choice": (r.sigma_model or {}).get("model_choice"),
            "seconds": time.perf_counter() - t}


def opencv(obs) -> dict:
    """cv2.calibrateCameraExtended on the same corners (each view's found corners), flags 0."""
    P = obs.points_mm.numpy().astype(np.float32)
    img, objs = [], []
    for v in range(obs.n_views):
        m = obs.corner_mask[v].numpy()
        objs.append(P[m])
        img.append(obs.corners_px[v].numpy()[m].astype(np.float32))
    W, H = obs.image_size_px
    t = time.perf_counter()
    rms, K, D, _, _, std, _, _ = cv2.calibrateCameraExtended(objs, img, (int(W), int(H)), None, None)
    std = std.ravel()
    return {"f_px": 0.5 * (K[0, 0] + K[1, 1]), "cx_px": K[0, 2], "cy_px": K[1, 2], "rms_px": rms,
            "sigma": {"f_px": 0.5 * (std[0] + std[1]), "cx_px": std[2], "cy_px": std[3]},
            "seconds": time.perf_counter() - t}


def spread(results: list) -> dict:
    """Per quantity: max − min over the subsets and spread/σ pooled over the pairs."""
    out = {}
    for k in KEYS:
        vals = [r[k] for r in results]
        z2 = [(a[k] - b[k]) ** 2 / max(a["sigma"][k] ** 2 + b["sigma"][k] ** 2, 1e-300)
              for a, b in itertools.combinations(results, 2)]
        out[k] = {"spread": max(vals) - min(vals), "spread_over_sigma": math.sqrt(sum(z2) / len(z2)) if z2 else None}
    return out


def charuco_four_views(folder: str, pitch: float):
    """Observations of the 4-view ChArUco case: 3×4 inner corners of 54 mm squares, corner id k at column k % 3,
    row k // 3 (OpenCV's ChArUco ids), the published corners in the 1280×720 frame."""
    import csv

    from tiltfit.calibrate.model import Observations

    rows = list(csv.DictReader(open(os.path.join(folder, "published_corners_4views.csv"))))
    frames = sorted({int(r["frame"]) for r in rows})
    pts = np.array([[(k % 3 + 1) * 54.0, (k // 3 + 1) * 54.0, 0.0] for k in range(12)])
    uv = np.full((len(frames), 12, 2), np.nan)
    for r in rows:
        uv[frames.index(int(r["frame"])), int(r["corner_id"])] = float(r["x_px"]), float(r["y_px"])
    return Observations(pts, uv, np.full(uv.shape[:2], np.nan), (1280, 720), pitch, [f"frame_{f}" for f in frames])


def run(sets) -> dict:
    out = {}
    for name in sets:
        folder, pitch, splits = SETS[name]
        obs = charuco_four_views(folder, pitch) if name == "charuco_webcam4" else observations(folder, pitch)[0]
        out[name] = {}
        for n in splits:
            subs = [obs if n == 1 else obs.subset([v for v in range(obs.n_views) if v % n == k]) for k in range(n)]
            entry = {"n_views": [s.n_views for s in subs], "ours": [ours(s) for s in subs],
                     "opencv": [opencv(s) for s in subs]}
            if n > 1:
                entry["spread"] = {tool: spread(entry[tool]) for tool in ("ours", "opencv")}
            out[name][{1: "all", 2: "halves", 3: "thirds", 4: "quarters"}[n]] = entry
            print(f"[{name}] {n} subsets done", file=sys.stderr, flush=True)
    return out


def lines(res: dict) -> list[str]:
    out = ["# Small boards and the fitted board's σ (bench_small_boards.py)", "",
           "Ours: defaults (board auto, distortion auto); OpenCV: calibrateCameraExtended (flags 0) on the same "
           "corners. f, cx, cy in px with 1σ. Spread/σ pooled over the pairs of subsets (1 is honest).", ""]
    for name, splits in res.items():
        for split, e in splits.items():
            out += [f"## {name}: {split} ({'+'.join(str(n) for n in e['n_views'])} views)", "",
                    "| subset | tool | f | cx | cy | board | distortion |", "|---|---|---|---|---|---|---|"]
            for i, (a, b) in enumerate(zip(e["ours"], e["opencv"])):
                for tool, r in (("ours", a), ("OpenCV", b)):
                    f = " | ".join(f"{r[k]:.1f} ± {r['sigma'][k]:.2f}" for k in KEYS)
                    out.append(f"| {i} | {tool} | {f} | {r.get('board', '')} | {r.get('distortion', 'opencv5')} |")
            if "spread" in e:
                out += ["", "| tool | spread f, cx, cy (px) | spread/σ f, cx, cy |", "|---|---|---|"]
                for tool in ("ours", "opencv"):
                    s = e["spread"][tool]
                    out.append(f"| {tool} | " + ", ".join(f"{s[k]['spread']:.2f}" for k in KEYS) + " | "
                               + ", ".join(f"{s[k]['spread_over_sigma']:.2f}" for k in KEYS) + " |")
            out.append("")
    pooled = {}
    for tool in ("ours", "opencv"):
        z = [e["spread"][tool][k]["spread_over_sigma"] for splits in res.values() for e in splits.values()
             if "spread" in e for k in ("cx_px", "cy_px")]
        pooled[tool] = math.sqrt(sum(x * x for x in z) / len(z)) if z else None
    out += ["## Pooled over every split, principal point (cx, cy)", "",
            f"spread/σ: ours {pooled['ours']:.2f}, OpenCV {pooled['opencv']:.2f}" if pooled["ours"] else "", ""]
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sets", default="sony_small,industrial_ds1")
    ap.add_argument("--out", default=os.path.join(HERE, "results", "small_boards"))
    args = ap.parse_args(argv)
    save(args.out, run(args.sets.split(",")), lambda path, res: write_lines(path, lines(res)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
