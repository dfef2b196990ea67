"""The default calibration after detection on real photo sets, against OpenCV's whole calibration of the same corners.

    python benchmarks/calibration/bench_calib_real_speed.py [--repeats 3] [--cv-repeats 5] [--sets gopro_wide,...]
                                                [--base /tmp/calib_before] [--name calib_real_speed]

Sets (tiltfit's own detections cached beside the photos, `data/real/SET/detections_tiltfit.json`, so detection is
not timed):
- gopro_wide (35 views with a board of 36, 8×6 corners, pixel pitch 0.00155 mm);
- industrial_ds1 (20 views, 16×10 corners, 0.0048 mm);
- sony_small (13 views of a 4×6-corner board, 640×480, 0.0096 mm; detections cached in benchmarks/small_sets);
- industrial_60: 60 views of the industrial camera, the size the issue reports (84 s there). Only dataset 1 of the
  source's three (20 photos) is shipped, so the set is its 20 views and two copies of each whose corners and blur
  widths have independent Gaussian noise added (0.1 px a corner coordinate, the free-board fit's residual RMS;
  0.2 px a width, the widths' noise there), seed 0. A copy's pose is its view's, and views are dealt into the
  held-out folds round-robin, so a view and its copies share a fold (no copy predicts its own view).

Timed in one process, CPU seconds (`time.process_time`, one torch thread) and wall seconds, medians of the repeats:
- ours: `tiltfit.calibrate.photos.fit_with_held_out` with `tiltfit calibrate`'s defaults (distortion auto, board
  auto, principal point tested, 5-fold held-out error, blur fit and its checks);
- OpenCV: `cv2.calibrateCamera` on the same corners (views with at least 6 corners, unobserved corners left out),
  its default model (k1 k2 p1 p2 k3, free principal point and both focal lengths).
`--base DIR` times the same in a child process with the code of another checkout (e.g. the commit before a
change: `git clone -q . /tmp/calib_before && git -C /tmp/calib_before checkout START`), so "before" and "after"
share a run (the two trees in turn, one repeat of every set each), and checks that a speed change changed no
result: the same distortion, board and principal-point choices, and focal length and principal point within
`SAME_SIGMA` of their σ of the other checkout's (the check's verdict per set is in both files; the command exits
with status 1 where one differs). Writes benchmarks/results/NAME.{json,md}: times, ratios ours/OpenCV, and the
chosen models and focal length / principal point with σ of ours.
"""
from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import platform
import statistics
import subprocess
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SETS = {"gopro_wide": ("gopro_wide", 0.00155), "industrial_ds1": ("industrial_ds1", 0.0048),
        "industrial_60": ("industrial_ds1", 0.0048), "sony_small": ("sony_small", 0.0096)}
#: Folders of the sets not in data/real (relative to the repository).
FOLDERS = {"sony_small": os.path.join("benchmarks", "small_sets", "sony_small")}
#: `--base`'s check: fitted focal length and principal point of the two checkouts within this many of their σ (this
#: tree's). A relative 1e-7 was the check before; a rounding-level change of the Jacobian (2e-16 relative) moves
#: industrial_ds1's principal point, whose σ is 5 px, by 6e-5 px (1e-5 σ, 1.1e-7 relative).
SAME_SIGMA = 1e-3
#: industrial_60's copies: noise added to corners (px a coordinate) and blur widths (px), and the seed.
COPY_CORNER_NOISE_PX, COPY_BLUR_NOISE_PX, COPY_SEED = 0.1, 0.2, 0


