"""Corner-and-blur calibration against photometric refinement, accuracy against time, across blur levels.

Same ray-traced photographs for both methods (`tiltfit.synth.render_view(method="renderer")`: the general
tracer's thin lens, not either fit's model), a lens tilted by 4.65°, a 6 × 4 board of 50 mm cells at 1/16
of the EOS 6D (342 × 228), three views at 480–700 mm, sensor noise 0.003. The blur grows by focusing the
untilted lens farther (U0); at the last levels the blur disc reaches the projected square and no corner
detector finds the board.

- corners + blur: `tiltfit.detect` (corners and edge blur widths) then the joint fit (`calibrate(..., "joint")`).
- photometric: `tiltfit.photometric.refine_photometric`, started from the corner fit where there is one,
  else from a rough start (pose 0.1°/0.5 mm, w +0.3 %, U +1 %, d −3 %, θF +1°: a prior calibration's quality).

    python benchmarks/bench_photometric.py [--quick]

writes benchmarks/results/photometric.{md,json,png}.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from tiltfit import reproduce, synth  # noqa: E402
from tiltfit.detect import detect  # noqa: E402
from tiltfit.fit import FitError, FitOptions, calibrate  # noqa: E402
from tiltfit.model import Observations  # noqa: E402
from tiltfit.photometric import PhotometricOptions, refine_photometric  # noqa: E402
from tiltfit.target import Target  # noqa: E402

BOARD = Target(tuple(50.0 * i for i in range(7)), tuple(50.0 * j for j in range(5)), (0, 0), 25.0)
W_MM, D_MM, THETA_L_DEG, DOWNSCALE = 55.39, 40.0, 4.65, 16
VIEWS = (0, 1, 2)
RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results")


def captures(U0_mm: float, spp: int):
    w_px, h_px, _ = reproduce.EOS_6D.downscaled(DOWNSCALE)
    pitch = reproduce.EOS_6D.pixel_pitch_mm * DOWNSCALE
    cam = synth.tilted_lens_camera(W_MM, U0_mm, D_MM, THETA_L_DEG, pitch, w_px, h_px)
    U, theta_F = cam.U_mm, cam.theta_F_rad
    images, poses, blur, ratio = [], [], [], []
    for k, i in enumerate(VIEWS):
        R, T = reproduce.target_pose(BOARD, *reproduce.TARGET_VIEWS[i])
        view = synth.render_view(BOARD, cam, R, T, method="renderer", spp=spp, noise_sigma=0.003, seed=k)
        images.append(view.image[..., 0].astype(np.float64))
        poses.append((R, T))
        blur.append(view.truth.blur_px)
        ratio.append(float(np.median(view.truth.blur_px) / np.median(synth.projected_square_px(BOARD, cam, R, T))))
    truth = {"U_mm": U, "theta_F_deg": math.degrees(theta_F), "pitch": pitch, "size": (w_px, h_px),
             "blur_px": float(np.median(np.concatenate(blur))), "blur_over_square": float(np.median(ratio))}
    return images, poses, truth


def errors(values: dict, truth: dict) -> dict:
    return {"theta_L_err_deg": values["theta_L_deg"] - THETA_L_DEG,
            "U_err_pct": 100 * (values["U_mm"] / truth["U_mm"] - 1),
            "d_err_pct": 100 * (values["d_mm"] / D_MM - 1),
            "w_err_pct": 100 * (values["w_mm"] / W_MM - 1)}


def rough_start(poses, truth, seed=1):
    import cv2

    rng = np.random.default_rng(seed)
    return {"w_mm": W_MM * 1.003, "U_mm": truth["U_mm"] * 1.01, "d_mm": D_MM * 0.97,
            "theta_F_deg": truth["theta_F_deg"] + 1.0,
            "views": [{"R": cv2.Rodrigues(rng.normal(0, math.radians(0.1), 3))[0] @ R,
                       "T_mm": T + rng.normal(0, 0.5, 3)} for R, T in poses]}


def corner_fit(images, truth):
    t0 = time.perf_counter()
    dets = [detect(im, BOARD) for im in images]
    found = [int(d.found.sum()) for d in dets]
    if min(found) < 0.75 * BOARD.n_points:
        return None, time.perf_counter() - t0, found
    obs = Observations(BOARD.feature_points(), np.stack([d.corners_px for d in dets]),
                       np.stack([d.blur_px for d in dets]), truth["size"], truth["pitch"])
    try:
        res = calibrate(obs, "joint", options=FitOptions(model_selection=False, nominal_focal_mm=55.0))
    except FitError:
        return None, time.perf_counter() - t0, found
    return res, time.perf_counter() - t0, found


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="three blur levels, fewer samples")
    args = ap.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    levels = (700.0, 1000.0, 1400.0) if args.quick else (640.0, 700.0, 760.0, 1000.0, 1400.0)
    spp = 32 if args.quick else 64
    rows = []
    for U0 in levels:
        images, poses, truth = captures(U0, spp)
        tag = f"U0 {U0:.0f} mm: blur {truth['blur_px']:.1f} px, blur/square {truth['blur_over_square']:.2f}"
        res, t_corner, found = corner_fit(images, truth)
        base = {"U0_mm": U0, "blur_px": truth["blur_px"], "blur_over_square": truth["blur_over_square"],
                "corners_found": found}
        if res is not None:
            rows.append({**base, "method": "corners + blur", "seconds": t_corner, **errors(res.values, truth),
                         "sigma_theta_L_deg": res.sigma.get("theta_L_deg")})
            start = {**{k: res.values[k] for k in ("w_mm", "U_mm", "d_mm", "theta_F_deg", "principal_point_px")},
                     "views": [{"R": v["R"], "T_mm": v["T_mm"]} for v in res.views]}
            start_name = "corner fit"
        else:
            start, start_name = rough_start(poses, truth), "rough start"
        n_samples = 64
        t0 = time.perf_counter()
        ph = refine_photometric(images, BOARD, start, truth["pitch"],
                                PhotometricOptions(lens_samples=n_samples, max_pixels=1500))
        t_ph = time.perf_counter() - t0
        rows.append({**base, "method": f"photometric (from {start_name})", "seconds": t_ph + (t_corner if res else 0.0),
                     "photometric_seconds": t_ph, **errors(ph.values, truth),
                     "sigma_theta_L_deg": ph.sigma["theta_L_deg"], "rms": ph.rms})
        print(f"{tag}; corners {found}: " + "; ".join(
            f"{r['method']}: θL {r['theta_L_err_deg']:+.4f}°, U {r['U_err_pct']:+.3f} %, d {r['d_err_pct']:+.3f} %, "
            f"{r['seconds']:.1f} s" for r in rows if r["U0_mm"] == U0), flush=True)
    os.makedirs(RESULTS, exist_ok=True)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    meta = {"board": "6 x 4 cells of 50 mm", "views": VIEWS, "spp": spp, "downscale": DOWNSCALE,
            "true": {"w_mm": W_MM, "d_mm": D_MM, "theta_L_deg": THETA_L_DEG}, "load_average": load,
            "quick": args.quick}
    with open(os.path.join(RESULTS, "photometric.json"), "w", encoding="utf-8") as f:
        json.dump({"meta": meta, "rows": rows}, f, indent=1)
    lines = ["# Corner-and-blur fit vs photometric refinement (same ray-traced photographs, same run)\n",
             f"{meta['board']} board, 3 views, 342 x 228, lens tilted {THETA_L_DEG}°, d {D_MM} mm, {spp} spp captures, "
             f"load average {load:.1f} at the end. `python benchmarks/bench_photometric.py`.\n",
             "| U0 mm | blur px | blur / square | corners found | method | θL error ° | σ θL ° | U error % | "
             "d error % | w error % | seconds |", "|" + "---|" * 11]
    for r in rows:
        sg = r.get("sigma_theta_L_deg")
        lines.append(f"| {r['U0_mm']:.0f} | {r['blur_px']:.1f} | {r['blur_over_square']:.2f} | "
                     f"{'/'.join(map(str, r['corners_found']))} | {r['method']} | {r['theta_L_err_deg']:+.4f} | "
                     f"{'' if sg is None else f'{sg:.4f}'} | {r['U_err_pct']:+.3f} | {r['d_err_pct']:+.3f} | "
                     f"{r['w_err_pct']:+.3f} | {r['seconds']:.1f} |")
    lines.append("\nPhotometric seconds include the corner fit it starts from where there is one. Where no "
                 "corners are found the photometric fit starts from a rough prior calibration instead.")
    with open(os.path.join(RESULTS, "photometric.md"), "w", encoding="utf-8") as f:
        f.write("\n".join(lines) + "\n")
    plot(rows, os.path.join(RESULTS, "photometric.png"))
    print("\n".join(lines))
    return 0


def plot(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for method, marker in (("corners + blur", "o"), ("photometric", "s")):
        sel = [r for r in rows if r["method"].startswith(method)]
        if not sel:
            continue
        axes[0].plot([r["seconds"] for r in sel], [abs(r["theta_L_err_deg"]) for r in sel], marker=marker,
                     label=method)
        for r in sel:
            axes[0].annotate(f"{r['blur_px']:.0f} px", (r["seconds"], abs(r["theta_L_err_deg"])), fontsize=7)
        axes[1].plot([r["blur_px"] for r in sel], [abs(r["d_err_pct"]) for r in sel], marker=marker, label=method)
    axes[0].set(xscale="log", yscale="log", xlabel="time, s (one thread)", ylabel="|θL error|, degrees",
                title="accuracy against time (labels: blur)")
    axes[1].set(yscale="log", xlabel="median blur disc, px", ylabel="|d error|, %", title="aperture error against blur")
    for ax in axes:
        ax.legend()
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    sys.exit(main())
