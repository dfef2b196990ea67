"""Processes a test started, read from /proc: whether one still runs, and the stragglers killed after a grace
period. Shared by tests/renderer/test_group_interrupt.py and tests/renderer/test_fuzz_commands.py (which check
that `renderer render`'s worker processes end with it). Standard library only.
"""
from __future__ import annotations

import os
import signal
import time


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
