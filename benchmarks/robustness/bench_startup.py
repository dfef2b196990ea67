"""Start-up of the commands (issue 32 §2): wall time from launch to exit of `tiltfit ...` and `renderer ...` for
--help, bad input (a missing file, bad JSON, a bad option value) and the light commands (target design and print,
export, compare), before and after the lazy imports, and which heavy libraries each command loads.

Each case is a fresh `python -m tiltfit|renderer ...` process, timed from the parent (wall clock, medians of
--repeats). "after" runs this checkout; "before", only where --old names an existing folder (default /tmp/old,
e.g. `git worktree add /tmp/old c3ffd60`, the revision before the lazy imports), runs the same commands from that
older checkout through PYTHONPATH with the same virtualenv. The peers in the same run: the bare interpreter (`python -c pass`), `import cv2` (OpenCV's own start-up,
what a script calling OpenCV pays first) and `import torch`. Heavy libraries loaded per command are read from one
extra `-X importtime` run of the "after" tree.

    python benchmarks/robustness/bench_startup.py [--repeats 5] [--old /tmp/old]   # -> benchmarks/results/startup.{json,md}
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from benchmarks.results_io import ROOT, add_output_options, markdown_only, save, write_lines  # noqa: E402

HEAVY = ("torch", "kornia", "matplotlib", "cv2", "mitsuba", "OpenImageIO", "numpy", "scipy")
TARGET = os.path.join(ROOT, "data", "real", "industrial_ds1", "target.json")
GOAL_S = 0.3  # the goal for --help and bad input, wall seconds

# (kind, name, argv after `python`): {T} target file, {C} a small CALIB.json, {D} the scratch folder.
CASES = [
    ("peer", "python -c pass", ["-c", "pass"]),
    ("peer", "import cv2 (OpenCV)", ["-c", "import cv2"]),
    ("peer", "import torch", ["-c", "import torch"]),
    ("help", "tiltfit --help", ["-m", "tiltfit", "--help"]),
    ("help", "tiltfit calibrate --help", ["-m", "tiltfit", "calibrate", "--help"]),
    ("help", "renderer --help", ["-m", "renderer", "--help"]),
    ("help", "renderer render --help", ["-m", "renderer", "render", "--help"]),
    ("bad input", "tiltfit detect: missing image", ["-m", "tiltfit", "detect", "{D}/nope.png", "--target", "{T}",
                                                    "-o", "{D}/det.json"]),
    ("bad input", "tiltfit calibrate: --pixel-pitch-mm 0", ["-m", "tiltfit", "calibrate", "{D}/nope.png", "--target",
                                                            "{T}", "--pixel-pitch-mm", "0", "-o", "{D}/c.json"]),
    ("bad input", "tiltfit calibrate: missing image", ["-m", "tiltfit", "calibrate", "{D}/nope.png", "--target", "{T}",
                                                       "--pixel-pitch-mm", "0.005", "-o", "{D}/c.json"]),
    ("bad input", "tiltfit export: missing CALIB", ["-m", "tiltfit", "export", "{D}/nope.json", "-o", "{D}/cam.yml"]),
    ("bad input", "tiltfit compare: bad JSON", ["-m", "tiltfit", "compare", "{D}/bad.json", "{C}"]),
    ("bad input", "tiltfit target print: missing target", ["-m", "tiltfit", "target", "print", "{D}/nope.json",
                                                           "--pdf", "{D}/t.pdf"]),
    ("bad input", "renderer render: missing scene", ["-m", "renderer", "render", "{D}/nope.json", "-o", "{D}/o.png"]),
    ("bad input", "renderer render: bad JSON", ["-m", "renderer", "render", "{D}/bad.json", "-o", "{D}/o.png"]),
    ("bad input", "renderer render: bad output type", ["-m", "renderer", "render", "fig7", "-o", "{D}/o.xyz"]),
    ("command", "tiltfit target design", ["-m", "tiltfit", "target", "design", "--cols", "9", "--rows", "8",
                                          "--square-mm", "20", "--w-mm", "50", "--distance-mm", "500", "-q",
                                          "-o", "{D}/t.json"]),
    ("command", "tiltfit target print --pdf", ["-m", "tiltfit", "target", "print", "{T}", "--pdf", "{D}/t.pdf", "-q"]),
    ("command", "tiltfit export --to mrcal", ["-m", "tiltfit", "export", "{C}", "--to", "mrcal", "-q",
                                              "-o", "{D}/cam.cameramodel"]),
    ("command", "tiltfit export --to opencv", ["-m", "tiltfit", "export", "{C}", "-q", "-o", "{D}/cam.yml"]),
    ("command", "tiltfit compare", ["-m", "tiltfit", "compare", "{C}", "{C}", "-q"]),
]


def make_inputs(folder: str) -> dict:
    """The scratch folder's files: a bad JSON file and a small CALIB.json (8 views of industrial_ds1's cached
    detections, k1, flat board, no model selection: seconds), written with this checkout's code."""
    with open(os.path.join(folder, "bad.json"), "w", encoding="utf-8") as f:
        f.write('{"image": \n')
    calib = os.path.join(folder, "calib.json")
    script = f"""
import json, os, sys
sys.path.insert(0, {os.path.join(ROOT, 'benchmarks')!r})
from tests.real_detections import observations
from tiltfit.files.calib import calib_dict, write_calib
from tiltfit.calibrate.flow import calibrate
from tiltfit.calibrate.fit import FitOptions
folder = {os.path.join(ROOT, 'data', 'real', 'industrial_ds1')!r}
obs, _ = observations(folder, 0.00155)
obs = obs.subset(list(range(0, obs.n_views, max(1, obs.n_views // 8)))[:8])
res = calibrate(obs, "unified", options=FitOptions(distortion="k1", board="flat", model_selection=False))
write_calib({calib!r}, calib_dict(res, obs=obs, target=json.load(open(os.path.join(folder, "target.json")))))
"""
    subprocess.run([sys.executable, "-c", script], check=True, cwd=ROOT, env=_env(ROOT))
    return {"T": TARGET, "C": calib, "D": folder}


