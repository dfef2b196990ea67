"""Run every benchmark in this folder one after another; each writes its numbers to benchmarks/results/.

    .venv/bin/python benchmarks/run_all.py [--quick]

The benchmarks time ours against a named peer in the same run (Mitsuba 3 for the renderer, OpenCV for
detection) and report medians and ratios. They need the `bench` extra (Mitsuba); see the Makefile.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
BENCHMARKS = ["bench_fig6_mitsuba.py", "bench_speed_mitsuba.py", "bench_thin_lens.py", "bench_detect_opencv.py",
              "bench_beam.py", "bench_real_detect.py", "bench_photometric.py", "bench_cluster.py",
              "bench_calib_speed.py"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smoke runs (the benchmarks that have a quick mode)")
    args = ap.parse_args(argv)
    env = dict(os.environ, OMP_WAIT_POLICY=os.environ.get("OMP_WAIT_POLICY", "PASSIVE"))
    failed = []
    for i, name in enumerate(BENCHMARKS, 1):
        cmd = [sys.executable, os.path.join(HERE, name)]
        if args.quick and name == "bench_speed_mitsuba.py":
            cmd += ["--size", "128", "--repeats", "3", "--out", os.path.join(HERE, "results", "speed_thin_lens_quick")]
        elif args.quick and name != "bench_fig6_mitsuba.py":
            cmd.append("--quick")
        elif args.quick:
            cmd += ["--sizes", "320x240", "--repeats", "3", "--modes", "eager", "--out", os.path.join(HERE, "results", "fig6_mitsuba_quick")]
        print(f"[{i}/{len(BENCHMARKS)}] {' '.join(cmd[1:])}", file=sys.stderr, flush=True)
        if subprocess.call(cmd, env=env) != 0:
            failed.append(name)
    if failed:
        print("benchmarks failed: " + ", ".join(failed), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
