"""Progress lines on stderr for long work: a fraction done (`Progress`: renders, fits) or timed messages (`RunLog`:
tiltfit's reproduce and stability runs), both printed by `say`."""
from __future__ import annotations

import sys
import time


def say(line: str) -> None:
    """Print one progress line on stderr, flushed (the one place progress is written)."""
    print(line, file=sys.stderr, flush=True)


class Progress:
    """Prints 'label: 40% (12.3 s)' to stderr at most every `interval` seconds and at the end."""

    def __init__(self, total: int, label: str, enabled: bool = True, interval: float = 2.0):
        self.total, self.label, self.enabled, self.interval = max(total, 1), label, enabled, interval
        self.start = self.last = time.perf_counter()
        self.done = 0

    def update(self, n: int) -> None:
        self.done += n
        now = time.perf_counter()
        finished = self.done >= self.total
        if self.enabled and (finished or now - self.last >= self.interval):
            self.last = now
            pct = 100.0 * min(self.done, self.total) / self.total
            say(f"{self.label}: {pct:5.1f}% ({now - self.start:.1f} s)")


class RunLog:
    """Call with a message to print '[label   12.3 s] message' on stderr (unless disabled): seconds since the run
    started."""

    def __init__(self, label: str, enabled: bool = True):
        self.label = label
        self.t0 = time.perf_counter()
        self.enabled = enabled

    def __call__(self, msg: str) -> None:
        if self.enabled:
            say(f"[{self.label} {self.elapsed:6.1f} s] {msg}")

    @property
    def elapsed(self) -> float:
        return time.perf_counter() - self.t0
