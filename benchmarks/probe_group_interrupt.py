"""Ctrl-C to the whole process group of `renderer render` while its worker processes start (issue 24).

A terminal's Ctrl-C reaches every process of the group, the workers too. Each trial starts the speed scene at
512 x 512, 64 spp (worker processes by default), waits until the first worker exists, waits `delay` more
seconds and sends SIGINT to the group; the outcome is the exit status and whether stderr holds a traceback.

    python benchmarks/probe_group_interrupt.py [--label L] [--trials 8] [-o OUT.json]
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCENE = os.path.join(ROOT, "benchmarks", "scenes", "speed_thin_lens.json")


def trial(delay_s: float, out: str) -> dict:
    p = subprocess.Popen([sys.executable, "-m", "renderer", "render", SCENE, "-o", out, "--spp", "64",
                          "--set", "image.width=512", "--set", "image.height=512"], stderr=subprocess.PIPE,
                         text=True, start_new_session=True, cwd=ROOT)
    t0 = time.time()
    while time.time() - t0 < 120 and p.poll() is None:
        if subprocess.run(["pgrep", "-P", str(p.pid)], capture_output=True, text=True).stdout.split():
            break
        time.sleep(0.05)
    time.sleep(delay_s)
    if p.poll() is None:
        os.killpg(p.pid, signal.SIGINT)
    err = p.communicate(timeout=300)[1]
    return {"delay_s": delay_s, "exit": p.returncode, "traceback": "Traceback" in err,
            "last_line": (err.strip().splitlines() or [""])[-1]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--label", default="now")
    ap.add_argument("--trials", type=int, default=8)
    ap.add_argument("-o", "--output", default=None)
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        rows = [trial(0.15 * k, os.path.join(tmp, f"t{k}.png")) for k in range(args.trials)]
    res = {"label": args.label, "trials": rows, "tracebacks": sum(r["traceback"] for r in rows),
           "not_interrupted": sum(r["exit"] != 130 for r in rows)}
    print(json.dumps(res, indent=1))
    if args.output:
        with open(args.output, "w", encoding="utf-8") as f:
            json.dump(res, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
