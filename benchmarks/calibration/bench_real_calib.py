"""tiltfit against OpenCV's calibrateCamera on the shipped real photos (GoPro wide, 36 photos), same corners.

Corners: cv2.findChessboardCornersSB on data/real/gopro_wide/*.jpg (cached in corners_opencv.json beside
the photos), the same corners for both. Both fits: one focal length (OpenCV with CALIB_FIX_ASPECT_RATIO,
since ours has square pixels), free principal point, the same distortion terms per model:
none, k1, k1k2, opencv5 (k1 k2 p1 p2 k3), rational (k1..k6, p1, p2).

RMS is OpenCV's definition, sqrt(Σ |e|² / number of corners) (per corner, both coordinates together).
Held-out: 5-fold; the lens fitted on 4/5 of the views, the held-out views' poses fitted with the lens held.
Times: median of `--repeats` runs of each fit, on the same machine in the same run (ratio = ours / OpenCV).
Also OpenCV's default (fx ≠ fy) for reference.

Writes benchmarks/results/real_calib.{json,md}. Usage:
    python benchmarks/calibration/bench_real_calib.py [--repeats 5] [--out benchmarks/results]
"""
from __future__ import annotations

import argparse
import datetime
import glob
import json
import math
import os
import platform
import sys

import cv2
import numpy as np
import torch

from renderer.cameras.distortion import MODELS
from tiltfit.calibrate.fit import FitOptions
from tiltfit.calibrate.flow import calibrate
from tiltfit.calibrate.model import Observations
from tiltfit.detect.opencv import opencv_detections
from tiltfit.target.layout import load_target
from tiltfit.select.held_out import held_out_rms

sys.path.append(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))  # the repository root, last: a --base child's PYTHONPATH keeps its own tiltfit
from benchmarks.results_io import timed  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
DATA = os.path.join(ROOT, "data", "real", "gopro_wide")
PIXEL_PITCH_MM = 0.00155  # GoPro HERO sensor pitch at 1280×960 is not published; intrinsics in px don't depend on it

OPENCV_FLAGS = {
    "none": cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
    "k1": cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
    "k1k2": cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
    "opencv5": 0,
    "rational": cv2.CALIB_RATIONAL_MODEL,
}


def real_observations(folder: str = DATA, say=None) -> tuple[Observations, list, int]:
    """(observations of the photos with a board, names of those without, number of photos)."""
    target = load_target(os.path.join(folder, "target.json"))
    paths = sorted(glob.glob(os.path.join(folder, "*.jpg")))
    dets = opencv_detections(paths, target, cache=os.path.join(folder, "corners_opencv.json"), say=say)
    found = [(os.path.basename(p), d) for p, d in zip(paths, dets) if d]
    missing = [os.path.basename(p) for p, d in zip(paths, dets) if not d]
    corners = np.array([d["corners_px"] for _, d in found], dtype=np.float64)
    size = tuple(found[0][1]["image_size_px"])
    obs = Observations(target.feature_points(), corners, np.full(corners.shape[:2], np.nan), size, PIXEL_PITCH_MM,
                       [n for n, _ in found])
    return obs, missing, len(paths)


def opencv_calibrate(obs: Observations, model: str, fix_aspect: bool = True, views=None):
    """cv2.calibrateCamera on the observations (all corners present); returns (rms, K, dist, rvecs, tvecs)."""
    idx = range(obs.n_views) if views is None else views
    obj = [obs.points_mm.numpy().astype(np.float32) for _ in idx]
    img = [obs.corners_px[v].numpy().astype(np.float32) for v in idx]
    flags = OPENCV_FLAGS[model] | (cv2.CALIB_FIX_ASPECT_RATIO if fix_aspect else 0)
    K0 = np.eye(3)
    W, H = obs.image_size_px
    K0[0, 2], K0[1, 2] = (W - 1) / 2, (H - 1) / 2
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    rms, K, dist, rv, tv = cv2.calibrateCamera(obj, img, (W, H), K0, None, flags=flags, criteria=crit)
    return rms, K, dist.ravel(), rv, tv


def opencv_held_out(obs: Observations, model: str, folds: int = 5) -> float:
    """K-fold held-out RMS (OpenCV's per-corner definition) with OpenCV: calibrate on the rest, solvePnP."""
    V = obs.n_views
    sq, n = 0.0, 0
    for k in range(folds):
        test = [v for v in range(V) if v % folds == k]
        train = [v for v in range(V) if v % folds != k]
        _, K, dist, _, _ = opencv_calibrate(obs, model, views=train)
        for v in test:
            pts, uv = obs.points_mm.numpy(), obs.corners_px[v].numpy()
            ok, r, t = cv2.solvePnP(pts, uv, K, dist, flags=cv2.SOLVEPNP_ITERATIVE)
            proj, _ = cv2.projectPoints(pts, r, t, K, dist)
            e = proj.reshape(-1, 2) - uv
            sq += float((e * e).sum())
            n += len(e)
    return math.sqrt(sq / n)


def ours(obs: Observations, model: str):
    opts = FitOptions(distortion=model, free_principal_point=True, max_rms_px=None, model_selection=False)
    return calibrate(obs, "unified", options=opts)


