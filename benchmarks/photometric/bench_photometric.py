"""Corner-and-blur calibration against photometric refinement: accuracy and time on the same captures.

Same ray-traced photographs for both methods (`tiltfit.experiments.synth.render_view(method="renderer")`: the general
tracer's thin lens with Monte Carlo lens sampling, not either fit's model), a 6 × 4 board of 50 mm cells at
1/8 of the EOS 6D (684 × 456), three views at 480–700 mm, 128 spp and sensor noise 0.003, lens tilts θL = +5°
and −5°. The blur grows by focusing the untilted lens farther (U0). Levels: blur discs of about 18 and 23 px
(a quarter and a third of the projected square), and one past the square (30 mm cells, d = 60 mm, 1/16 of
the EOS 6D: discs 1.4 squares) where no corner detector finds the board.

- corners + blur: `tiltfit.detect.chessboard` (corners and edge blur widths) then the joint fit (`calibrate(..., "joint")`)
  on the views where the detector finds at least 3/4 of the corners (at least two views).
- photometric: `tiltfit.photometric.refine_photometric` on all views, started from the corner fit where there
  is one (a view the corner fit left out starts from the rough prior's pose), else from a rough start (pose
  0.1°/0.5 mm, w +0.3 %, U +1 %, d −3 %, θL +0.1°: a prior calibration's quality), twice: with the aperture
  in closed form (its default at these blurs, `tiltfit.photometric.aperture`) on `--pixels` pixels per view, and with
  the fixed lens samples (`aperture="samples"`, 192 samples) on 1500 (`--no-samples` leaves that one out:
  it takes 6 to 12 minutes a case on one thread).

Each row's error is against the truth; σ is the method's own one-σ (the photometric fit's from its
cluster-robust sandwich covariance, with the textbook Gauss–Newton σ beside it). Times are CPU seconds of the
job's process (all its threads): they compare across thread counts and with jobs sharing the machine.

    python benchmarks/photometric/bench_photometric.py [--quick] [--workers N]

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

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))

from renderer.cameras import EOS_6D
from renderer import Lens, Sensor
from renderer.cameras import optics  # noqa: E402
from tiltfit.experiments import synth  # noqa: E402
from tiltfit.experiments import reproduce  # noqa: E402
from tiltfit.detect.chessboard import detect  # noqa: E402
from tiltfit.calibrate.fit import FitError, FitOptions  # noqa: E402
from tiltfit.calibrate.flow import calibrate  # noqa: E402
from tiltfit.calibrate.model import Observations  # noqa: E402
from tiltfit.files.calib import camera_from_calib  # noqa: E402
from tiltfit.photometric import PhotometricOptions, refine_photometric  # noqa: E402
from tiltfit.target.layout import Target  # noqa: E402

BOARD = Target(tuple(50.0 * i for i in range(7)), tuple(50.0 * j for j in range(5)), (0, 0), 25.0)
SMALL_BOARD = Target(tuple(30.0 * i for i in range(7)), tuple(30.0 * j for j in range(5)), (0, 0), 25.0)
W_MM, D_MM = 55.39, 40.0
TILTS_DEG = (5.0, -5.0)
#: (U0 mm, board, d mm, views, downscale): the blur levels. Past the square the discs are about 30 px at 1/16
#: already; at 1/8 they would need four times the lens samples.
LEVELS = ((700.0, "board", D_MM, (0, 1, 2), 8), (760.0, "board", D_MM, (0, 1, 2), 8),
          (1400.0, "small", 60.0, (0, 1, 4), 16))
#: The issue's targets for the refined lens (|error|): θL degrees, U and d percent.
TARGETS = {"theta_L_err_deg": 0.01, "U_err_pct": 0.05, "d_err_pct": 0.1}
#: Pixels per view of the lens-sample fit (its cost grows with pixels × samples).
SAMPLES_PIXELS = 1500
RESULTS = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "benchmarks", "results")


def captures(U0_mm: float, board: Target, d_mm: float, theta_L_deg: float, views, downscale: int, spp: int):
    """Ray-traced photographs and the truth for one blur level and tilt."""
    w_px, h_px = EOS_6D.binned(downscale).size_px
    pitch = EOS_6D.pixel_pitch * downscale
    cam = Lens.from_tilt(W_MM, float(optics.focal_length(W_MM, U0_mm)), math.radians(theta_L_deg), d_mm, sensor=Sensor(w_px, h_px, pitch))
    images, poses, blur, ratio = [], [], [], []
    for k, i in enumerate(views):
        R, T = reproduce.target_pose(board, *reproduce.TARGET_VIEWS[i])
        view = synth.render_view(board, cam, R, T, method="renderer", spp=spp, noise_sigma=0.003, seed=k)
        images.append(view.image[..., 0].astype(np.float64))
        poses.append((R, T))
        blur.append(view.truth.blur_px)
        ratio.append(float(np.median(view.truth.blur_px) / np.median(synth.projected_square_px(board, cam, R, T))))
    truth = {"U_mm": cam.U, "theta_F_deg": math.degrees(cam.theta_F), "theta_L_deg": theta_L_deg,
             "d_mm": d_mm, "pitch": pitch, "size": (w_px, h_px), "blur_px": float(np.median(np.concatenate(blur))),
             "blur_over_square": float(np.median(ratio))}
    return images, poses, truth


def errors(values: dict, sigma: dict, truth: dict) -> dict:
    """Errors against the truth (θL degrees; U, d, w percent) and the method's σ in the same units."""
    return {"theta_L_err_deg": values["theta_L_deg"] - truth["theta_L_deg"],
            "U_err_pct": 100 * (values["U_mm"] / truth["U_mm"] - 1),
            "d_err_pct": 100 * (values["d_mm"] / truth["d_mm"] - 1),
            "w_err_pct": 100 * (values["w_mm"] / W_MM - 1),
            "sigma_theta_L_deg": sigma.get("theta_L_deg"),
            "sigma_U_pct": 100 * sigma["U_mm"] / truth["U_mm"] if sigma.get("U_mm") is not None else None,
            "sigma_d_pct": 100 * sigma["d_mm"] / truth["d_mm"] if sigma.get("d_mm") is not None else None}


