"""Processes a test started, read from /proc (and pgrep): a process's children, whether one is a
multiprocessing worker, whether it still runs, and the stragglers killed after a grace period. Shared by
tests/renderer/test_group_interrupt.py, tests/renderer/test_fuzz_commands.py and
benchmarks/robustness/probe_group_interrupt.py (which check that `renderer render`'s worker processes end with it).
Standard library only.
"""
from __future__ import annotations

import os
import signal
import subprocess
import time


def children(pid: int) -> set[int]:
    """The ids of the child processes of `pid` (pgrep -P)."""
    out = subprocess.run(["pgrep", "-P", str(pid)], capture_output=True, text=True).stdout
    return {int(x) for x in out.split()}


def is_worker(pid: int) -> bool:
    """Whether process `pid` is a multiprocessing (spawn) worker."""
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return b"spawn_main" in f.read()
    except OSError:
        return False


def running(pid: int) -> bool:
    """Whether process `pid` exists and is not a zombie."""
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return False


def kill_left_running(pids, within_s: float, poll_s: float) -> list:
    """Wait up to `within_s` seconds (polling every `poll_s`) for the processes `pids` to end; SIGKILL those
    still running then and return them (empty when all ended in time)."""
    deadline = time.time() + within_s
    while time.time() < deadline and any(running(p) for p in pids):
        time.sleep(poll_s)
    left = [p for p in pids if running(p)]
    for p in left:
        os.kill(p, signal.SIGKILL)
    return left
