"""Where the photometric fit's error comes from at heavy blur: controlled experiments, seed by seed.

One blur level (U0 = 1000 mm: discs of 18 px, half the projected square, at 1/16 of the EOS 6D, 342 × 228),
a lens tilted by 4.65°, the 6 × 4 board of 50 mm cells, three views (`reproduce.TARGET_VIEWS` 0–2), 1000
pixels per view, started from the truth perturbed like a corner fit (pose 0.1°/0.5 mm, w +0.3 %, U +1 %,
d −3 %, θL +0.1°). What changes from one group to the next:

- own model: captures rendered by the fit's own target model (`render_target`, 256 or 64 fixed lens samples)
  plus Gaussian noise 0.003; with the fit's own 64 samples and no noise the fit must return the truth exactly,
  with 256 samples the difference is the fit's lens-sample coarseness alone;
- ray traced at 64 or 512 spp (`synth.render_view(method="renderer")`, sensor noise 0.003): render noise;
- the fit's lens samples, 64 or 192.

z = error / σ with σ the fit's own (cluster-robust sandwich; the textbook Gauss–Newton σ beside it).

    python benchmarks/history/diag_photometric.py [--workers N]

writes benchmarks/results/photometric_diagnosis.{md,json}. Runs about 25 min on one core.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))

from benchmarks.photometric.bench_photometric import BOARD, D_MM, W_MM, rough_start  # noqa: E402
from renderer import Lens, Sensor
from renderer.cameras import optics  # noqa: E402
from renderer.cameras import EOS_6D  # noqa: E402
from tiltfit.experiments import synth  # noqa: E402
from tiltfit.experiments import reproduce  # noqa: E402
from tiltfit import photometric as P  # noqa: E402
from tiltfit.files.calib import camera_from_calib  # noqa: E402

RESULTS = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "benchmarks", "results")
THETA_L_DEG, U0_MM, DOWNSCALE, VIEWS = 4.65, 1000.0, 16, (0, 1, 2)
#: (group, capture method, spp or model samples, capture noise, fit lens samples, seeds)
GROUPS = (("own model, 64 samples, no noise", "model", 64, 0.0, 64, (0,)),
          ("own model, 256 samples", "model", 256, 0.003, 64, (0, 1, 2)),
          ("ray traced, 64 spp", "renderer", 64, 0.003, 64, (0, 1, 2)),
          ("ray traced, 512 spp", "renderer", 512, 0.003, 64, (0, 1, 2)),
          ("ray traced, 512 spp, 192 lens samples", "renderer", 512, 0.003, 192, (0, 1)))


def captures(method: str, samples: int, noise: float, seed: int):
    """Three views of the board: (images, poses, truth)."""
    import torch

    w_px, h_px = EOS_6D.binned(DOWNSCALE).size_px
    pitch = EOS_6D.pixel_pitch * DOWNSCALE
    cam = Lens.from_tilt(W_MM, float(optics.focal_length(W_MM, U0_MM)), math.radians(THETA_L_DEG), D_MM, sensor=Sensor(w_px, h_px, pitch))
    images, poses = [], []
    for k, i in enumerate(VIEWS):
        R, T = reproduce.target_pose(BOARD, *reproduce.TARGET_VIEWS[i])
        if method == "model":
            yy, xx = np.mgrid[0:h_px, 0:w_px]
            uv = torch.tensor(np.stack([xx.ravel(), yy.ravel()], -1), dtype=torch.float64)
            view_cam = camera_from_calib({"image_size_px": (w_px, h_px), "pixel_pitch_mm": pitch, "w_mm": W_MM,
                                          "U_mm": cam.U, "d_mm": D_MM, "theta_F_deg": math.degrees(cam.theta_F),
                                          "views": [{"R": R, "T_mm": T}]}).view_camera(0)
            lens = P.hammersley_disc_samples(samples)
            with torch.no_grad():
                img = torch.cat([P.render_target(BOARD, view_cam, uv[a:a + 4096], lens, 0.8, 0.05, 0.0)
                                 for a in range(0, uv.shape[0], 4096)]).numpy().reshape(h_px, w_px)
            images.append(img + np.random.default_rng(1000 * seed + k).normal(0, noise, img.shape))
        else:
            view = synth.render_view(BOARD, cam, R, T, method="renderer", spp=samples, noise_sigma=noise,
                                     seed=1000 * seed + k)
            images.append(view.image[..., 0].astype(np.float64))
        poses.append((R, T))
    truth = {"U_mm": cam.U, "theta_L_deg": THETA_L_DEG, "d_mm": D_MM}
    return images, poses, truth, pitch


def run(job: dict) -> dict:
    import torch

    torch.set_num_threads(1)
    images, poses, truth, pitch = captures(job["method"], job["samples"], job["noise"], job["seed"])
    start = rough_start(poses, truth, seed=job["seed"] + 1)
    h, w = images[0].shape
    camera = camera_from_calib({**start, "image_size_px": (w, h), "pixel_pitch_mm": pitch})
    res = P.refine_photometric(images, BOARD, camera,
                               P.PhotometricOptions(lens_samples=job["lens_samples"], max_pixels=1000,
                                                    seed=job["seed"]))
    v, s, gn = res.values, res.sigma, res.sigma_gauss_newton
    row = {**job, "rms": res.rms, "fit_seconds": res.runtime_s}
    for key, name, scale in (("theta_L_deg", "theta_L", None), ("U_mm", "U", truth["U_mm"]), ("d_mm", "d", D_MM)):
        err = v[key] - truth[key]
        f = 1.0 if scale is None else 100.0 / scale   # θL in degrees, U and d in percent
        row.update({f"{name}_err": err * f, f"{name}_sigma": s[key] * f, f"{name}_sigma_gn": gn[key] * f,
                    f"{name}_z": err / s[key] if s[key] > 0 else float("nan")})
    print(json.dumps({k: (round(x, 5) if isinstance(x, float) else x) for k, x in row.items()}), flush=True)
    return row


def table(rows) -> list[str]:
    lines = ["# Photometric fit at heavy blur: where the error comes from\n",
             "342 x 228, blur discs of 18 px (half the square), θL 4.65°, 3 views, 1000 pixels per view; "
             "`python benchmarks/history/diag_photometric.py`. Errors: θL in degrees, U and d in percent; z = error / σ "
             "(σ: cluster-robust sandwich; Gauss–Newton σ in brackets).\n",
             "| captures | seed | fit lens samples | residual RMS | θL error | σ θL | z θL | U error | σ U | "
             "z U | "
             "d error | σ d | z d | fit s |", "|" + "---|" * 14]
    for r in rows:
        lines.append(f"| {r['group']} | {r['seed']} | {r['lens_samples']} | {r['rms']:.4f} | "
                     f"{r['theta_L_err']:+.4f} | {r['theta_L_sigma']:.4f} ({r['theta_L_sigma_gn']:.4f}) | "
                     f"{r['theta_L_z']:+.2f} | {r['U_err']:+.3f} | {r['U_sigma']:.3f} ({r['U_sigma_gn']:.3f}) | "
                     f"{r['U_z']:+.2f} | {r['d_err']:+.3f} | {r['d_sigma']:.3f} ({r['d_sigma_gn']:.3f}) | "
                     f"{r['d_z']:+.2f} | {r['fit_seconds']:.0f} |")
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workers", type=int, default=1)
    args = ap.parse_args(argv)
    jobs = [{"group": g, "method": m, "samples": n, "noise": noise, "lens_samples": s, "seed": seed}
            for g, m, n, noise, s, seeds in GROUPS for seed in seeds]
    t0 = time.perf_counter()
    if args.workers > 1:
        import multiprocessing as mp

        with mp.get_context("spawn").Pool(args.workers) as pool:
            rows = pool.map(run, jobs, chunksize=1)
    else:
        rows = [run(j) for j in jobs]
    os.makedirs(RESULTS, exist_ok=True)
    with open(os.path.join(RESULTS, "photometric_diagnosis.json"), "w", encoding="utf-8") as f:
        json.dump({"wall_s": time.perf_counter() - t0, "rows": rows}, f, indent=1)
    lines = table(rows)
    with open(os.path.join(RESULTS, "photometric_diagnosis.md"), "w", encoding="utf-8") as f:
        f.write("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
