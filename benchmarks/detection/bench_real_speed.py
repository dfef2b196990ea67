"""Detection speed on all shipped real photo sets, against OpenCV and against an earlier revision of tiltfit,
image by image in one run.

Sets: data/real/gopro_wide (36 GoPro JPEGs, 8 × 6 corners) and data/real/industrial_ds1 (20 PNGs, 1280 × 1024,
16 × 10 corners). Per image, interleaved (so every method sees the same machine load):
- `ours`: `tiltfit.detect.chessboard.detect` as `tiltfit detect` runs it (corners and blur widths), on the image decoded to
  linear by `camio.files.read_image`; and `ours_corners`: the same with `measure_blur=False`.
- `sb`: `cv2.findChessboardCornersSB` (NORMALIZE_IMAGE | EXHAUSTIVE | ACCURACY) on the 8-bit grey image, and
  `sb_subpix`: the same + `cv2.cornerSubPix` (5 × 5), i.e. `tiltfit.detect.opencv.sb_corners`.
- `base` (with `--baseline-rev REV`): `detect` of tiltfit at git revision REV (extracted with `git archive`),
  in a worker process fed one image at a time; its corners and blur widths are compared with ours.
One torch thread and one OpenCV thread everywhere. Times exclude file decoding; each is the median over
`--repeats` runs (`--baseline-repeats` for the revision), as wall-clock and as process CPU time (the CPU time
is the steadier figure on a shared machine). Tables give medians over the images and ratios of those medians.
Corner agreement with SB + cornerSubPix is measured after matching the labelling (both boards look the same
turned by 180°).

Writes benchmarks/results/real_speed_detect.{json,md}. Usage:
    python benchmarks/detection/bench_real_speed.py [--repeats 3] [--baseline-rev fc99d87] [--sets gopro_wide,...]
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile

import cv2
import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))  # the repository root: benchmarks.results_io
from benchmarks.results_io import add_output_options, markdown_only, save, timed  # noqa: E402
from camio.files import read_image  # noqa: E402
from tiltfit.detect.chessboard import detect  # noqa: E402
from tiltfit.detect.opencv import match_labelling  # noqa: E402
from tiltfit.target.layout import load_target  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SETS = {"gopro_wide": "*.jpg", "industrial_ds1": "*.png"}
SB_FLAGS = cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 1e-3)

# The revision's worker: reads {"path", "target", "repeats"} lines, answers one JSON line per image.
WORKER = r"""
import json, statistics, sys, time
import torch
torch.set_num_threads(1)
from camio.files import read_image
from tiltfit.detect.chessboard import detect
from tiltfit.target.layout import load_target
print(json.dumps({"ready": True}), flush=True)
for line in sys.stdin:
    job = json.loads(line)
    target, image = load_target(job["target"]), read_image(job["path"])
    wall, cpu = [], []
    for _ in range(job["repeats"]):
        t0, c0 = time.perf_counter(), time.process_time()
        det = detect(image, target)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    nan = lambda a: [None if x != x else float(x) for x in a]
    print(json.dumps({"wall_s": statistics.median(wall), "cpu_s": statistics.median(cpu), "found": det.grid_found,
                      "corners": [nan(c) for c in det.corners_px.tolist()], "blur": nan(det.blur_px.tolist()),
                      "sigma": nan(det.blur_sigma_px.tolist()), "stages_s": det.timings_s}), flush=True)