def rough_start(poses, truth, seed=1):
    import cv2

    rng = np.random.default_rng(seed)
    U = truth["U_mm"] * 1.01
    theta_F = optics.theta_F_from_theta_L(math.radians(truth["theta_L_deg"] + 0.1), W_MM * 1.003, U)
    return {"w_mm": W_MM * 1.003, "U_mm": U, "d_mm": truth["d_mm"] * 0.97,
            "theta_F_deg": math.degrees(float(theta_F)),
            "views": [{"R": cv2.Rodrigues(rng.normal(0, math.radians(0.1), 3))[0] @ R,
                       "T_mm": T + rng.normal(0, 0.5, 3)} for R, T in poses]}


def corner_fit(images, board, truth):
    """The corner-and-blur calibration on the views where the detector finds at least 3/4 of the corners (at
    least two views); (result or None, CPU seconds, corners found per view, the views it used)."""
    t0 = time.process_time()
    dets = [detect(im, board) for im in images]
    found = [int(d.found.sum()) for d in dets]
    used = [k for k, n in enumerate(found) if n >= 0.75 * board.n_points]
    if len(used) < 2:
        return None, time.process_time() - t0, found, used
    obs = Observations(board.feature_points(), np.stack([dets[k].corners_px for k in used]),
                       np.stack([dets[k].blur_px for k in used]), truth["size"], truth["pitch"])
    try:
        res = calibrate(obs, "joint", options=FitOptions(model_selection=False, nominal_focal_mm=55.0))
    except FitError:
        return None, time.process_time() - t0, found, used
    return res, time.process_time() - t0, found, used


def photometric_row(images, board, start, truth, base, start_name, t_corner, options, label):
    t0 = time.process_time()
    h, w = images[0].shape[:2]
    camera = camera_from_calib({**start, "image_size_px": (w, h), "pixel_pitch_mm": truth["pitch"]})
    ph = refine_photometric(images, board, camera, options)
    t_ph = time.process_time() - t0
    gn = errors(ph.values, ph.sigma_gauss_newton, truth)
    if ph.values["aperture"] == "mixed":
        total = sum(v["n_pixels"] for v in ph.views)
        label += f" ({ph.values['closed_form_pixels']} of {total} in closed form, lens samples for the sharper)"
    return {**base, "method": f"photometric, {label} (from {start_name})", "aperture": ph.values["aperture"],
            "pixels": options.max_pixels, "seconds": t_ph + t_corner, "photometric_seconds": t_ph,
            **errors(ph.values, ph.sigma, truth), "rms": ph.rms,
            "iterations": ph.iterations, "gauss_newton_sigma_theta_L_deg": gn["sigma_theta_L_deg"],
            "gauss_newton_sigma_U_pct": gn["sigma_U_pct"], "gauss_newton_sigma_d_pct": gn["sigma_d_pct"]}


