"""Progress lines on stderr for long work (renders, fits, sweeps)."""
from __future__ import annotations

import sys
import time


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
            print(f"{self.label}: {pct:5.1f}% ({now - self.start:.1f} s)", file=sys.stderr, flush=True)
