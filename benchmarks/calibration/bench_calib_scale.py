"""Calibration at scale: time and peak memory of `tiltfit calibrate` against the number of views, with
cv2.calibrateCamera on the same corners as the peer.

Views: synthetic DET files of the paper's designed target (`reproduce.calibration_target`, 40 corners) seen by
the simulated tilt lens (w = 55.39 mm, f = 50.84 mm, d = 18.81 mm, θL = 5°), 1368 × 912 px, random poses at
480–760 mm (seeded), corners with 0.05 px and blur widths with 0.1 px + 3 % Gaussian noise
(`model.synthesize_observations`), as benchmarks/calibration/bench_calib_speed.py's synthetic set but with N views.

Each measurement runs in a fresh child process (so its peak RSS is its own):
- tiltfit: `tiltfit calibrate DET... --target T --pixel-pitch-mm P -q -o CALIB.json` in the child (`cli.main`:
  the defaults a user gets: distortion auto with the 5-fold held-out error, principal-point and θF tests,
  uncertainties);
- OpenCV: cv2.calibrateCamera on the same corners (one focal length, free principal point, k1 k2 p1 p2 k3,
  200 iterations / 1e-12).
Peak RSS is the child's ru_maxrss, its baseline the RSS after the imports (Python, torch, cv2), before reading
the DET files. CPU time (user + system of the child, all threads) and wall time are medians over --repeats at the
sizes up to --repeat-max-views, one run above; CPU time is the figure to compare on a loaded machine.

Writes benchmarks/results/calib_scale.{json,md}. Usage:
    python benchmarks/calibration/bench_calib_scale.py [--sizes 50,200,500,1000,2000] [--repeats 3] [--repeat-max-views 200]
                                           [--threads 1] [--base REV --base-sizes 1000,2000]
"""
from __future__ import annotations

import argparse
import datetime
import glob
import json
import math
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))  # the repository root
from benchmarks.results_io import ROOT, add_output_options, markdown_only, save  # noqa: E402

PITCH_MM = 0.00654 * 4
SIZE_PX = (1368, 912)


def _cpu_s() -> float:
    """CPU time of this process so far (user + system, all threads), seconds."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def write_views(n: int, folder: str) -> tuple[list, str]:
    """n synthetic DET files and their target file in `folder` (written once, seeded): bench_calib_speed's
    synthetic tilted capture, n views."""
    from benchmarks.calibration.bench_calib_speed import write_synthetic_views

    return write_synthetic_views(n, folder, SIZE_PX)


# --------------------------------------------------------------------------------------------- the children

def child_tiltfit(folder: str) -> dict:
    import torch  # noqa: F401  (imports before the baseline)

    from tiltfit.cli import main as cli

    base = _rss_mb()
    dets = sorted(glob.glob(os.path.join(folder, "view*.json")))
    out = os.path.join(tempfile.mkdtemp(), "calib.json")
    t0, c0 = time.perf_counter(), _cpu_s()
    rc = cli.main(["calibrate", *dets, "--target", os.path.join(folder, "target.json"), "--pixel-pitch-mm",
                   str(PITCH_MM), "-q", "-o", out])
    wall, cpu = time.perf_counter() - t0, _cpu_s() - c0
    res = {"rc": rc, "wall_s": wall, "cpu_s": cpu, "baseline_rss_mb": base,
           "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}
    if rc == 0:
        with open(out) as f:
            data = json.load(f)
        res.update(f_px=data["w_mm"] / data["pixel_pitch_mm"], rms_px=data["rms_reprojection_px"],
                   distortion_model=data.get("distortion_model"))
    return res


def child_opencv(folder: str) -> dict:
    import cv2
    import numpy as np
    import torch  # noqa: F401  (the same imports as the tiltfit child, for a comparable baseline)

    from tiltfit.target.layout import load_target

    base = _rss_mb()
    pts = np.asarray(load_target(os.path.join(folder, "target.json")).feature_points(), dtype=np.float32)
    t0, c0 = time.perf_counter(), _cpu_s()
    obj, img = [], []
    for p in sorted(glob.glob(os.path.join(folder, "view*.json"))):
        with open(p) as f:
            c = np.array([q if q is not None else [np.nan, np.nan] for q in json.load(f)["corners_px"]])
        m = np.isfinite(c).all(1)
        obj.append(pts[m])
        img.append(c[m].astype(np.float32))
    W, H = SIZE_PX
    K0 = np.array([[1.0, 0, (W - 1) / 2], [0, 1.0, (H - 1) / 2], [0, 0, 1]])
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    rms, K, dist, _, _ = cv2.calibrateCamera(obj, img, (W, H), K0, None, flags=cv2.CALIB_FIX_ASPECT_RATIO,
                                             criteria=crit)
    wall, cpu = time.perf_counter() - t0, _cpu_s() - c0
    return {"rc": 0, "wall_s": wall, "cpu_s": cpu, "baseline_rss_mb": base, "f_px": float(K[0, 0]), "rms_px": float(rms),
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def run_child(kind: str, folder: str, timeout_s: float, threads: int, code: str = ROOT) -> dict:
    """Run a measurement in a fresh process with the package of `code` (a checkout's root) first on the path."""
    env = dict(os.environ, PYTHONPATH=code + os.pathsep + os.environ.get("PYTHONPATH", ""), PYTHONDONTWRITEBYTECODE="1")
    if threads:
        env.update(OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads))
    cmd = [sys.executable, os.path.abspath(__file__), "--child", kind, "--folder", folder]
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return {"rc": "timeout", "wall_s": timeout_s}
    if p.returncode != 0:
        return {"rc": p.returncode, "error": (p.stderr.strip().splitlines() or ["?"])[-1]}
    return json.loads(p.stdout.strip().splitlines()[-1])