def observations(name: str, root: str):
    """(Observations of set `name` with the code under `root`) from the cached detections."""
    from tiltfit.calibrate.model import Observations
    from tiltfit.target.layout import load_target

    folder, pitch = SETS[name]
    folder = os.path.join(ROOT, FOLDERS.get(name, os.path.join("data", "real", folder)))
    target = load_target(os.path.join(folder, "target.json"))
    with open(os.path.join(folder, "detections_tiltfit.json"), encoding="utf-8") as f:
        cache = json.load(f)
    names = [n for n in sorted(cache) if "no_board" not in cache[n]]
    corners = np.array([[c if c is not None else [np.nan, np.nan] for c in cache[n]["corners_px"]] for n in names])
    blur = np.array([[b if b is not None else np.nan for b in cache[n]["blur_px"]] for n in names])
    if name == "industrial_60":
        rng = np.random.default_rng(COPY_SEED)
        copies = [(corners + rng.normal(0, COPY_CORNER_NOISE_PX, corners.shape),
                   blur + rng.normal(0, COPY_BLUR_NOISE_PX, blur.shape)) for _ in range(2)]
        names = names + [f"{n}#copy{k + 1}" for k in range(2) for n in names]
        corners = np.concatenate([corners] + [c for c, _ in copies])
        blur = np.concatenate([blur] + [b for _, b in copies])
    size = tuple(cache[names[0].split("#")[0]]["image_size_px"])
    return Observations(target.feature_points(), corners.astype(np.float64), blur.astype(np.float64), size, pitch,
                        names)


def time_opencv(obs, repeats: int) -> dict:
    """cv2.calibrateCamera on the observed corners of the views with at least 6; medians of `repeats`."""
    import cv2

    pts = obs.points_mm.numpy().astype(np.float32)
    obj, img = [], []
    for v in range(obs.n_views):
        m = obs.corner_mask[v].numpy()
        if m.sum() >= 6:
            obj.append(pts[m])
            img.append(obs.corners_px[v].numpy()[m].astype(np.float32))
    cpu, wall = [], []
    for _ in range(repeats):
        c0, w0 = time.process_time(), time.perf_counter()
        rms, K, dist, _, _ = cv2.calibrateCamera(obj, img, tuple(obs.image_size_px), None, None)
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - w0)
    return {"cpu_s": statistics.median(cpu), "wall_s": statistics.median(wall), "repeats": repeats,
            "rms_px": float(rms), "focal_px": [float(K[0, 0]), float(K[1, 1])],
            "principal_point_px": [float(K[0, 2]), float(K[1, 2])]}


def time_ours(obs, repeats: int) -> dict:
    """`fit_with_held_out` with `tiltfit calibrate`'s defaults; medians of `repeats`; the last run's choices."""
    from tiltfit.calibrate.fit import FitOptions
    from tiltfit.calibrate.photos import fit_with_held_out

    cpu, wall = [], []
    for _ in range(repeats):
        c0, w0 = time.process_time(), time.perf_counter()
        res, used, held = fit_with_held_out(obs, "unified", options=FitOptions(distortion="auto", board="auto"))
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - w0)
    pitch = float(res.camera.pixel_pitch_mm)
    return {"cpu_s": statistics.median(cpu), "wall_s": statistics.median(wall), "repeats": repeats,
            "cpu_s_all": cpu, "distortion": res.distortion_model,
            "board": res.board.model if res.board is not None else "flat",
            "free_principal_point": bool(res.free_principal_point), "undetermined": list(res.undetermined),
            "focal_px": res.values["w_mm"] / pitch, "sigma_focal_px": res.sigma["w_mm"] / pitch,
            "principal_point_px": res.values["principal_point_px"],
            "sigma_principal_point_px": res.sigma.get("principal_point_px"),
            "held_out_rms_px": (held or {}).get("rms_px")}


def child(args) -> None:
    """One code tree's measurements, as JSON on stdout (run in the tree given by --code)."""
    sys.path.insert(0, args.code)
    import torch

    torch.set_num_threads(1)
    out = {}
    for name in args.sets.split(","):
        obs = observations(name, args.code)
        out[name] = {"views": obs.n_views, "corners": int(obs.corner_mask.sum()),
                     "opencv": time_opencv(obs, args.cv_repeats) if not args.no_opencv else None,
                     "ours": time_ours(obs, args.repeats)}
        print(f"[{os.path.basename(args.code)}] {name}: ours {out[name]['ours']['cpu_s']:.2f} s CPU",
              file=sys.stderr, flush=True)
    print(json.dumps(out))