def run_case(case: dict) -> list[dict]:
    """Both methods on one set of captures (one blur level, one tilt); the rows of the table."""
    import torch

    torch.set_num_threads(case["threads"])
    board = BOARD if case["board"] == "board" else SMALL_BOARD
    images, poses, truth = captures(case["U0_mm"], board, case["d_mm"], case["theta_L_deg"], case["views"],
                                    case["downscale"], case["spp"])
    res, t_corner, found, used = corner_fit(images, board, truth)
    base = {**case, "blur_px": truth["blur_px"], "blur_over_square": truth["blur_over_square"],
            "corners_found": found}
    rows = []
    if res is not None:
        partial = len(used) < len(images)
        if case["photometric"] == "closed_form":
            rows.append({**base, "method": "corners + blur" + (f" (views {used})" if partial else ""),
                         "seconds": t_corner, **errors(res.values, res.sigma, truth)})
        # Views without corners start from the rough prior's pose (the lens from the corner fit).
        rough = rough_start(poses, truth)["views"]
        fitted = dict(zip(used, res.views))
        start = {**{k: res.values[k] for k in ("w_mm", "U_mm", "d_mm", "theta_F_deg", "principal_point_px")},
                 "views": [{"R": fitted[k]["R"], "T_mm": fitted[k]["T_mm"]} if k in fitted else rough[k]
                           for k in range(len(images))]}
        start_name = "corner fit" + (f" on views {used}, rough pose elsewhere" if partial else "")
    else:
        start, start_name = rough_start(poses, truth), "rough start"
    t_start = t_corner if res else 0.0
    if case["photometric"] == "closed_form":
        rows.append(photometric_row(images, board, start, truth, base, start_name, t_start,
                                    PhotometricOptions(max_pixels=case["pixels"]),
                                    f"closed form, {case['pixels']} px/view"))
    else:
        rows.append(photometric_row(images, board, start, truth, base, start_name, t_start,
                                    PhotometricOptions(aperture="samples", lens_samples=case["lens_samples"],
                                                       max_pixels=SAMPLES_PIXELS),
                                    f"{case['lens_samples']} lens samples, {SAMPLES_PIXELS} px/view"))
    for r in rows:
        print(f"θL {r['theta_L_deg']:+.2f}°, blur {r['blur_px']:.1f} px ({r['blur_over_square']:.2f} square), "
              f"corners {found}: {r['method']}: θL {r['theta_L_err_deg']:+.4f}° (σ {r['sigma_theta_L_deg']:.4f}), "
              f"U {r['U_err_pct']:+.3f} %, d {r['d_err_pct']:+.3f} %, {r['seconds']:.1f} s", flush=True)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="1/16 images, two blur levels, +5° only")
    ap.add_argument("--workers", type=int, default=2, help="cases run in parallel processes [2]")
    ap.add_argument("--pixels", type=int, default=None, help="pixels per view of the closed-form fit [20000; "
                    "--quick 2000]")
    ap.add_argument("--no-samples", action="store_true", help="leave out the lens-sample photometric fit")
    ap.add_argument("--threads", type=int, default=1, help="torch threads of each closed-form job [1] (times "
                    "are CPU seconds, so they compare across thread counts)")
    ap.add_argument("--out", default=RESULTS, help="results folder [benchmarks/results]")
    ap.add_argument("--levels", default="all", choices=("all", "board", "past"),
                    help="blur levels: all, the two on the coarse board, or past the square only [all]")
    ap.add_argument("--table-from", metavar="PARTIAL_JSON", help="write the table and chart from the rows of "
                    "an interrupted run (its photometric.partial.json) instead of running")
    ap.add_argument("--note", default="", help="a sentence for the table's header (with --table-from: the "
                    "machine and why the run stopped)")
    args = ap.parse_args(argv)
    out = args.out
    spp, pixels, lens_samples = (32, 2000, 64) if args.quick else (128, 20000, 192)
    pixels = args.pixels or pixels
    lens_samples = 0 if args.no_samples else lens_samples
    levels = [(U0, b, d, v, 16) for U0, b, d, v, _ in LEVELS[1:]] if args.quick else LEVELS
    levels = [lv for lv in levels if args.levels == "all" or (lv[1] == "board") == (args.levels == "board")]
    tilts = TILTS_DEG[:1] if args.quick else TILTS_DEG
    cases = [{"U0_mm": U0, "board": board, "d_mm": d, "views": views, "theta_L_deg": tilt,
              "downscale": downscale, "spp": spp, "pixels": pixels, "lens_samples": lens_samples,
              "photometric": variant, "threads": args.threads if variant == "closed_form" else 1}
             for variant in ("closed_form", "samples")[:1 if args.no_samples else 2]
             for U0, board, d, views, downscale in levels for tilt in tilts
             if board == "board" or tilt > 0]   # past the square: one tilt (a photometric fit only)
    # Each job renders its case's captures itself (the same seeds: the same images in every job).
    t0 = time.perf_counter()
    if args.table_from:
        with open(args.table_from, encoding="utf-8") as f:
            rows = json.load(f)
    elif args.workers > 1:
        import multiprocessing as mp

        with mp.get_context("spawn").Pool(args.workers) as pool:
            rows = []
            for rs in pool.imap_unordered(run_case, cases, chunksize=1):
                rows += rs
                _partial(out, rows)
    else:
        rows = []
        for c in cases:
            rows += run_case(c)
            _partial(out, rows)
    wall = time.perf_counter() - t0
    order = {"corners + blur": 0, "photometric, closed form": 1, "photometric, lens samples": 2}
    rows.sort(key=lambda r: (-r["downscale"] < -8, r["U0_mm"], -r["theta_L_deg"], order[_family(r)]))
    os.makedirs(out, exist_ok=True)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    if args.table_from:
        wall, load = float("nan"), float("nan")
    meta = {"size_px": {str(c["downscale"]): list(EOS_6D.binned(c["downscale"]).size_px) for c in cases},
            "spp": spp, "pixels_per_view": pixels, "lens_samples": lens_samples,
            "true": {"w_mm": W_MM, "d_mm": D_MM}, "tilts_deg": list(tilts), "load_average": load,
            "wall_s": wall, "workers": args.workers, "quick": args.quick, "targets": TARGETS, "cpu": _cpu_name(),
            "cores": os.cpu_count(), "note": args.note, "table_from": args.table_from}
    with open(os.path.join(out, "photometric.json"), "w", encoding="utf-8") as f:
        json.dump({"meta": meta, "rows": rows}, f, indent=1)
    lines = table(rows, meta)
    with open(os.path.join(out, "photometric.md"), "w", encoding="utf-8") as f:
        f.write("\n".join(lines) + "\n")
    plot(rows, os.path.join(out, "photometric.png"))
    print("\n".join(lines))
    return 0