def _env(tree: str) -> dict:
    env = dict(os.environ, PYTHONPATH=tree, PYTHONDONTWRITEBYTECODE="0")
    env.pop("PYTHONPROFILEIMPORTTIME", None)
    return env


def _argv(case_argv: list[str], files: dict) -> list[str]:
    return [a.format(**files) for a in case_argv]


def run_once(tree: str, argv: list[str], importtime: bool = False) -> tuple[float, int, str]:
    """(wall seconds, exit status, stderr) of one `python ARGV` process run from `tree`."""
    cmd = [sys.executable] + (["-X", "importtime"] if importtime else []) + argv
    t0 = time.perf_counter()
    p = subprocess.run(cmd, cwd=tree, env=_env(tree), capture_output=True, text=True)
    return time.perf_counter() - t0, p.returncode, p.stderr


def heavy_modules(stderr: str) -> list[str]:
    """The HEAVY libraries named in `-X importtime` output (top-level packages imported at all)."""
    seen = set()
    for line in stderr.splitlines():
        if line.startswith("import time:") and line.count("|") == 2:
            seen.add(line.rsplit("|", 1)[1].strip().split(".")[0])
    return [h for h in HEAVY if h in seen]


def measure(args) -> dict:
    trees = {"after": ROOT}
    if os.path.isdir(args.old):
        trees["before"] = args.old
    with tempfile.TemporaryDirectory() as folder:
        files = make_inputs(folder)
        rows = []
        for kind, name, case_argv in CASES:
            argv = _argv(case_argv, files)
            row = {"kind": kind, "name": name, "argv": " ".join(case_argv)}
            for label, tree in trees.items():
                run_once(tree, argv)  # warm the file cache and .pyc files: every row starts alike
                times, codes = [], set()
                for _ in range(args.repeats):
                    wall, rc, _err = run_once(tree, argv)
                    times.append(wall)
                    codes.add(rc)
                row[label] = {"median_s": statistics.median(times), "runs_s": times, "exit": sorted(codes)}
            _, _, err = run_once(ROOT, argv, importtime=True)
            row["after"]["heavy"] = heavy_modules(err)
            if "before" in row:
                row["before_over_after"] = row["before"]["median_s"] / row["after"]["median_s"]
            rows.append(row)
            print(f"{name}: " + ", ".join(f"{k} {row[k]['median_s']:.2f} s" for k in trees), file=sys.stderr,
                  flush=True)
    return {"date": datetime.date.today().isoformat(), "repeats": args.repeats, "python": sys.version.split()[0],
            "cpus": os.cpu_count(), "load_average": os.getloadavg(), "old_tree": args.old if "before" in trees else None,
            "goal_s": GOAL_S, "rows": rows}


def write_markdown(path: str, res: dict) -> None:
    lines = [
        "# Start-up of the commands (issue 32 §2)",
        "",
        f"`python benchmarks/robustness/bench_startup.py` on {res['date']}: each case a fresh process, wall seconds from launch "
        f"to exit, median of {res['repeats']} (after one warm-up run); {res['cpus']} CPUs, load average "
        f"{res['load_average'][0]:.1f} at the end. before: {res['old_tree'] or '(not measured)'}; after: this checkout. "
        f"Peers in the same run: the bare interpreter, `import cv2`, `import torch`. Goal for help and bad input: "
        f"≤ {res['goal_s']} s. Heavy: the libraries the command imports (after), from `-X importtime`.",
        "",
        "| kind | case | before s | after s | before / after | exit (before, after) | heavy (after) |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in res["rows"]:
        before = r.get("before")
        lines.append(
            f"| {r['kind']} | {r['name']} | {before['median_s']:.2f} |" if before else f"| {r['kind']} | {r['name']} | – |")
        lines[-1] += (f" {r['after']['median_s']:.2f} | "
                      + (f"{r['before_over_after']:.1f}× | " if before else "– | ")
                      + f"{before['exit'] if before else '–'}, {r['after']['exit']} | "
                      + (", ".join(r["after"]["heavy"]) or "none") + " |")
    lines.append("")
    write_lines(path, lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--old", default="/tmp/old", help="checkout of the older revision [/tmp/old]")
    add_output_options(ap, "startup")
    args = ap.parse_args(argv)
    if not markdown_only(args, write_markdown):
        save(args.out, measure(args), write_markdown)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