"""


class Baseline:
    """tiltfit at a git revision, in a worker process (its own copy of `tiltfit` and `renderer`)."""

    def __init__(self, rev: str):
        self.dir = tempfile.mkdtemp(prefix="tiltfit_base_")
        archive = subprocess.run(["git", "-C", ROOT, "archive", rev, "tiltfit", "renderer"], check=True,
                                 capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", self.dir], input=archive, check=True)
        self.rev = subprocess.run(["git", "-C", ROOT, "rev-parse", "--short", rev], check=True, capture_output=True,
                                  text=True).stdout.strip()
        env = {**os.environ, "PYTHONPATH": self.dir, "OMP_NUM_THREADS": "1"}
        self.proc = subprocess.Popen([sys.executable, "-c", WORKER], cwd=self.dir, env=env, stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True)
        assert json.loads(self.proc.stdout.readline())["ready"], "baseline worker did not start"

    def detect(self, path: str, target_path: str, repeats: int) -> dict:
        self.proc.stdin.write(json.dumps({"path": path, "target": target_path, "repeats": repeats}) + "\n")
        self.proc.stdin.flush()
        return json.loads(self.proc.stdout.readline())

    def close(self):
        self.proc.stdin.close()
        self.proc.wait()
        shutil.rmtree(self.dir, ignore_errors=True)


def sb(gray8, pattern):
    ok, c = cv2.findChessboardCornersSB(gray8, pattern, flags=SB_FLAGS)
    return c if ok else None


def sb_subpix(gray8, pattern):
    c = sb(gray8, pattern)
    if c is None:
        return None
    return cv2.cornerSubPix(gray8, c.astype(np.float32), (5, 5), (-1, -1), SUBPIX_CRITERIA).reshape(-1, 2).astype(
        np.float64)


def stats(e) -> dict:
    e = np.asarray(e, dtype=np.float64)
    e = e[np.isfinite(e)]
    if e.size == 0:
        return {}
    return {"n": int(e.size), "median": round(float(np.median(e)), 4), "p95": round(float(np.percentile(e, 95)), 4),
            "p99": round(float(np.percentile(e, 99)), 4), "max": round(float(e.max()), 4)}


def run_set(name: str, args, base: Baseline | None) -> dict:
    folder = os.path.join(ROOT, "data", "real", name)
    target_path = os.path.join(folder, "target.json")
    target = load_target(target_path)
    ny, nx = target.grid_shape
    pattern = (nx, ny)
    paths = sorted(glob.glob(os.path.join(folder, SETS[name])))[:: args.every]
    rows, agree, vs_base_corner, vs_base_blur_z, vs_base_blur_px = [], [], [], [], []
    for path in paths:
        linear = read_image(path)
        gray8 = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
        row = {"image": os.path.basename(path)}
        det, row["ours_wall_s"], row["ours_cpu_s"] = timed(lambda: detect(linear, target), args.repeats)
        row["ours_stages_s"] = {k: round(v, 4) for k, v in det.timings_s.items()}
        dc, row["ours_corners_wall_s"], row["ours_corners_cpu_s"] = timed(
            lambda: detect(linear, target, measure_blur=False), args.repeats)
        c_sb, row["sb_wall_s"], row["sb_cpu_s"] = timed(lambda: sb(gray8, pattern), args.repeats)
        c_sp, row["sb_subpix_wall_s"], row["sb_subpix_cpu_s"] = timed(lambda: sb_subpix(gray8, pattern), args.repeats)
        row.update(ours_found=bool(det.grid_found), ours_corners=int(det.found.sum()), sb_found=c_sb is not None)
        assert np.array_equal(np.isfinite(dc.corners_px), np.isfinite(det.corners_px)), "corners with/without blur"
        if det.grid_found and c_sp is not None:
            e, same = match_labelling(det.corners_px, c_sp)
            e = e[np.isfinite(e)]
            agree.append(e)
            row.update(sb_median_px=round(float(np.median(e)), 4), sb_max_px=round(float(e.max()), 4),
                       sb_labelling_same=same)
        if base is not None:
            b = base.detect(path, target_path, args.baseline_repeats)
            row.update(base_wall_s=b["wall_s"], base_cpu_s=b["cpu_s"], base_found=bool(b["found"]),
                       base_stages_s={k: round(v, 4) for k, v in b["stages_s"].items()})
            bc = np.array([[np.nan, np.nan] if c[0] is None else c for c in b["corners"]], dtype=np.float64)
            bb = np.array([np.nan if x is None else x for x in b["blur"]], dtype=np.float64)
            bs = np.array([np.nan if x is None else x for x in b["sigma"]], dtype=np.float64)
            row["base_same_corners_found"] = bool(np.array_equal(np.isfinite(bc).all(1), det.found))
            if det.grid_found and b["found"]:
                both = np.isfinite(bc).all(1) & det.found
                d = np.hypot(*(bc[both] - det.corners_px[both]).T)
                vs_base_corner.append(d)
                ok = np.isfinite(bb) & np.isfinite(det.blur_px) & (bs > 0)
                row["base_same_blur_measured"] = bool(np.array_equal(np.isfinite(bb), np.isfinite(det.blur_px)))
                vs_base_blur_z.append(np.abs(det.blur_px[ok] - bb[ok]) / bs[ok])
                vs_base_blur_px.append(np.abs(det.blur_px[ok] - bb[ok]))
                row["base_corner_max_px"] = float(d.max()) if d.size else 0.0
        rows.append(row)
        print(f"{name}/{row['image']}: ours {row['ours_corners']} corners {row['ours_wall_s']:.2f} s "
              f"({row['ours_cpu_s']:.2f} s CPU), corners only {row['ours_corners_wall_s']:.2f} s; SB "
              f"{row['sb_found']} {row['sb_wall_s']:.2f} s ({row['sb_cpu_s']:.2f} s CPU)"
              + (f"; base {row['base_wall_s']:.2f} s ({row['base_cpu_s']:.2f} s CPU)" if base else ""), flush=True)

    def med(key):
        v = [r[key] for r in rows if key in r]
        return round(statistics.median(v), 4) if v else None

    times = {m: {"wall_s": med(f"{m}_wall_s"), "cpu_s": med(f"{m}_cpu_s")}
             for m in ("ours", "ours_corners", "sb", "sb_subpix", "base")}
    ratio = {}
    for m in ("ours", "ours_corners", "base"):
        for peer in ("sb", "sb_subpix"):
            for clock in ("wall_s", "cpu_s"):
                if times[m][clock] and times[peer][clock]:
                    ratio[f"{m}/{peer} ({clock[:-2]})"] = round(times[m][clock] / times[peer][clock], 3)
    summary = {
        "images": len(rows), "pattern": list(pattern),
        "found": {"ours": sum(r["ours_found"] for r in rows), "sb": sum(r["sb_found"] for r in rows),
                  "base": sum(r.get("base_found", False) for r in rows) if base else None},
        "ours_corners_total": sum(r["ours_corners"] for r in rows),
        "time_median": times, "ratio": ratio,
        "agreement_sb_subpix_px": stats(np.concatenate(agree)) if agree else {},
        "views_both_sb": len(agree),
    }
    if base is not None:
        summary["vs_base"] = {
            "same_boards": all(r.get("base_found") == r["ours_found"] for r in rows),
            "same_corners_found": all(r.get("base_same_corners_found", False) for r in rows),
            "corner_diff_px": stats(np.concatenate(vs_base_corner)) if vs_base_corner else {},
            "blur_diff_over_sigma": stats(np.concatenate(vs_base_blur_z)) if vs_base_blur_z else {},
            "blur_points_over_1_sigma": int((np.concatenate(vs_base_blur_z) > 1).sum()) if vs_base_blur_z else 0,
            "blur_points_over_3_sigma": int((np.concatenate(vs_base_blur_z) > 3).sum()) if vs_base_blur_z else 0,
            "blur_diff_px": stats(np.concatenate(vs_base_blur_px)) if vs_base_blur_px else {},
            "same_blur_measured": all(r.get("base_same_blur_measured", True) for r in rows),
        }
        for clock in ("wall_s", "cpu_s"):
            if times["base"][clock]:
                summary["ratio"][f"base/ours ({clock[:-2]})"] = round(times["base"][clock] / times["ours"][clock], 3)
    return {"summary": summary, "rows": rows}


def write_markdown(path: str, res: dict) -> None:
    base = res.get("baseline_rev")
    md = ["# Detection speed on the shipped real photos, against OpenCV" + (f" and tiltfit {base}" if base else ""),
          "",
          f"`{res['command']}` — one torch thread and one OpenCV thread; per image the median of "
          f"{res['repeats']} runs ({res['baseline_repeats']} for the revision), file decoding excluded; the table "
          "gives the median over the images. Wall-clock and process CPU time (the machine was shared: load "
          f"average {res['load_before'][0]:.1f} before, {res['load_after'][0]:.1f} after, on "
          f"{res['machine']['cpu_count']} cores; the CPU time is the steadier figure). Ratios are of the medians.",
          ""]
    for name, s in ((k, v["summary"]) for k, v in res["sets"].items()):
        t, r = s["time_median"], s["ratio"]
        md += [f"## {name} ({s['images']} images, {s['pattern'][0]} × {s['pattern'][1]} corners)", "",
               "| method | boards found | time / image, wall | CPU | / SB (wall, CPU) "
               "| / SB + cornerSubPix (wall, CPU) |",
               "|---|---|---|---|---|---|"]

        def line(label, m, found):
            if not t[m]["wall_s"]:
                return
            cells = [f"{r.get(f'{m}/{p} (wall)', '')}, {r.get(f'{m}/{p} (cpu)', '')}" for p in ("sb", "sb_subpix")]
            md.append(f"| {label} | {found} | {t[m]['wall_s']:.3f} s | {t[m]['cpu_s']:.3f} s | {cells[0]} "
                      f"| {cells[1]} |")

        n = s["images"]
        line("ours: `detect` (corners + blur widths)", "ours", f"{s['found']['ours']} / {n}")
        line("ours: corners only (`measure_blur=False`)", "ours_corners", f"{s['found']['ours']} / {n}")
        if base:
            line(f"tiltfit {base}: `detect` (corners + blur widths)", "base", f"{s['found']['base']} / {n}")
        md.append(f"| OpenCV `findChessboardCornersSB` | {s['found']['sb']} / {n} | {t['sb']['wall_s']:.3f} s | "
                  f"{t['sb']['cpu_s']:.3f} s | 1, 1 | |")
        md.append(f"| OpenCV SB + `cornerSubPix` (5 × 5) | {s['found']['sb']} / {n} | "
                  f"{t['sb_subpix']['wall_s']:.3f} s | "
                  f"{t['sb_subpix']['cpu_s']:.3f} s | | 1, 1 |")
        a = s["agreement_sb_subpix_px"]
        md += ["", f"Ours against SB + cornerSubPix on the {s['views_both_sb']} views both find ({a.get('n', 0)} "
                   f"corners, labelling matched): median {a.get('median')} px, 95 % {a.get('p95')} px, max "
                   f"{a.get('max')} px."]
        if base and "vs_base" in s:
            v = s["vs_base"]
            c, z, bp = v["corner_diff_px"], v["blur_diff_over_sigma"], v["blur_diff_px"]
            moved = "less than 1e-4" if c.get("max", 0) < 1e-4 else f"at most {c.get('max')}"
            md += ["", f"Against tiltfit {base}: {r.get('base/ours (wall)')}× faster wall-clock, "
                       f"{r.get('base/ours (cpu)')}× in CPU time; the same boards: {v['same_boards']}; the same "
                       f"corners found: {v['same_corners_found']}; corners move by {moved} px; blur widths measured "
                       f"at the same points: {v['same_blur_measured']}, changed by a median {z.get('median')} σ "
                       "(σ: the "
                       f"revision's uncertainty), 99 % within {z.get('p99')} σ; {v['blur_points_over_1_sigma']} of "
                       f"{z.get('n')} points by more than 1 σ, {v['blur_points_over_3_sigma']} by more than 3 σ, the "
                       f"largest change {bp.get('max')} px. (The revision's own blur widths move as much under a "
                       "change of rounding order alone: `blur_reproducibility.md`.)"]
        md.append("")
        stages = [r["ours_stages_s"] for r in res["sets"][name]["rows"]]
        keys = [k for k in stages[0] if k != "total"] if stages else []
        if keys:
            md += ["Our stages (median wall-clock s over the images, last run of each): " + ", ".join(
                f"{k} {statistics.median(st.get(k, 0.0) for st in stages):.3f}" for k in keys) + ".", ""]
    with open(path, "w") as f:
        f.write("\n".join(md))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--baseline-rev", default=None, help="git revision of tiltfit to time in the same run")
    ap.add_argument("--baseline-repeats", type=int, default=1)
    ap.add_argument("--sets", default=",".join(SETS), help="comma-separated set names")
    ap.add_argument("--every", type=int, default=1, help="use every k-th image (quick checks)")
    add_output_options(ap, "real_speed_detect")
    args = ap.parse_args(argv)
    if markdown_only(args, write_markdown):
        return
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    base = Baseline(args.baseline_rev) if args.baseline_rev else None
    load_before = os.getloadavg()
    try:
        sets = {name: run_set(name, args, base) for name in args.sets.split(",")}
    finally:
        if base is not None:
            base.close()
    res = {"command": "python benchmarks/detection/bench_real_speed.py " + " ".join(argv if argv is not None else sys.argv[1:]),
           "repeats": args.repeats, "baseline_repeats": args.baseline_repeats,
           "baseline_rev": base.rev if base else None, "load_before": load_before, "load_after": os.getloadavg(),
           "sets": sets,
           "machine": {"platform": platform.platform(), "python": platform.python_version(), "torch": torch.__version__,
                       "opencv": cv2.__version__, "threads": 1, "cpu_count": os.cpu_count()}}
    save(args.out, res, write_markdown)


if __name__ == "__main__":
    main()