def _cpu_name() -> str:
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            return next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), "unknown")
    except OSError:
        return "unknown"


def _partial(out: str, rows: list) -> None:
    """The rows so far (photometric.partial.json), so an interrupted run keeps its finished cases."""
    os.makedirs(out, exist_ok=True)
    with open(os.path.join(out, "photometric.partial.json"), "w", encoding="utf-8") as f:
        json.dump(rows, f, indent=1)


def _family(r) -> str:
    """The method without its settings: corners + blur, photometric closed form or lens samples."""
    if not r["method"].startswith("photometric"):
        return "corners + blur"
    return "photometric, closed form" if r.get("aperture") in ("closed_form", "mixed") else "photometric, lens samples"


def _met(r) -> str:
    """Which of the issue's targets a row meets."""
    return " ".join(("✓" if abs(r[k]) <= v else "✗") for k, v in TARGETS.items())


def table(rows, meta) -> list[str]:
    lines = ["# Corner-and-blur fit vs photometric refinement (same ray-traced photographs, same run)\n",
             f"6 x 4 board of 50 mm cells (30 mm past the square), 3 views, "
             f"{' and '.join(f'{w} x {h}' for w, h in meta['size_px'].values())}, {meta['spp']} spp captures and "
             f"sensor noise 0.003; photometric fit: "
             f"the closed form on {meta['pixels_per_view']} pixels per view, the lens samples on {SAMPLES_PIXELS}. "
             + (f"{meta['workers']} worker processes on {meta['cores']} cores ({meta['cpu']}), "
              f"{meta['wall_s'] / 60:.1f} min in all, load average {meta['load_average']:.1f} at the end. "
              if not meta.get("table_from") else "Rows of an interrupted run (below). ")
             + "`python benchmarks/photometric/bench_photometric.py`.\n",
             *([meta["note"] + "\n"] if meta.get("note") else []),
             "Targets (issue 9): |θL error| ≤ 0.01°, |U error| ≤ 0.05 %, |d error| ≤ 0.1 %; the last column "
             "says "
             "which a row meets (θL U d). σ: the method's own one-σ; for the photometric fit the cluster-robust "
             "sandwich, with the textbook Gauss–Newton σ(θL) in brackets.\n",
             "| θL true ° | size | blur px | blur / square | corners found | method | θL error ° | σ θL ° | "
             "U error % | σ U % | d error % | σ d % | w error % | CPU seconds | targets met |", "|" + "---|" * 15]
    for r in rows:
        sg = r.get("sigma_theta_L_deg")
        gn = r.get("gauss_newton_sigma_theta_L_deg")
        sgl = f"{sg:.4f}" + (f" ({gn:.4f})" if gn is not None else "")
        size = meta["size_px"][str(r["downscale"])]
        lines.append(f"| {r['theta_L_deg']:+.1f} | {size[0]}x{size[1]} | {r['blur_px']:.1f} | "
                     f"{r['blur_over_square']:.2f} | "
                     f"{'/'.join(map(str, r['corners_found']))} | {r['method']} | {r['theta_L_err_deg']:+.4f} | "
                     f"{sgl} | {r['U_err_pct']:+.3f} | {r['sigma_U_pct']:.3f} | {r['d_err_pct']:+.3f} | "
                     f"{r['sigma_d_pct']:.3f} | {r['w_err_pct']:+.3f} | {r['seconds']:.1f} | {_met(r)} |")
    lines.append("\nPhotometric seconds include the corner fit it starts from where there is one. Where no "
                 "corners are found the photometric fit starts from a rough prior calibration instead.")
    lines.append("\n| method | rows | median CPU seconds | targets met (θL, U, d) |\n|---|---|---|---|")
    for method in sorted({_family(r) for r in rows}):
        sel = [r for r in rows if _family(r) == method]
        met = [sum(abs(r[k]) <= v for r in sel) for k, v in TARGETS.items()]
        lines.append(f"| {method} | {len(sel)} | {float(np.median([r['seconds'] for r in sel])):.1f} | "
                     f"{met[0]}/{len(sel)}, {met[1]}/{len(sel)}, {met[2]}/{len(sel)} |")
    return lines


