"""Photometric refinement before and after its redesign: time and accuracy in one run, the corner fit as reference.

Two parts, each run by the code of two trees in subprocesses (`--before REV`, extracted with `git archive`, and
this checkout), on the same machine in the same run:

1. speed: ray-traced captures (`synth.render_view(method="renderer")`, 64 spp, sensor noise 0.003) of the 6 x 4
   board of 50 mm cells, 3 views (`reproduce.TARGET_VIEWS` 0-2) at 342 x 228 (1/16 of the EOS 6D), lens tilted
   by θL 4.65°, blur discs of 18 px; the photometric fit with its defaults (2000 pixels a view) started from a
   corner fit's quality of start (pose 0.1°/0.5 mm, w +0.3 %, U +1 %, d −3 %, θL +0.1°), and its accuracy over
   `--seeds` choices of the pixels (the selection's seed). Wall and CPU seconds,
   median of `--repeats` fits after one warm-up (imports), one torch thread; the corner fit (detection of
   the three views + the joint fit) timed the same way in the same process as the reference.
2. accuracy on the quick reproduce captures: `tiltfit reproduce --quick` run by each tree; the photometric
   and the joint corner fits' errors against the simulated camera's true lens states (θL, θF, w, U, d) and
   their run times, and whether Tables 1 and 2 (table1.md, table2.md) are the same.

    python benchmarks/history/bench_photometric_speed.py [--before REV] [--repeats N] [--no-reproduce]

writes benchmarks/results/photometric_speed.{md,json}.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import pickle
import statistics
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))  # benchmarks/
ROOT = os.path.dirname(HERE)
RESULTS = os.path.join(HERE, "results")
W_MM, D_MM, THETA_L_DEG, U0_MM, DOWNSCALE, VIEWS = 55.39, 40.0, 4.65, 1000.0, 16, (0, 1, 2)


def _board():
    from tiltfit.target.layout import Target

    return Target(tuple(50.0 * i for i in range(7)), tuple(50.0 * j for j in range(5)), (0, 0), 25.0)


def make_captures(path: str) -> None:
    """Ray-traced captures, their true poses and lens, and the start (pickled for the workers)."""
    import cv2
    import numpy as np

    from renderer.cameras import optics
    from tiltfit.experiments import synth
    from tiltfit.experiments import reproduce

    board = _board()
    from renderer import Lens
    from renderer.cameras import EOS_6D

    sensor = EOS_6D.binned(DOWNSCALE)
    w_px, h_px, pitch = *sensor.size_px, sensor.pixel_pitch
    f_mm = float(optics.focal_length(W_MM, U0_MM))
    cam = Lens.from_tilt(W_MM, f_mm, math.radians(THETA_L_DEG), D_MM, sensor=sensor)
    images, poses = [], []
    for k, i in enumerate(VIEWS):
        R, T = reproduce.target_pose(board, *reproduce.TARGET_VIEWS[i])
        view = synth.render_view(board, cam, R, T, method="renderer", spp=64, noise_sigma=0.003, seed=k)
        images.append(view.image[..., 0].astype(np.float64))
        poses.append((R, T))
    rng = np.random.default_rng(1)
    w, U = W_MM * 1.003, cam.U * 1.01
    theta_F = optics.theta_F_from_theta_L(math.radians(THETA_L_DEG + 0.1), w, U)
    start = {"w_mm": w, "U_mm": U, "d_mm": D_MM * 0.97, "theta_F_deg": math.degrees(float(theta_F)),
             "views": [{"R": cv2.Rodrigues(rng.normal(0, math.radians(0.1), 3))[0] @ R,
                        "T_mm": T + rng.normal(0, 0.5, 3)} for R, T in poses]}
    truth = {"w_mm": W_MM, "U_mm": cam.U, "d_mm": D_MM, "theta_L_deg": THETA_L_DEG,
             "theta_F_deg": math.degrees(cam.theta_F)}
    with open(path, "wb") as f:
        pickle.dump({"images": images, "start": start, "truth": truth, "pitch": pitch, "size": (w_px, h_px)}, f)


def errors(values: dict, truth: dict) -> dict:
    return {"theta_L_err_deg": values["theta_L_deg"] - truth["theta_L_deg"],
            "theta_F_err_deg": values["theta_F_deg"] - truth["theta_F_deg"],
            "w_err_pct": 100 * (values["w_mm"] / truth["w_mm"] - 1),
            "U_err_pct": 100 * (values["U_mm"] / truth["U_mm"] - 1),
            "d_err_pct": 100 * (values["d_mm"] / truth["d_mm"] - 1)}


def worker(captures: str, repeats: int, seeds: int) -> None:
    """In the tree on PYTHONPATH: the corner fit and the photometric fit, timed; one JSON line on stdout."""
    import inspect

    import numpy as np
    import torch

    torch.set_num_threads(1)
    from tiltfit.calibrate.flow import calibrate
    from tiltfit.detect.chessboard import detect
    from tiltfit.calibrate.fit import FitOptions
    from tiltfit.calibrate.model import Observations
    from tiltfit.photometric import PhotometricOptions, refine_photometric

    with open(captures, "rb") as f:
        cap = pickle.load(f)
    board, images = _board(), cap["images"]

    def corner_fit():
        dets = [detect(im, board) for im in images]
        obs = Observations(board.feature_points(), np.stack([d.corners_px for d in dets]),
                           np.stack([d.blur_px for d in dets]), cap["size"], cap["pitch"])
        return calibrate(obs, "joint", options=FitOptions(model_selection=False, nominal_focal_mm=55.0))

    new_api = "camera" in inspect.signature(refine_photometric).parameters
    if new_api:
        from tiltfit.files.calib import camera_from_calib

        camera = camera_from_calib({**cap["start"], "image_size_px": cap["size"], "pixel_pitch_mm": cap["pitch"]})

    def photometric(seed: int = 0):
        if new_api:
            return refine_photometric(images, board, camera, PhotometricOptions(seed=seed))
        return refine_photometric(images, board, cap["start"], cap["pitch"], PhotometricOptions(seed=seed))

    out = {"api": "camera" if new_api else "init dict"}
    for name, fn in (("corner_fit", corner_fit), ("photometric", photometric)):
        fn()   # warm-up: imports, caches
        walls, cpus = [], []
        for _ in range(repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            res = fn()
            walls.append(time.perf_counter() - t0)
            cpus.append(time.process_time() - c0)
        out[name] = {"wall_s": statistics.median(walls), "cpu_s": statistics.median(cpus), "walls": walls,
                     **errors(res.values, cap["truth"])}
        if name == "photometric":
            out[name].update(iterations=res.iterations, rms=res.rms,
                             sigma_theta_L_deg=res.sigma["theta_L_deg"], sigma_d_pct=100 * res.sigma["d_mm"] / D_MM)
    # The pixels are a random choice among the edge and flat pixels: the errors over other choices (seeds).
    out["seeds"] = [errors(photometric(seed).values, cap["truth"]) for seed in range(1, seeds)]
    print(json.dumps(out))


def run_tree(tree: str, args: list[str], cwd: str | None = None) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": tree, "OMP_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, *args], env=env, cwd=cwd or tree, capture_output=True, text=True)


def reproduce_accuracy(tree: str, out_dir: str) -> dict:
    """`tiltfit reproduce --quick` by `tree`: per lens state the joint and photometric errors and times."""
    t0 = time.perf_counter()
    p = run_tree(tree, ["-m", "tiltfit", "reproduce", "--quick", "-o", out_dir])
    if p.returncode != 0:
        raise RuntimeError(f"reproduce in {tree} failed: {p.stderr[-2000:]}")
    with open(os.path.join(out_dir, "run.json")) as f:
        run = json.load(f)
    states = run["truth"]["lens_states"]
    rows = []
    for label, rec in run["calibration"].items():
        state = "a" if label == "stage1" else label
        truth = states[state]
        for method, r in (("corners + blur", rec if label == "stage1" else rec.get("joint")),
                          ("photometric", rec.get("photometric"))):
            if r:
                rows.append({"state": state, "method": method, "runtime_s": r.get("runtime_s"), **errors(r, truth)})
    tables = {}
    for name in ("table1.md", "table_stage1.md", "table2.md"):
        path = os.path.join(out_dir, name)
        tables[name] = open(path).read() if os.path.exists(path) else None
    return {"rows": rows, "tables": tables, "seconds": time.perf_counter() - t0}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", default="c6c763c", help="git revision of the code before [c6c763c]")
    ap.add_argument("--repeats", type=int, default=3, help="timed fits per tree after a warm-up [3]")
    ap.add_argument("--seeds", type=int, default=6, help="pixel-selection seeds of the accuracy over seeds [6]")
    ap.add_argument("--no-reproduce", action="store_true", help="leave out the reproduce --quick accuracy part")
    ap.add_argument("--worker", metavar="CAPTURES", help=argparse.SUPPRESS)
    ap.add_argument("--out", default=RESULTS, help="results folder [benchmarks/results]")
    args = ap.parse_args(argv)
    if args.worker:
        worker(args.worker, args.repeats, args.seeds)
        return 0
    sys.path.insert(0, ROOT)
    tmp = tempfile.mkdtemp(prefix="bench_photometric_speed_")
    before = os.path.join(tmp, "before")
    os.makedirs(before)
    archive = subprocess.run(["git", "-C", ROOT, "archive", args.before, "renderer", "tiltfit", "benchmarks"],
                             capture_output=True, check=True).stdout
    subprocess.run(["tar", "-x", "-C", before], input=archive, check=True)
    rev = subprocess.run(["git", "-C", ROOT, "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    caps = os.path.join(tmp, "captures.pkl")
    make_captures(caps)
    trees = {"before": before, "after": ROOT}
    result = {"before": args.before, "after": rev, "repeats": args.repeats, "speed": {}, "reproduce": {}}
    for label, tree in trees.items():
        p = run_tree(tree, [os.path.abspath(__file__), "--worker", caps, "--repeats", str(args.repeats),
                                 "--seeds", str(args.seeds)], cwd=ROOT)
        if p.returncode != 0:
            raise RuntimeError(f"{label}: {p.stderr[-2000:]}")
        result["speed"][label] = json.loads(p.stdout.strip().splitlines()[-1])
        print(label, json.dumps(result["speed"][label]), flush=True)
    if not args.no_reproduce:
        for label, tree in trees.items():
            result["reproduce"][label] = reproduce_accuracy(tree, os.path.join(tmp, f"reproduce_{label}"))
            print(label, "reproduce", f"{result['reproduce'][label]['seconds']:.0f} s", flush=True)
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "photometric_speed.json"), "w") as f:
        json.dump(result, f, indent=1)
    with open(os.path.join(args.out, "photometric_speed.md"), "w") as f:
        f.write(report(result))
    print(report(result))
    return 0


def report(result: dict) -> str:
    lines = ["# Photometric refinement before and after the redesign (same machine, same run)", "",
             f"Before: {result['before']}; after: {result['after']}. `python benchmarks/history/bench_photometric_speed.py`. "
             f"One torch thread; median of {result['repeats']} fits after a warm-up; the machine's 2 cores are "
             "shared with other jobs, so CPU seconds are the steadier measure.", "",
             "## Speed: 3 views at 342 x 228, blur discs 18 px, θL 4.65°, 2000 pixels a view", "",
             "| code | corner fit wall s | photometric wall s | photometric CPU s | photometric / corner fit (wall) "
             "| θL err ° | σ θL ° | θF err ° | w err % | U err % | d err % | iterations |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for label, s in result["speed"].items():
        c, p = s["corner_fit"], s["photometric"]
        lines.append(f"| {label} | {c['wall_s']:.2f} | {p['wall_s']:.2f} | {p['cpu_s']:.2f} | "
                     f"{p['wall_s'] / c['wall_s']:.1f} | {p['theta_L_err_deg']:+.4f} | {p['sigma_theta_L_deg']:.4f} | "
                     f"{p['theta_F_err_deg']:+.3f} | {p['w_err_pct']:+.3f} | {p['U_err_pct']:+.3f} | "
                     f"{p['d_err_pct']:+.3f} | {p['iterations']} |")
    lines += ["", f"Over the pixel choice (seeds 0-{len(next(iter(result['speed'].values()))['seeds'])} of the selection "
              "among edge and flat pixels), RMS and mean error:", "",
              "| code | θL RMS ° (mean) | θF RMS ° (mean) | w RMS % (mean) | U RMS % (mean) | d RMS % (mean) |",
              "|---|---|---|---|---|---|"]
    for label, s in result["speed"].items():
        runs = [{k: s["photometric"][k] for k in s["seeds"][0]}] + s["seeds"] if s["seeds"] else []
        cells = []
        for key in ("theta_L_err_deg", "theta_F_err_deg", "w_err_pct", "U_err_pct", "d_err_pct"):
            x = [r[key] for r in runs]
            cells.append(f"{math.sqrt(sum(v * v for v in x) / len(x)):.4f} ({sum(x) / len(x):+.4f})")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines += ["", "| code | corner fit | θL err ° | θF err ° | w err % | U err % | d err % |", "|---|---|---|---|---|---|---|"]
    c = result["speed"].get("after", {}).get("corner_fit")
    if c:
        lines.append(f"| after | detection + joint fit (the reference) | {c['theta_L_err_deg']:+.4f} | "
                     f"{c['theta_F_err_deg']:+.3f} | {c['w_err_pct']:+.3f} | {c['U_err_pct']:+.3f} | {c['d_err_pct']:+.3f} |")
    if result["reproduce"]:
        lines += ["", "## Accuracy on the quick reproduce captures (`tiltfit reproduce --quick`: 684 x 456, 5 views a "
                  "lens state, 800 pixels a view, 32 lens samples)", "",
                  "| code | state | method | θL err ° | θF err ° | w err % | U err % | d err % | seconds |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for label, rep in result["reproduce"].items():
            for r in rep["rows"]:
                lines.append(f"| {label} | {r['state']} | {r['method']} | {r['theta_L_err_deg']:+.4f} | "
                             f"{r['theta_F_err_deg']:+.4f} | {r['w_err_pct']:+.4f} | {r['U_err_pct']:+.4f} | "
                             f"{r['d_err_pct']:+.4f} | {r['runtime_s']:.2f} |")
        b, a = result["reproduce"].get("before", {}), result["reproduce"].get("after", {})
        for name in ("table1.md", "table_stage1.md", "table2.md"):
            same = b.get("tables", {}).get(name) == a.get("tables", {}).get(name)
            lines.append(f"\n{name}: {'identical' if same else 'differs (see photometric_speed.json)'} before and after.")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
