"""Ctrl-C to the whole process group of `renderer render` while its worker processes start (issue 24).

A terminal's Ctrl-C reaches every process of the group, the workers too. Each trial starts the speed scene at
512 x 512, 64 spp (worker processes by default), waits until its first child process exists (the Mitsuba
probe: then Mitsuba loads and the workers start; `--start worker`: until the first worker exists), waits
`delay` more seconds and sends SIGINT to the group. Recorded per trial: the exit status, whether stderr holds
a traceback, its number of lines, whether the render finished anyway (exit 0 or the image written: the Ctrl-C
was lost), and the child processes still running 3 s after the command ended (orphaned workers).

    python benchmarks/robustness/probe_group_interrupt.py [--label L] [--trials 24] [--step 0.1] [--start child|worker]
                                               [--cwd CHECKOUT] [-o OUT.json]
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SCENE = os.path.join(ROOT, "benchmarks", "scenes", "speed_thin_lens.json")

sys.path.insert(0, os.path.join(ROOT, "tests"))
from processes import children as _children  # noqa: E402  (shared with tests/renderer/test_group_interrupt.py)
from processes import is_worker as _is_worker  # noqa: E402
from processes import running as _running  # noqa: E402


def trial(delay_s: float, out: str, cwd: str = ROOT, start: str = "child") -> dict:
    p = subprocess.Popen([sys.executable, "-m", "renderer", "render", SCENE, "-o", out, "--spp", "64",
                          "--set", "image.width=512", "--set", "image.height=512"], stderr=subprocess.PIPE,
                         text=True, start_new_session=True, cwd=cwd,
                         env={**os.environ, "PYTHONPATH": cwd})
    err: list[str] = []
    reader = threading.Thread(target=lambda: err.append(p.stderr.read()), daemon=True)
    reader.start()
    seen: set[int] = set()
    t0 = time.time()
    while time.time() - t0 < 120 and p.poll() is None and not (
            seen and (start == "child" or any(_is_worker(c) for c in seen))):
        seen |= _children(p.pid)
        time.sleep(0.05)
    t_first = time.time()
    while time.time() - t_first < delay_s and p.poll() is None:
        seen |= _children(p.pid)
        time.sleep(0.02)
    sent = p.poll() is None
    if sent:
        os.killpg(p.pid, signal.SIGINT)
    while p.poll() is None and time.time() - t0 < 300:
        seen |= _children(p.pid)
        time.sleep(0.05)
    p.wait(timeout=300)
    reader.join(timeout=10)
    text = "".join(err)
    time.sleep(3.0)
    leftover = sorted(pid for pid in seen if _running(pid))
    for pid in leftover:  # do not let one trial's orphans load the next
        try:
            os.kill(pid, signal.SIGKILL)
        except OSError:
            pass
    lines = text.strip().splitlines()
    return {"delay_s": round(delay_s, 3), "sigint_sent": sent, "exit": p.returncode,
            "traceback": "Traceback" in text or "Exception ignored" in text, "stderr_lines": len(lines),
            "finished_anyway": p.returncode == 0 or os.path.exists(out), "children_seen": len(seen),
            "leftover_processes": len(leftover), "last_line": (lines or [""])[-1],
            "stderr_tail": lines[-8:] if len(lines) > 1 else []}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--label", default="now")
    ap.add_argument("--trials", type=int, default=24)
    ap.add_argument("--step", type=float, default=0.1, help="delay added per trial, seconds [0.1]")
    ap.add_argument("--cwd", default=ROOT, help="checkout whose renderer runs [this one]")
    ap.add_argument("--start", choices=("child", "worker"), default="child",
                    help="delays count from the first child process (the Mitsuba probe: Mitsuba loads, then the "
                         "workers start) or from the first worker process [child]")
    ap.add_argument("-o", "--output", default=None)
    args = ap.parse_args(argv)
    # A command started in the background of a non-interactive shell inherits SIGINT ignored, and so would the
    # renderer (which then never sees the Ctrl-C): Python's own handler here makes the children start with the
    # default disposition.
    signal.signal(signal.SIGINT, signal.default_int_handler)
    with tempfile.TemporaryDirectory() as tmp:
        rows = []
        for k in range(args.trials):
            rows.append(trial(args.step * (k % 12), os.path.join(tmp, f"t{k}.png"), os.path.abspath(args.cwd),
                              args.start))
            print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    sent = [r for r in rows if r["sigint_sent"]]
    res = {"label": args.label, "checkout": os.path.abspath(args.cwd), "delays_from": args.start,
           "trials_run": len(rows),
           "sigint_sent": len(sent),
           "tracebacks": sum(r["traceback"] for r in sent),
           "not_exit_130": sum(r["exit"] != 130 for r in sent),
           "finished_anyway": sum(r["finished_anyway"] for r in sent),
           "not_one_line": sum(r["stderr_lines"] != 1 for r in sent),
           "with_leftover_processes": sum(r["leftover_processes"] > 0 for r in sent),
           "trials": rows}
    print(json.dumps({k: v for k, v in res.items() if k != "trials"}, indent=1))
    if args.output:
        with open(args.output, "w", encoding="utf-8") as f:
            json.dump(res, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