def plot(rows, path):
    """Accuracy against time, one panel, one curve per method: |θL error| (filled) and its σ (open) against
    seconds, the points of a curve ordered by time and labelled by blur and tilt."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 4.8))
    for method, color in (("corners + blur", "C0"), ("photometric, closed form", "C3"),
                          ("photometric, lens samples", "C2")):
        sel = sorted((r for r in rows if _family(r) == method), key=lambda r: r["seconds"])
        if not sel:
            continue
        t = [r["seconds"] for r in sel]
        ax.plot(t, [abs(r["theta_L_err_deg"]) for r in sel], "o-", color=color, label=f"{method}: |θL error|")
        ax.plot(t, [r["sigma_theta_L_deg"] for r in sel], "o--", mfc="none", color=color, alpha=0.6,
                label=f"{method}: its σ(θL)")
        for r in sel:
            ax.annotate(f"{r['blur_px']:.0f} px, {r['theta_L_deg']:+.0f}°", (r["seconds"], abs(r["theta_L_err_deg"])),
                        fontsize=7, xytext=(3, 3), textcoords="offset points")
    ax.axhline(TARGETS["theta_L_err_deg"], color="grey", lw=0.8, ls=":", label="target 0.01°")
    ax.set(xscale="log", yscale="log", xlabel="CPU time, s", ylabel="θL, degrees",
           title="accuracy against time, same captures (labels: blur disc, tilt)")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    sys.exit(main())