# --------------------------------------------------------------------------------------------- the table

def extract(rev: str) -> str:
    """The code of git revision `rev`, extracted into a temporary folder (`git archive`)."""
    out = tempfile.mkdtemp(prefix="bench_calib_scale_base_")
    archive = subprocess.run(["git", "-C", ROOT, "archive", rev], capture_output=True, check=True).stdout
    subprocess.run(["tar", "-x", "-C", out], input=archive, check=True)
    return out


def write_markdown(path: str, res: dict) -> None:
    lines = ["# Calibration at scale: time and memory against the number of views", "",
             f"{res['date']}, {res['machine']}; `python benchmarks/calibration/bench_calib_scale.py "
             f"--sizes {','.join(str(r['views']) for r in res['rows'])}"
             f"{' --base ' + res['base']['rev'] if res.get('base') else ''}`. Synthetic views of the paper's target "
             "(40 corners, blur widths), `tiltfit calibrate` with its defaults (distortion auto with the 5-fold "
             "held-out error, model selection, uncertainties) and cv2.calibrateCamera (k1 k2 p1 p2 k3) on the same "
             "corners, each in a fresh process. CPU: the process's user + system time for the calibration (its "
             "threads together; robust to other load on the machine), wall beside it; medians of the repeats (n). "
             f"Load average at the start: {res.get('load', '?')}; OMP/MKL threads per process: "
             f"{res.get('threads') or 'default'}. Peak RSS: the process's maximum resident memory "
             "(baseline: after the imports).", "",
             "| views | tiltfit CPU (s) | wall (s) | n | OpenCV CPU (s) | ratio (CPU) | tiltfit peak RSS (MB) | "
             "baseline (MB) | OpenCV peak RSS (MB) | f tiltfit / OpenCV (px) | RMS tiltfit / OpenCV (px) |",
             "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---|"]
    for r in res["rows"]:
        t, o = r["tiltfit"], r["opencv"]
        if t.get("rc") != 0:
            lines.append(f"| {r['views']} | failed: {t.get('error', t.get('rc'))} | | | {o.get('cpu_s', 0):.2f} | | | | "
                         f"{o.get('peak_rss_mb', 0):.0f} | | |")
            continue
        lines.append(f"| {r['views']} | {t['cpu_s']:.1f} | {t['wall_s']:.1f} | {r['repeats']} | {o['cpu_s']:.2f} | "
                     f"{t['cpu_s'] / o['cpu_s']:.0f} | {t['peak_rss_mb']:.0f} | {t['baseline_rss_mb']:.0f} | "
                     f"{o['peak_rss_mb']:.0f} | {t['f_px']:.2f} / {o['f_px']:.2f} | "
                     f"{t['rms_px']:.4f} / {o['rms_px']:.4f} |")
    if res.get("base"):
        lines += ["", f"Before ({res['base']['rev']}: the covariance as a (P, P) matrix, the blur scan's whole table), "
                  "the same child on the same DET files in the same run:", "",
                  "| views | CPU (s) before → now | peak RSS (MB) before → now | same f and RMS |", "|---:|---|---|---|"]
        now = {r["views"]: r["tiltfit"] for r in res["rows"]}
        for n, b in sorted(res["base"]["rows"].items(), key=lambda kv: int(kv[0])):
            t = now.get(int(n), {})
            if b.get("rc") != 0:
                lines.append(f"| {n} | failed ({b.get('error', b.get('rc'))}) → {t.get('cpu_s', 0):.1f} | → "
                             f"{t.get('peak_rss_mb', 0):.0f} | |")
                continue
            same = "yes" if (abs(b["f_px"] - t.get("f_px", math.inf)) < 1e-6
                             and abs(b["rms_px"] - t.get("rms_px", math.inf)) < 1e-9) else "no"
            lines.append(f"| {n} | {b['cpu_s']:.1f} → {t.get('cpu_s', 0):.1f} | {b['peak_rss_mb']:.0f} → "
                         f"{t.get('peak_rss_mb', 0):.0f} | {same} |")
    lines += ["", "OpenCV fits one model once; `tiltfit calibrate` fits five distortion models on five held-out "
              "folds each, then the chosen model with and without the principal point and θF, with blur widths and "
              "uncertainties, so the ratio is the price of those defaults, not of one solve.", ""]
    with open(path, "w") as f:
        f.write("\n".join(lines))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="50,200,500,1000,2000", help="view counts, comma-separated")
    ap.add_argument("--repeats", type=int, default=3, help="repeats at the small sizes [3]")
    ap.add_argument("--repeat-max-views", type=int, default=200, help="sizes above this run once [200]")
    ap.add_argument("--cache", default=os.path.join(tempfile.gettempdir(), "bench_calib_scale"),
                    help="where the synthetic DET files are kept")
    ap.add_argument("--timeout-s", type=float, default=3600.0, help="per child process [3600]")
    ap.add_argument("--threads", type=int, default=1,
                    help="OMP/MKL threads of the children [1]; 0 keeps the defaults (on a loaded machine torch's "
                         "spinning threads then cost more than they give: 14.6 s of CPU at 50 views instead of 1.3)")
    ap.add_argument("--base", help="git revision whose code is measured too, at --base-sizes (before/after)")
    ap.add_argument("--base-sizes", default="1000,2000", help="view counts of the --base runs [1000,2000]")
    ap.add_argument("--child", choices=("tiltfit", "opencv"), help=argparse.SUPPRESS)
    ap.add_argument("--folder", help=argparse.SUPPRESS)
    add_output_options(ap, "calib_scale")
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(child_tiltfit(args.folder) if args.child == "tiltfit" else child_opencv(args.folder)))
        return 0
    if markdown_only(args, write_markdown):
        return 0
    res_load = " / ".join(f"{x:.1f}" for x in os.getloadavg())
    rows = []
    for n in [int(s) for s in args.sizes.split(",")]:
        folder = os.path.join(args.cache, f"views{n}")
        write_views(n, folder)
        reps = args.repeats if n <= args.repeat_max_views else 1
        runs = {"tiltfit": [], "opencv": []}
        for _ in range(reps):
            for kind in ("opencv", "tiltfit"):
                runs[kind].append(run_child(kind, folder, args.timeout_s, args.threads))
                print(f"[bench_calib_scale] {n} views, {kind}: {runs[kind][-1]}", file=sys.stderr, flush=True)
        row = {"views": n, "repeats": reps}
        for kind, rs in runs.items():
            ok = [r for r in rs if r.get("rc") == 0]
            if not ok:
                row[kind] = rs[-1]
                continue
            row[kind] = dict(ok[-1], wall_s=statistics.median(r["wall_s"] for r in ok),
                             cpu_s=statistics.median(r["cpu_s"] for r in ok),
                             peak_rss_mb=max(r["peak_rss_mb"] for r in ok), walls_s=[r["wall_s"] for r in ok])
        rows.append(row)
    base = None
    if args.base:
        code = extract(args.base)
        base = {"rev": args.base, "rows": {}}
        for n in [int(s) for s in args.base_sizes.split(",")]:
            base["rows"][str(n)] = r = run_child("tiltfit", os.path.join(args.cache, f"views{n}"), args.timeout_s,
                                                 args.threads, code)
            print(f"[bench_calib_scale] {n} views, tiltfit at {args.base}: {r}", file=sys.stderr, flush=True)
    import cv2
    import torch

    res = {"date": datetime.date.today().isoformat(),
           "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPU cores, "
                      f"torch {torch.__version__}, OpenCV {cv2.__version__}",
           "load": res_load, "threads": args.threads, "rows": rows, "base": base}
    save(args.out, res, write_markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
