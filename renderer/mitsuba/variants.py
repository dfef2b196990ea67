"""Mitsuba 3 itself: import it and choose a variant, falling back to `scalar_rgb` where a JIT variant (llvm_*,
cuda_*) is missing or cannot run here (Dr.Jit needs libLLVM >= 16; probed once per process in a child). Mitsuba
is an optional extra (`pip install -e '.[test]'` or `'.[bench]'`); it is imported on first use.
"""
from __future__ import annotations

import os

DEFAULT_VARIANT = "llvm_ad_rgb"


_LLVM_RUNS: dict = {}  # variant -> whether its JIT runs here (probed once per process)
_PROBE = ("import drjit as dr, mitsuba as mi; mi.set_variant({v!r}); "
          "x = dr.maximum(mi.Float([1, 2]), mi.Float([2, 1])); dr.eval(x); print(x)")


#: Set (to anything but "" or "0") to hide Mitsuba's JIT variants, as on a machine without libLLVM >= 16: CI runs
#: the suite once this way so the pure-torch fallback of `intersector="auto"` stays tested.
HIDE_JIT_ENV = "RENDERER_HIDE_MITSUBA_JIT"


def jit_hidden() -> bool:
    """Whether `HIDE_JIT_ENV` hides Mitsuba's JIT variants in this process."""
    return os.environ.get(HIDE_JIT_ENV, "") not in ("", "0")


def jit_variant_runs(variant: str) -> bool:
    """Whether a JIT variant (llvm_*, cuda_*) runs here, probed in a child process: Dr.Jit needs LLVM >= 16,
    and with an older libLLVM the first kernel aborts the whole process. False whenever `HIDE_JIT_ENV` is set."""
    if variant.startswith("scalar"):
        return True
    if jit_hidden():
        return False
    if variant not in _LLVM_RUNS:
        import subprocess
        import sys

        try:
            probe = subprocess.run([sys.executable, "-c", _PROBE.format(v=variant)], capture_output=True,
                                   text=True, timeout=300)
            _LLVM_RUNS[variant] = probe.returncode == 0
        except (OSError, subprocess.TimeoutExpired):
            _LLVM_RUNS[variant] = False
    return _LLVM_RUNS[variant]


def variant_runs(variant: str) -> None:
    """Record that a JIT variant runs here, without probing: for a worker process whose parent probed it."""
    _LLVM_RUNS[variant] = True


def load_mitsuba(variant: str | None = DEFAULT_VARIANT):
    """Import mitsuba and set `variant` (None: keep the current one, or the default if none is set); falls
    back to scalar_rgb where a JIT variant is missing or cannot run here (see `jit_variant_runs`)."""
    try:
        import mitsuba as mi
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError("mitsuba is not installed; pip install -e '.[test]'") from e
    if variant is None:
        if mi.variant() is not None:
            return mi
        variant = DEFAULT_VARIANT
    if mi.variant() == variant:
        return mi
    try:
        if not jit_variant_runs(variant):
            raise ImportError(variant)
        mi.set_variant(variant)
    except (ImportError, AttributeError):
        mi.set_variant("scalar_rgb")
    return mi
