"""Why stage 1's d missed by many σ on rendered captures, and what the blur-offset parameter does about it.

Captures: the θL = 0 views of `bench_calib_opencv` (analytic renderer, exact blur spot, shot + read noise,
vignetting, 8-bit sRGB), 1/`--downscale` of the EOS 6D; corners and blur from `tiltfit.detect.chessboard` against the
truth of `tiltfit.experiments.synth`. Reports the blur detector's error (mean = bias, std = scatter, against the σ it
reports) by blur size, then stage 1 (unified) with the blur offset held at 0 (the old fit) and free (now),
as z = (estimate − truth) / σ for w, U, d.

Writes benchmarks/results/blur_bias.{json,md}. Usage:
    python benchmarks/history/bench_blur_bias.py [--downscale 4] [--out benchmarks/results]
"""
from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from benchmarks.calibration.bench_calib_opencv import CAMERA, TARGET, capture  # noqa: E402

from tiltfit.detect.chessboard import detect  # noqa: E402
from tiltfit.calibrate.fit import FitOptions  # noqa: E402
from tiltfit.calibrate.flow import calibrate  # noqa: E402
from tiltfit.calibrate.model import Observations  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--downscale", type=int, default=4)
    ap.add_argument("--views", type=int, default=5)
    ap.add_argument("--out", default=os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "benchmarks", "results"))
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    C, B, S, TB, TC = [], [], [], [], []
    for v in range(args.views):
        img, truth, cam = capture(0.0, v, args.downscale, seed=100 + v)
        det = detect(img, TARGET)
        C.append(det.corners_px)
        B.append(det.blur_px)
        S.append(det.blur_sigma_px)
        TB.append(np.asarray(truth.blur_px))
        TC.append(np.asarray(truth.corners_px))
        print(f"[bench_blur_bias] view {v} detected", file=sys.stderr, flush=True)
    C, B, S, TB, TC = map(np.array, (C, B, S, TB, TC))
    corner_rms = float(np.sqrt(np.nanmean((C - TC) ** 2)))
    err = B - TB
    ok = np.isfinite(err)
    bins = []
    for lo, hi in ((0, 2), (2, 4), (4, 8), (8, 16), (16, 1000)):
        m = ok & (TB >= lo) & (TB < hi)
        if m.any():
            bins.append({"blur_px": [lo, hi], "n": int(m.sum()), "mean_error_px": float(err[m].mean()),
                         "std_error_px": float(err[m].std()), "median_reported_sigma_px": float(np.median(S[m]))})
    obs = Observations(TARGET.feature_points(), C, B, cam.sensor.size_px, cam.sensor.pixel_pitch)
    truth = {"w_mm": CAMERA.untilted.w, "U_mm": cam.U, "d_mm": CAMERA.untilted.d}
    fits = {}
    for label, offset in (("offset held at 0 (before)", False), ("offset free (now)", True)):
        res = calibrate(obs, "unified", options=FitOptions(model_selection=False, blur_offset=offset))
        fits[label] = {k: {"value": res.values[k], "sigma": res.sigma[k],
                           "z": (res.values[k] - t) / res.sigma[k]} for k, t in truth.items()}
        fits[label]["blur_offset_px"] = {"value": res.values.get("blur_offset_px"),
                                         "sigma": res.sigma.get("blur_offset_px")}
        fits[label]["sigma_corner_px"] = res.noise["sigma_corner_px"]
    out = {"downscale": args.downscale, "views": args.views, "blur_error_by_size": bins,
           "blur_error_mean_px": float(err[ok].mean()), "blur_error_std_px": float(err[ok].std()),
           "z_rms_of_reported_sigma": float(np.sqrt(np.mean((err[ok] / S[ok]) ** 2))), "truth": truth,
           "corner_error_rms_px": corner_rms,
           "fits": fits}
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "blur_bias.json"), "w", encoding="utf-8") as f:
        json.dump(out, f, indent=1)
        f.write("\n")
    lines = ["# Stage 1 on rendered captures: the blur detector's bias and the blur-offset parameter", "",
             f"θL = 0 captures of `bench_calib_opencv` at 1/{args.downscale} resolution, {args.views} views. "
             f"Blur error (detected − truth) mean {out['blur_error_mean_px']:+.4f} px, std "
             f"{out['blur_error_std_px']:.4f} px; RMS of error / reported σ = {out['z_rms_of_reported_sigma']:.2f}.",
             "", "| true blur (px) | n | mean error (px) | std (px) | reported σ (px) |", "|---|---|---|---|---|"]
    for b in bins:
        lines.append(f"| {b['blur_px'][0]}–{b['blur_px'][1]} | {b['n']} | {b['mean_error_px']:+.4f} | "
                     f"{b['std_error_px']:.4f} | {b['median_reported_sigma_px']:.4f} |")
    lines += ["", "| fit | w z | U z | d z | blur offset (px) | fitted σ_corner (px) |", "|---|---|---|---|---|---|"]
    for label, f in fits.items():
        bo = f["blur_offset_px"]
        lines.append(f"| {label} | {f['w_mm']['z']:+.1f} | {f['U_mm']['z']:+.1f} | {f['d_mm']['z']:+.1f} | "
                     + ("held 0" if not bo["sigma"] else f"{bo['value']:+.4f} ± {bo['sigma']:.4f}")
                     + f" | {f['sigma_corner_px']:.4f} |")
    lines += ["", f"Corner error (detected − truth) RMS per coordinate: {corner_rms:.4f} px, against the "
              "σ_corner the fit infers from its residuals: the corner errors are mostly systematic per view "
              f"(absorbed by the poses), which is what still pulls w and U by "
              f"{fits['offset free (now)']['w_mm']['z']:+.1f}σ and {fits['offset free (now)']['U_mm']['z']:+.1f}σ."]
    with open(os.path.join(args.out, "blur_bias.md"), "w", encoding="utf-8") as f:
        f.write("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