def run_tree(code: str, args, opencv: bool, repeats: int | None = None) -> dict:
    cmd = [sys.executable, os.path.abspath(__file__), "--child", "--code", code, "--sets", args.sets,
           "--repeats", str(repeats or args.repeats), "--cv-repeats", str(args.cv_repeats)] + \
        ([] if opencv else ["--no-opencv"])
    done = subprocess.run(cmd, check=True, stdout=subprocess.PIPE, text=True, cwd=code)
    return json.loads(done.stdout.strip().splitlines()[-1])


def merged(runs: list) -> dict:
    """One tree's results from several children (one repeat each): the last run's record, its times the medians
    over the runs (`cpu_s_all` every run's)."""
    out = json.loads(json.dumps(runs[-1]))
    for name, rec in out.items():
        cpu = [r[name]["ours"]["cpu_s"] for r in runs]
        rec["ours"].update(cpu_s=statistics.median(cpu), cpu_s_all=cpu, repeats=len(runs),
                           wall_s=statistics.median(r[name]["ours"]["wall_s"] for r in runs))
        if rec["opencv"] is not None:
            rec["opencv"]["cpu_s"] = statistics.median(r[name]["opencv"]["cpu_s"] for r in runs)
            rec["opencv"]["wall_s"] = statistics.median(r[name]["opencv"]["wall_s"] for r in runs)
    return out


def same_results(after: dict, before: dict) -> str:
    """'same' where two checkouts' results on a set agree (choices equal, focal length and principal point within
    `SAME_SIGMA` of their σ), else what differs; with the largest difference in σ."""
    diffs = [k for k in ("distortion", "board", "free_principal_point") if after[k] != before[k]]
    sigma_pp = after["sigma_principal_point_px"] or [math.nan, math.nan]
    triples = [("focal_px", after["focal_px"], before["focal_px"], after["sigma_focal_px"])] + [
        (f"principal_point_px[{i}]", a, b, s) for i, (a, b, s) in
        enumerate(zip(after["principal_point_px"], before["principal_point_px"], sigma_pp))]
    # a held principal point has no σ: then its two values must be equal
    z = {k: abs(a - b) / s if s > 0 else (0.0 if a == b else math.inf) for k, a, b, s in triples}
    diffs += [f"{k} {a:.10g} vs {b:.10g} ({z[k]:.2g} σ)" for k, a, b, _ in triples if not z[k] <= SAME_SIGMA]
    return (f"same (within {max(z.values()):.1g} σ)" if not diffs else "differs: " + ", ".join(diffs))


