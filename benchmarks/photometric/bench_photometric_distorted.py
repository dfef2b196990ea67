"""The photometric fit of a distorted camera before and after, in one process: `tiltfit.cli.photometric.
refine_calibration` (what `tiltfit calibrate --refine photometric` runs) on three GoPro views of data/real/gopro_wide
(GOPR0047, GOPR0053, GOPR0061 under the corner fit of every third view from the third, opencv5 distortion:
tests/tiltfit/test_photometric_left_out.py's case), once with `_Problem._focus` as it was at `--before REV` and once
with this checkout's, alternating; CPU seconds (one thread, medians) and every number of the photometric block
compared (largest relative difference).

    python benchmarks/photometric/bench_photometric_distorted.py [--before b23bca3^] [--repeats 2]
"""
from __future__ import annotations

import argparse
import importlib.util
import os
import statistics
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))
sys.path[:0] = [ROOT, os.path.dirname(HERE), os.path.join(ROOT, "tests", "tiltfit")]

import torch  # noqa: E402

from results_io import run_benchmark, write_lines  # noqa: E402


def _old_focus(rev: str):
    """`_Problem._focus` of tiltfit/photometric/problem.py at `rev` (the module loaded beside this checkout's)."""
    text = subprocess.run(["git", "-C", ROOT, "show", f"{rev}:tiltfit/photometric/problem.py"], check=True,
                          capture_output=True, text=True).stdout
    text = text.replace("from .render import", "from tiltfit.photometric.render import")
    path = os.path.join(tempfile.mkdtemp(), "problem_before.py")
    with open(path, "w", encoding="utf-8") as f:
        f.write(text)
    spec = importlib.util.spec_from_file_location("problem_before", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules["problem_before"] = module
    spec.loader.exec_module(module)
    return module._Problem._focus


def _numbers(block, path=""):
    """{path: float} of every number in the photometric block (run time left out)."""
    out = {}
    if isinstance(block, dict):
        for k, v in block.items():
            if k != "runtime_s":
                out.update(_numbers(v, f"{path}.{k}"))
    elif isinstance(block, (list, tuple)):
        for i, v in enumerate(block):
            out.update(_numbers(v, f"{path}[{i}]"))
    elif isinstance(block, float):
        out[path] = block
    return out


def measure(args) -> dict:
    import test_photometric_left_out as lo  # the case (its corner fit and the three views)
    from tiltfit.cli.photometric import refine_calibration
    from tiltfit.photometric import problem

    torch.set_num_threads(1)
    importlib.import_module("torch._dynamo")   # its first import (2-3 s) is neither side's

    focus = {"before": _old_focus(args.before), "after": problem._Problem._focus}
    subset = lo._gopro_third_subset()
    cpu, blocks = {"before": [], "after": []}, {}
    for _ in range(args.repeats):
        for side in ("before", "after"):
            problem._Problem._focus = focus[side]
            target, small, used, held_out = lo._three_views(subset)
            ns = argparse.Namespace(psf="disc", encoding=None, inputs=small.views[0]["image"], quiet=True)
            t = time.process_time()
            blocks[side] = refine_calibration(small, used, target, ns, lambda line: None, held_out=held_out)
            cpu[side].append(time.process_time() - t)
    problem._Problem._focus = focus["after"]
    a, b = _numbers(blocks["before"]), _numbers(blocks["after"])
    rel = max(abs(a[k] - b[k]) / max(abs(a[k]), 1e-300) for k in a)
    return {"before": args.before, "cpu_s": cpu, "median_cpu_s": {k: statistics.median(v) for k, v in cpu.items()},
            "kept": {k: v["kept"] for k, v in blocks.items()}, "numbers": len(a), "max_relative_difference": rel,
            "same_keys": sorted(a) == sorted(b)}


def write_markdown(path: str, res: dict) -> None:
    m = res["median_cpu_s"]
    write_lines(path, [
        "# The photometric fit of a distorted camera, before and after (one process, alternating)", "",
        "`python benchmarks/photometric/bench_photometric_distorted.py`: `refine_calibration` on three GoPro views "
        "(opencv5), CPU seconds of one thread.", "",
        "| | before (`_Problem._focus` of " + res["before"] + ") | after (this checkout) |", "|---|---|---|",
        f"| CPU s, each run | {', '.join(f'{v:.1f}' for v in res['cpu_s']['before'])} | "
        f"{', '.join(f'{v:.1f}' for v in res['cpu_s']['after'])} |",
        f"| median | {m['before']:.1f} | {m['after']:.1f} ({m['after'] / m['before']:.2f}×) |",
        f"| kept | {res['kept']['before']} | {res['kept']['after']} |", "",
        f"Every number of the photometric block ({res['numbers']}) equal to {res['max_relative_difference']:.1e} "
        f"relative; the same keys: {res['same_keys']}.", ""])


if __name__ == "__main__":
    sys.exit(run_benchmark(__doc__, "photometric_distorted", measure, write_markdown, before="b23bca3^", repeats=2))
