"""Corner detection against OpenCV on the same synthetic images: success and accuracy versus blur, and time.

Peers, measured in the same run on the same images:
- `sb`: cv2.findChessboardCornersSB (flags NORMALIZE_IMAGE | EXHAUSTIVE | ACCURACY), the sub-pixel
  detector OpenCV recommends;
- `classic`: cv2.findChessboardCorners (ADAPTIVE_THRESH | NORMALIZE_IMAGE) + cv2.cornerSubPix (11 × 11 window).
OpenCV gets the 8-bit sRGB image (as cv2.imread would), ours the same image decoded to linear.

Images: `tiltfit.experiments.synth` exact disc-blur rendering of the 9 × 6 designed target (40 inner corners) from several
poses, blur set to a fraction of the projected square (focus at 400 mm, target at ~650 mm), 8-bit sRGB with
Gaussian noise 0.004 (linear). A method succeeds on an image when it returns every visible corner and
none is more than 1 px off (a returned board with misplaced corners counts as a failure; the JSON keeps
both rates); corner error = distance to the true projection (OpenCV corners matched to the nearest truth
corner, ours by index — a wrong index counts as an error of a square).

Writes benchmarks/results/detect_opencv.{json,md,png}. Usage:
    python benchmarks/detection/bench_detect_opencv.py [--quick] [--out benchmarks/results]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time

import cv2
import numpy as np
import torch

from tiltfit.detect.chessboard import detect, detect_corners, to_gray
from tiltfit.detect.blur import measure_blur
from tiltfit.experiments.synth import PAPER_CAMERA, look_at_pose, projected_square_px, render_view, with_blur_ratio
from tiltfit.target.design import design_target

TARGET = design_target(9, 6, 20.0, w_mm=55.39, distance_mm=650.0, inclination_deg=20.0)
PATTERN = (TARGET.grid_shape[1], TARGET.grid_shape[0])  # OpenCV: (points per row, per column)
POSES = [((40.0, -30.0, -650.0), 10.0), ((-80.0, -120.0, -600.0), -15.0), ((150.0, 60.0, -700.0), 25.0)]


def opencv_sb(gray8):
    flags = cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
    ok, c = cv2.findChessboardCornersSB(gray8, PATTERN, flags=flags)
    return c.reshape(-1, 2).astype(np.float64) if ok else None


def opencv_classic(gray8):
    ok, c = cv2.findChessboardCorners(gray8, PATTERN, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
    if not ok:
        return None
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 1e-3)
    c = cv2.cornerSubPix(gray8, c, (11, 11), (-1, -1), crit)
    return c.reshape(-1, 2).astype(np.float64)


def ours(linear):
    det = detect(linear, TARGET, measure_blur=False)
    return det.corners_px if det.grid_found else None


def score(found, truth, visible, by_index):
    """(success, errors of returned corners)."""
    if found is None:
        return False, np.zeros(0)
    if by_index:
        ok = np.isfinite(found).all(1)
        err = np.hypot(*(found[ok] - truth[ok]).T)
        return bool(ok[visible].all()), err
    d = np.hypot(found[:, None, 0] - truth[None, :, 0], found[:, None, 1] - truth[None, :, 1])
    return True, d.min(1)


def sweep(camera, ratios, poses, noise, log):
    rows = []
    for ratio in ratios:
        for (pos, roll) in poses:
            R, T = look_at_pose(TARGET, pos, roll_deg=roll)
            cam = with_blur_ratio(camera, TARGET, R, T, max(ratio, 1e-4), U_mm=400.0)
            t0 = time.perf_counter()
            seed = int(ratio * 100) * 7 + int(abs(roll))
            v = render_view(TARGET, cam, R, T, noise_sigma=noise, srgb8=True, seed=seed)
            t_render = time.perf_counter() - t0
            truth = v.truth.corners_px
            visible = v.truth.in_image
            gray8 = v.image_srgb8[..., 0]
            square = float(np.median(projected_square_px(TARGET, cam, R, T)))
            row = {"ratio": ratio, "pose": list(pos), "roll_deg": roll, "square_px": square,
                   "blur_px_median": float(np.median(v.truth.blur_px)), "render_s": t_render}
            for name, fn, arg, by_index in (("ours", ours, v.image, True), ("sb", opencv_sb, gray8, False),
                                            ("classic", opencv_classic, gray8, False)):
                t0 = time.perf_counter()
                found = fn(arg)
                dt = time.perf_counter() - t0
                ok, err = score(found, truth, visible, by_index)
                row[name] = {"success": ok, "n": int(err.size), "rms_px": float(np.sqrt(np.mean(err ** 2))) if err.size
                             else None, "max_px": float(err.max()) if err.size else None, "time_s": dt}
            rows.append(row)
            log(f"ratio {ratio:.2f} roll {roll:+.0f}: blur {row['blur_px_median']:.1f} px / square {square:.1f} px | "
                + " | ".join(f"{n} {'ok' if row[n]['success'] else '--'} "
                             f"{(row[n]['rms_px'] or float('nan')):.3f}" for n in ("ours", "sb", "classic")))
    return rows


def summarize(rows, ratios):
    out = []
    for ratio in ratios:
        rr = [r for r in rows if r["ratio"] == ratio]
        s = {"ratio": ratio, "blur_px": statistics.median(r["blur_px_median"] for r in rr),
             "square_px": statistics.median(r["square_px"] for r in rr)}
        for n in ("ours", "sb", "classic"):
            returned = [r[n]["success"] for r in rr]
            succ = [r[n]["success"] and r[n]["max_px"] is not None and r[n]["max_px"] < 1.0 for r in rr]
            errs = [r[n]["rms_px"] for r, ok in zip(rr, succ) if ok]
            s[n] = {"returned_rate": sum(returned) / len(returned), "success_rate": sum(succ) / len(succ),
                    "rms_px": float(np.sqrt(np.mean(np.square(errs)))) if errs else None}
        out.append(s)
    return out


def _opencv_child(which: str, npy: str) -> None:
    """Child process: time one OpenCV detector on a saved 8-bit image and print the seconds."""
    cv2.setNumThreads(1)
    gray8 = np.load(npy)
    t0 = time.perf_counter()
    (opencv_sb if which == "sb" else opencv_classic)(gray8)
    print(f"{time.perf_counter() - t0:.4f}", flush=True)


def time_opencv(which: str, gray8, limit_s: float) -> float:
    """Seconds one OpenCV detector takes, measured in a child process; inf when it runs past `limit_s`."""
    import subprocess
    import sys
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        npy = os.path.join(tmp, "gray8.npy")
        np.save(npy, gray8)
        try:
            out = subprocess.run([sys.executable, __file__, "--opencv-child", which, npy], capture_output=True,
                                 text=True, timeout=limit_s + 30)
            return float(out.stdout.strip().splitlines()[-1])
        except subprocess.TimeoutExpired:
            return float("inf")


def timing(camera, ratio, repeats, log, label, opencv_repeats, limit_s):
    R, T = look_at_pose(TARGET, POSES[0][0], roll_deg=POSES[0][1])
    cam = with_blur_ratio(camera, TARGET, R, T, ratio, U_mm=400.0)
    t0 = time.perf_counter()
    v = render_view(TARGET, cam, R, T, noise_sigma=0.004, srgb8=True, seed=11)
    log(f"{label}: rendered {camera.sensor.width_px}×{camera.sensor.height_px} in {time.perf_counter() - t0:.1f} s")
    gray8 = v.image_srgb8[..., 0]
    detect(v.image, TARGET)  # warm-up (imports, kernels)
    res = {"image_px": [camera.sensor.width_px, camera.sensor.height_px], "blur_px_median": float(np.median(v.truth.blur_px)),
           "square_px": float(np.median(projected_square_px(TARGET, cam, R, T))), "opencv_limit_s": limit_s}
    times = {"ours_total": [], "ours_corners": [], "ours_blur": [], "sb": [], "classic": []}
    for _ in range(repeats):
        t0 = time.perf_counter()
        det = detect(v.image, TARGET)
        times["ours_total"].append(time.perf_counter() - t0)
        times["ours_blur"].append(det.timings_s.get("blur", float("nan")))
        times["ours_corners"].append(times["ours_total"][-1] - times["ours_blur"][-1])
    for name in ("sb", "classic"):
        for _ in range(opencv_repeats):
            times[name].append(time_opencv(name, gray8, limit_s))
            if not np.isfinite(times[name][-1]):
                break  # timed out once: no need to wait again
    e = np.hypot(*(det.corners_px - v.truth.corners_px).T)
    eb = np.abs(det.blur_px / v.truth.blur_px - 1)
    res["median_s"] = {k: statistics.median(t) for k, t in times.items()}
    res["ours_found"] = int(det.found.sum())
    res["ours_rms_px"] = float(np.sqrt(np.nanmean(e ** 2)))
    res["ours_blur_max_rel_err"] = float(np.nanmax(eb))
    log(f"{label}: " + ", ".join(f"{k} {v:.2f} s" for k, v in res["median_s"].items())
        + f"; ours {res['ours_found']} corners, RMS {res['ours_rms_px']:.3f} px, "
        f"blur ≤ {100 * res['ours_blur_max_rel_err']:.1f} %")
    return res


def write_outputs(out_dir, summary, rows, timings, meta):
    os.makedirs(out_dir, exist_ok=True)
    with open(os.path.join(out_dir, "detect_opencv.json"), "w") as f:
        json.dump({"meta": meta, "summary": summary, "timing": timings, "images": rows}, f, indent=1)
        f.write("\n")
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 4))
    ax1, ax2 = fig.subplots(1, 2)
    x = [s["ratio"] for s in summary]
    for n, label, m in (("ours", "ours (kornia saddles + point symmetry)", "o-"),
                        ("sb", "cv2.findChessboardCornersSB", "s--"),
                        ("classic", "cv2.findChessboardCorners + cornerSubPix", "^:")):
        ax1.plot(x, [s[n]["success_rate"] for s in summary], m, label=label)
        ax2.plot(x, [s[n]["rms_px"] if s[n]["rms_px"] is not None else np.nan for s in summary], m, label=label)
    ax1.set_xlabel("blur diameter / projected square")
    ax1.set_ylabel("success: every visible corner, none > 1 px off")
    ax1.set_ylim(-0.05, 1.05)
    ax2.set_xlabel("blur diameter / projected square")
    ax2.set_ylabel("corner RMS error (px), successful images")
    ax2.set_yscale("log")
    ax2.axhline(0.05, color="grey", lw=0.8)
    ax1.legend(fontsize=7)
    fig.suptitle(f"{meta['sweep_image_px'][0]}×{meta['sweep_image_px'][1]} synthetic disc-blurred images, "
                 f"{meta['poses']} poses per blur", fontsize=9)
    fig.tight_layout()
    fig.savefig(os.path.join(out_dir, "detect_opencv.png"), dpi=110)

    lines = ["# Corner detection vs OpenCV", "",
             f"Machine: {meta['machine']}; load average at start {meta['loadavg']}; torch threads "
             f"{meta['torch_threads']}, OpenCV threads {meta['cv2_threads']}. Command: `{meta['command']}`.", "",
             "## Success and accuracy versus blur", "",
             "| blur / square | blur px | ours ok | ours RMS px | SB ok | SB RMS px | classic ok | classic RMS px |",
             "|---|---|---|---|---|---|---|---|"]
    for s in summary:
        def f(v):
            return "–" if v is None else f"{v:.3f}"
        lines.append(f"| {s['ratio']:.2f} | {s['blur_px']:.1f} | {s['ours']['success_rate']:.0%} "
                     f"| {f(s['ours']['rms_px'])} | {s['sb']['success_rate']:.0%} | {f(s['sb']['rms_px'])} "
                     f"| {s['classic']['success_rate']:.0%} | {f(s['classic']['rms_px'])} |")
    lines += ["", "## Time per image (median)", "",
              "| image | blur px | ours total s | ours corners s | ours blur s | SB s | classic s "
              "| SB / ours corners |",
              "|---|---|---|---|---|---|---|---|"]
    for t in timings:
        m = t["median_s"]

        def cv(k):
            return f"{m[k]:.2f}" if np.isfinite(m[k]) else f"> {t['opencv_limit_s']:.0f}"

        ratio = f"{m['sb'] / m['ours_corners']:.1f}×" if np.isfinite(m["sb"]) else \
            f"> {t['opencv_limit_s'] / m['ours_corners']:.0f}×"
        lines.append(f"| {t['image_px'][0]}×{t['image_px'][1]} | {t['blur_px_median']:.1f} | {m['ours_total']:.2f} | "
                     f"{m['ours_corners']:.2f} | {m['ours_blur']:.2f} | {cv('sb')} | {cv('classic')} | {ratio} |")
    lines += ["", "![chart](detect_opencv.png)", ""]
    with open(os.path.join(out_dir, "detect_opencv.md"), "w") as f:
        f.write("\n".join(lines))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="684×456 sweep, one pose, no 20 MP timing")
    p.add_argument("--out", default=os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "benchmarks", "results"))
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--opencv-limit-s", type=float, default=120.0, help="time limit per OpenCV call (timing)")
    p.add_argument("--skip-sweep", action="store_true", help="keep the sweep of the last run's JSON, redo timing")
    p.add_argument("--replot", action="store_true", help="re-summarise and redraw from the JSON of a run")
    p.add_argument("--opencv-child", nargs=2, metavar=("WHICH", "NPY"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.opencv_child:
        return _opencv_child(*args.opencv_child)
    json_path = os.path.join(args.out, "detect_opencv.json")
    if args.replot:
        with open(json_path) as f:
            d = json.load(f)
        ratios = sorted({r["ratio"] for r in d["images"]})
        write_outputs(args.out, summarize(d["images"], ratios), d["images"], d["timing"], d["meta"])
        return
    # one thread each: on a shared machine extra threads only measure the contention
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    log = lambda s: print(s, flush=True)  # noqa: E731
    ratios = [0.0, 0.2, 0.5, 0.8] if args.quick else [0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0]
    poses = POSES[:1] if args.quick else POSES
    sweep_cam = PAPER_CAMERA.binned(8 if args.quick else 4)
    meta = {"machine": f"{platform.machine()}, {os.cpu_count()} CPUs, {platform.python_version()}, torch "
                       f"{torch.__version__}, OpenCV {cv2.__version__}",
            "loadavg": [round(v, 2) for v in os.getloadavg()], "torch_threads": torch.get_num_threads(),
            "cv2_threads": cv2.getNumThreads(), "command": "python benchmarks/detection/bench_detect_opencv.py"
            + (" --quick" if args.quick else ""), "sweep_image_px": [sweep_cam.sensor.width_px, sweep_cam.sensor.height_px],
            "poses": len(poses), "noise_linear": 0.004, "target": TARGET.to_dict()}
    if args.skip_sweep:
        with open(json_path) as f:
            old = json.load(f)
        rows, meta = old["images"], {**old["meta"], "loadavg_timing": meta["loadavg"]}
        ratios = sorted({r["ratio"] for r in rows})
    else:
        rows = sweep(sweep_cam, ratios, poses, 0.004, log)
    summary = summarize(rows, ratios)
    write_outputs(args.out, summary, rows, [], meta)  # the sweep is safe on disk before the long timings
    timings = [timing(PAPER_CAMERA.binned(4), 0.15, args.repeats, log, "1368×912", 3, args.opencv_limit_s)]
    if not args.quick:
        timings.append(timing(PAPER_CAMERA, 0.15, max(3, args.repeats // 2), log, "5472×3648", 1,
                              args.opencv_limit_s))
    write_outputs(args.out, summary, rows, timings, meta)
    log(f"wrote {args.out}/detect_opencv.{{json,md,png}}")


if __name__ == "__main__":
    main()
