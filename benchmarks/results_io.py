"""Where a benchmark's figures go: `OUT.json` (the measurements) and `OUT.md` (the table made from them).

Every timing benchmark takes `--out STEM` and `--markdown-only` (rewrite OUT.md from OUT.json without
timing anything, after a change to the table's layout), and saves the same way.
"""
from __future__ import annotations

import json
import os
import statistics
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
#: Where every benchmark writes its figures by default (one folder for all groups).
RESULTS = os.path.join(ROOT, "benchmarks", "results")


def add_output_options(ap, stem: str) -> None:
    """--out (default benchmarks/results/<stem>) and --markdown-only on an argparse parser."""
    ap.add_argument("--out", default=os.path.join(RESULTS, stem),
                    help="output path without extension (.json and .md are written)")
    ap.add_argument("--markdown-only", action="store_true", help="rewrite OUT.md from OUT.json (no timing)")


def markdown_only(args, write_markdown) -> bool:
    """With --markdown-only: rewrite OUT.md from OUT.json and return True (the caller stops)."""
    if not args.markdown_only:
        return False
    with open(args.out + ".json") as f:
        write_markdown(args.out + ".md", json.load(f))
    return True


def save(out: str, res: dict, write_markdown) -> None:
    """Write OUT.json and OUT.md, and print the Markdown."""
    os.makedirs(os.path.dirname(out) or ".", exist_ok=True)
    with open(out + ".json", "w") as f:
        json.dump(res, f, indent=1)
    write_markdown(out + ".md", res)
    with open(out + ".md") as f:
        print(f.read())


def write_lines(path: str, lines) -> None:
    """OUT.md from its lines (UTF-8)."""
    with open(path, "w", encoding="utf-8") as f:
        f.write("\n".join(lines))


def run_benchmark(doc: str, stem: str, measure, write_markdown, argv=None, **int_options) -> int:
    """A benchmark's main: parse `--NAME N` for each of `int_options` (name=default; a str default takes a
    string), --out and --markdown-only; with --markdown-only rewrite OUT.md, else `save` what `measure(args)`
    returns. Returns the exit status (0)."""
    import argparse

    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    for name, default in int_options.items():
        ap.add_argument("--" + name.replace("_", "-"), type=str if isinstance(default, str) else int, default=default)
    add_output_options(ap, stem)
    args = ap.parse_args(argv)
    if not markdown_only(args, write_markdown):
        save(args.out, measure(args), write_markdown)
    return 0


def timed(fn, repeats: int, samples: bool = False):
    """(last result, median wall-clock s, median process CPU s) of `repeats` calls of fn(): medians, because
    timings on a shared 2-core machine are noisy; with `samples`, the list of CPU seconds of every call too."""
    out, wall, cpu = None, [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    medians = (out, statistics.median(wall), statistics.median(cpu))
    return (*medians, cpu) if samples else medians
