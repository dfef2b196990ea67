"""The C allocator under torch's CPU tensors.

Eager tracing and the fits' forward-mode Jacobians allocate and free many tensors of a few hundred KB to a
few hundred MB per batch. glibc serves every block above its mmap threshold (128 KB, raised dynamically up
to 32 MB) with a fresh mmap and returns it with munmap, so each batch pays page faults for memory it had a
moment ago (kernel time; measured with `benchmarks/renderer/bench_allocator.py`, docs/speed.md).

`tune_allocator` raises the mmap threshold and the heap-trim threshold once per process, so freed blocks
are reused from the heap instead. The price: the process keeps up to `trim_threshold` of freed memory
instead of returning it to the system at once. It runs when `renderer` is imported (worker processes
included); set RENDERER_MALLOPT=0 to leave the allocator alone.
"""
from __future__ import annotations

import ctypes
import os
import sys

M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3   # glibc's mallopt parameters (malloc.h)
MMAP_THRESHOLD = 1 << 28                      # 256 MiB: blocks below come from the heap
TRIM_THRESHOLD = 1 << 29                      # 512 MiB of free heap kept before trimming

_TUNED: bool | None = None


def tune_allocator(mmap_threshold: int = MMAP_THRESHOLD, trim_threshold: int = TRIM_THRESHOLD) -> bool:
    """Raise glibc's mmap and trim thresholds (once per process); False where it does not apply (not Linux
    with glibc, or RENDERER_MALLOPT=0)."""
    global _TUNED
    if _TUNED is not None:
        return _TUNED
    _TUNED = False
    if not sys.platform.startswith("linux") or os.environ.get("RENDERER_MALLOPT", "1") == "0":
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc (musl has no mallopt)
        return False
    _TUNED = bool(mallopt(M_MMAP_THRESHOLD, int(mmap_threshold))) and bool(mallopt(M_TRIM_THRESHOLD,
                                                                                      int(trim_threshold)))
    return _TUNED