def markdown(res: dict, args) -> str:
    lines = [f"# Default calibration after detection against OpenCV on real photo sets ({res['date']})", "",
             f"- machine: {res['machine']}; one torch thread; `python benchmarks/calibration/bench_calib_real_speed.py "
             f"--repeats {args.repeats} --cv-repeats {args.cv_repeats} --sets {args.sets}"
             + (f" --base {args.base}" if args.base else "") + "`",
             f"- after: this tree ({res['after_commit']}); before: {res['base'] or 'not measured'}"
             + (f" ({res['before_commit']})" if res.get('before_commit') else ""),
             "- CPU seconds, medians of the repeats (with --base: after and before in turn, one repeat each); ratio = "
             "ours / cv2.calibrateCamera on the same corners, same run",
             "- industrial_60: the 20 shipped industrial views and two noisy copies of each (module docstring)",
             f"- check (with --base): the same distortion, board and principal-point choices, and focal length and "
             f"principal point within {SAME_SIGMA:g} of their σ of before's (the largest difference in σ)", "",
             "| set | views | OpenCV CPU s | ours after CPU s | ratio after | ours before CPU s | ratio before | "
             "after: distortion, board, pp | before: distortion, board, pp | check |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for name, a in res["after"].items():
        b = (res.get("before") or {}).get(name)
        cv = a["opencv"]["cpu_s"]
        desc = lambda o: f"{o['distortion']}, {o['board']}, {'free' if o['free_principal_point'] else 'held'}"  # noqa
        lines.append(f"| {name} | {a['views']} | {cv:.3f} | {a['ours']['cpu_s']:.2f} | {a['ours']['cpu_s'] / cv:.0f}× | "
                     + (f"{b['ours']['cpu_s']:.2f} | {b['ours']['cpu_s'] / cv:.0f}× | " if b else "– | – | ")
                     + f"{desc(a['ours'])} | " + (desc(b["ours"]) if b else "–") + " | "
                     + (res.get("check", {}).get(name, "–")) + " |")
    lines += ["", "Fitted values (focal length and principal point, px, ± σ):", "",
              "| set | after | before | OpenCV |", "|---|---|---|---|"]
    for name, a in res["after"].items():
        b = (res.get("before") or {}).get(name)
        fmt = lambda o: (f"f {o['focal_px']:.2f} ± {o['sigma_focal_px']:.2g}, pp "  # noqa: E731
                         f"({o['principal_point_px'][0]:.2f}, {o['principal_point_px'][1]:.2f}) ± "
                         f"({(o['sigma_principal_point_px'] or [math.nan] * 2)[0]:.2g}, "
                         f"{(o['sigma_principal_point_px'] or [math.nan] * 2)[1]:.2g})")
        cv = a["opencv"]
        lines.append(f"| {name} | {fmt(a['ours'])} | {fmt(b['ours']) if b else '–'} | f {cv['focal_px'][0]:.2f}, pp "
                     f"({cv['principal_point_px'][0]:.2f}, {cv['principal_point_px'][1]:.2f}) |")
    return "\n".join(lines) + "\n"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--cv-repeats", type=int, default=5)
    p.add_argument("--sets", default="gopro_wide,industrial_ds1,industrial_60")
    p.add_argument("--base", default=None, help="another checkout whose code gives the 'before' figures")
    p.add_argument("--name", default="calib_real_speed")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--no-opencv", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--code", default=ROOT, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        child(args)
        return 0
    commit = lambda d: subprocess.run(["git", "-C", d, "rev-parse", "--short", "HEAD"], text=True,  # noqa: E731
                                      stdout=subprocess.PIPE).stdout.strip()
    res = {"date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
           "machine": f"{platform.machine()}, {os.cpu_count()} CPUs (shared)", "base": args.base,
           "after_commit": commit(ROOT)}
    if not args.base:
        res["after"] = run_tree(ROOT, args, opencv=True)
    else:
        # the two trees in turn, one repeat of every set each (the load of a shared machine drifts over minutes)
        after, before = [], []
        for _ in range(args.repeats):
            after.append(run_tree(ROOT, args, opencv=True, repeats=1))
            before.append(run_tree(args.base, args, opencv=False, repeats=1))
        res["after"], res["before"] = merged(after), merged(before)
        res["before_commit"] = commit(args.base)
        res["check"] = {name: same_results(a["ours"], res["before"][name]["ours"]) for name, a in res["after"].items()}
    out = os.path.join(ROOT, "benchmarks", "results", args.name)
    with open(out + ".json", "w", encoding="utf-8") as f:
        json.dump(res, f, indent=1)
    with open(out + ".md", "w", encoding="utf-8") as f:
        f.write(markdown(res, args))
    print(markdown(res, args))
    return 0 if all(v.startswith("same") for v in res.get("check", {}).values()) else 1


if __name__ == "__main__":
    sys.exit(main())
