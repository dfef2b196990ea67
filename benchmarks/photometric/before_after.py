"""A photometric benchmark run by the code of two revisions in one run, with a before → after section.

`bench_photometric.py` or `bench_photometric_forward.py`, with the given options, is run first by a `git archive`
of `--before REV` (its own copy of the script), then by `--after REV` (or this checkout), one after the other on the
same machine; the after run's results are written where the script writes them (its --out), and a section
"Before → after (same run)" is appended to its Markdown: per row the time before and after and the accuracy
figures side by side.

    python benchmarks/photometric/before_after.py [--before REV] [--after REV] --out STEM bench_photometric.py -- --quick
    python benchmarks/photometric/before_after.py --out benchmarks/results/photometric_forward_quick \\
        bench_photometric_forward.py -- --quick 1
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))


def _tree(rev: str, where: str) -> str:
    path = os.path.join(where, rev)
    os.makedirs(path)
    archive = subprocess.run(["git", "-C", ROOT, "archive", rev], check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", path], input=archive, check=True)
    return path


def _run(tree: str, script: str, options: list, out: str) -> float:
    """Run the tree's own copy of the script; returns its wall seconds."""
    t0 = time.perf_counter()
    env = {**os.environ, "PYTHONPATH": tree, "OMP_NUM_THREADS": "1"}
    subprocess.run([sys.executable, os.path.join(tree, "benchmarks", "photometric", script), *options, "--out", out],
                   check=True, env=env, cwd=tree)
    return time.perf_counter() - t0


def _photometric_rows(res: dict) -> dict:
    """bench_photometric.py's rows keyed by (θL, blur level, method family)."""
    sys.path.insert(0, HERE)
    from bench_photometric import _family

    return {(r["theta_L_deg"], round(r["blur_px"], 1), _family(r)): r for r in res["rows"]}


def _photometric_section(before: dict, after: dict) -> list:
    b, a = _photometric_rows(before), _photometric_rows(after)
    L = ["", "## Before → after (same run)", "",
         "| θL true ° | blur px | method | CPU s before | after | θL err ° before | after | U err % before | after | "
         "d err % before | after | w err % before | after |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for key in sorted(a, key=str):
        if key not in b:
            continue
        rb, ra = b[key], a[key]
        L.append(f"| {key[0]:+.1f} | {key[1]:.1f} | {key[2]} | {rb['seconds']:.1f} | {ra['seconds']:.1f} | "
                 + " | ".join(f"{rb[k]:+.4f} | {ra[k]:+.4f}" for k in ("theta_L_err_deg", "U_err_pct", "d_err_pct",
                                                                       "w_err_pct")) + " |")
    return L


def _forward_section(before: dict, after: dict) -> list:
    cb = {c["case"]: c for c in before["cases"]}
    L = ["", "## Before → after (same run)", "",
         "| case | path | mean before | after | excess RMS before | after | d % before | after |",
         "|---|---|---|---|---|---|---|---|"]
    times = ["", "| case | forward model, all four paths s before | after | exact capture s before | after |",
             "|---|---|---|---|---|"]
    for c in after["cases"]:
        if c["case"] not in cb:
            continue
        b = cb[c["case"]]
        for path, p in c["paths"].items():
            q = b["paths"][path]
            L.append(f"| {c['case']} | {path} | {q['mean']:+.5f} | {p['mean']:+.5f} | {q['excess_rms']:.5f} | "
                     f"{p['excess_rms']:.5f} | {q['implied_d_pct']:+.3f} | {p['implied_d_pct']:+.3f} |")
        sb, sa = b["seconds"], c["seconds"]
        times.append(f"| {c['case']} | {sb['model_all_paths']:.2f} | {sa['model_all_paths']:.2f} | "
                     f"{sb['exact_per_capture']:.2f} | {sa['exact_per_capture']:.2f} |")
    return L + times


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", default="8c1f30a", help="revision before [8c1f30a]")
    ap.add_argument("--after", default=None, help="revision after [this checkout]")
    ap.add_argument("--out", required=True, help="the script's --out (its results stem or folder)")
    ap.add_argument("script", choices=("bench_photometric.py", "bench_photometric_forward.py"))
    ap.add_argument("options", nargs=argparse.REMAINDER, help="the script's options, after --")
    args = ap.parse_args()
    options = [o for o in args.options if o != "--"]
    forward = args.script == "bench_photometric_forward.py"
    with tempfile.TemporaryDirectory() as tmp:
        out_before = os.path.join(tmp, "before_out" if forward else "before_out/")
        wall_b = _run(_tree(args.before, tmp), args.script, options, out_before.rstrip("/"))
        after_tree = ROOT if args.after is None else _tree(args.after, tmp)
        wall_a = _run(after_tree, args.script, options, os.path.abspath(args.out))
        if forward:
            before, md = json.load(open(out_before + ".json")), os.path.abspath(args.out) + ".md"
            after = json.load(open(os.path.abspath(args.out) + ".json"))
        else:
            before = json.load(open(os.path.join(out_before, "photometric.json")))
            after = json.load(open(os.path.join(args.out, "photometric.json")))
            md = os.path.join(args.out, "photometric.md")
    after_rev = args.after or subprocess.run(["git", "-C", ROOT, "rev-parse", "--short", "HEAD"],
                                             capture_output=True, text=True).stdout.strip() + " (working tree)"
    lines = (_forward_section if forward else _photometric_section)(before, after)
    lines[3:3] = [f"Before: {args.before}; after: {after_rev}; run one after the other by "
                  f"`python benchmarks/photometric/before_after.py --out {args.out} {args.script} -- "
                  f"{' '.join(options)}` ({wall_b / 60:.1f} and {wall_a / 60:.1f} min wall, load average "
                  f"{os.getloadavg()[0]:.1f} at the end). The rows above are the after run's.", ""]
    with open(md, "a", encoding="utf-8") as f:
        f.write("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