def per_corner_rms(result) -> float:
    """OpenCV's RMS definition from our per-coordinate residual sum."""
    return math.sqrt(result.rss["corners"] / (result.rss["n_corners"] / 2))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", default=os.path.join(ROOT, "benchmarks", "results"))
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    say = lambda m: print(f"[bench_real_calib] {m}", file=sys.stderr, flush=True)  # noqa: E731
    obs, missing, n_photos = real_observations(say=say)
    say(f"{obs.n_views} of {n_photos} boards found by findChessboardCornersSB (missing: {', '.join(missing)})")
    ours(obs, "opencv5")  # warm-up: lazy imports
    rows = []
    for model in MODELS:
        (rms_cv, K, dist, _, _), t_cv = timed(lambda: opencv_calibrate(obs, model), args.repeats)[:2]
        res, t_ours = timed(lambda: ours(obs, model), args.repeats)[:2]
        cam = res.camera
        F = float(cam.focal_px.detach())
        sF = res.sigma["w_mm"] / obs.pixel_pitch_mm
        ho = held_out_rms(obs, FitOptions(free_principal_point=True), folds=5, distortion=model)
        ho_ours = ho["rms_px"]  # per corner, OpenCV's definition
        ho_cv = opencv_held_out(obs, model)
        rms_cv_default = opencv_calibrate(obs, model, fix_aspect=False)[0]
        row = {
            "model": model,
            "opencv": {"rms_px": rms_cv, "held_out_rms_px": ho_cv, "fx_px": K[0, 0], "fy_px": K[1, 1],
                       "cx_px": K[0, 2], "cy_px": K[1, 2], "distortion": dist.tolist(), "time_s": t_cv,
                       "rms_px_fx_ne_fy": rms_cv_default},
            "tiltfit": {"rms_px": per_corner_rms(res), "held_out_rms_px": ho_ours, "f_px": F, "sigma_f_px": sF,
                        "principal_point_px": res.values["principal_point_px"],
                        "sigma_principal_point_px": res.sigma["principal_point_px"],
                        "distortion": [float(v) for v in cam.distortion.detach()], "sigma_distortion": res.sigma["distortion"],
                        "time_s": t_ours, "iterations": res.iterations},
            "f_rel_diff": F / K[0, 0] - 1, "time_ratio": t_ours / t_cv,
        }
        rows.append(row)
        say(f"{model}: RMS ours {row['tiltfit']['rms_px']:.4f} / OpenCV {rms_cv:.4f} px; held-out "
            f"{ho_ours:.4f} / {ho_cv:.4f} px; f {F:.2f} ± {sF:.2f} / {K[0, 0]:.2f} px; time {t_ours:.3f} / "
            f"{t_cv:.3f} s")
    auto, t_auto = timed(lambda: calibrate(obs, "unified", options=FitOptions(
        distortion="auto", free_principal_point=True, model_selection=False)), args.repeats)[:2]
    out = {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
           "machine": platform.platform(), "torch_threads": torch.get_num_threads(), "opencv": cv2.__version__,
           "photos": n_photos, "boards_found": obs.n_views, "missing": missing, "repeats": args.repeats,
           "models": rows, "auto_choice": auto.distortion_model, "auto_time_s": t_auto,
           "auto_selection": auto.distortion_selection}
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "real_calib.json"), "w", encoding="utf-8") as f:
        json.dump(out, f, indent=1)
        f.write("\n")
    lines = [
        "# Real photos (GoPro wide, 8×6 corners): tiltfit vs cv2.calibrateCamera on the same corners",
        "",
        f"{obs.n_views} of {n_photos} boards found by cv2.findChessboardCornersSB; both fits with one focal "
        "length (OpenCV: CALIB_FIX_ASPECT_RATIO) and a free principal point. RMS per corner (OpenCV's "
        "definition); held-out: 5-fold, lens from the other views, pose refitted. Times: median of "
        f"{args.repeats}, same run, 1 torch thread. `{out['date']}`.",
        "",
        "| model | RMS ours | RMS OpenCV | held-out ours | held-out OpenCV | f ours (±σ) | f OpenCV | Δf | "
        "c ours (±σ) | c OpenCV | time ours | time OpenCV | ratio |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        o, c = r["tiltfit"], r["opencv"]
        pp, sp = o["principal_point_px"], o["sigma_principal_point_px"]
        lines.append(
            f"| {r['model']} | {o['rms_px']:.4f} | {c['rms_px']:.4f} | {o['held_out_rms_px']:.4f} | "
            f"{c['held_out_rms_px']:.4f} | {o['f_px']:.2f} ± {o['sigma_f_px']:.2f} | {c['fx_px']:.2f} | "
            f"{100 * r['f_rel_diff']:+.3f} % | ({pp[0]:.1f} ± {sp[0]:.1f}, {pp[1]:.1f} ± {sp[1]:.1f}) | "
            f"({c['cx_px']:.1f}, {c['cy_px']:.1f}) | {o['time_s']:.3f} s | {c['time_s']:.3f} s | "
            f"{r['time_ratio']:.1f}× |")
    lines += ["", f"`--distortion auto` chooses **{auto.distortion_model}** (all five candidate fits and tests: "
                  f"{t_auto:.2f} s):", ""]
    for e in auto.distortion_selection:
        lines.append(f"- {e['model']}: RMS {e.get('rms_px', float('nan')):.4f} px (per corner), "
                     + (f"held-out {e['held_out_rms_px']:.4f} px" if "held_out_rms_px" in e else
                        f"refused: {e['refused']}" if "refused" in e else
                        f"held-out not computed ({e.get('held_out_skipped')})")
                     + (" → chosen" if e.get("chosen") else ""))
    with open(os.path.join(args.out, "real_calib.md"), "w", encoding="utf-8") as f:
        f.write("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
