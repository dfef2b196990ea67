"""Progress lines for long tiltfit jobs (reproduce, stability): stderr, time since the start of the run."""
from __future__ import annotations

import sys
import time


class RunLog:
    """Call with a message to print '[label   12.3 s] message' on stderr (unless disabled)."""

    def __init__(self, label: str, enabled: bool = True):
        self.label = label
        self.t0 = time.perf_counter()
        self.enabled = enabled

    def __call__(self, msg: str) -> None:
        if self.enabled:
            print(f"[{self.label} {time.perf_counter() - self.t0:6.1f} s] {msg}", file=sys.stderr, flush=True)

    @property
    def elapsed(self) -> float:
        return time.perf_counter() - self.t0
