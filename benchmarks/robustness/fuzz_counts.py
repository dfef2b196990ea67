"""Run the fuzz corpora of tests/{renderer,tiltfit}/test_fuzz.py and test_fuzz_commands.py against whichever
`renderer`/`tiltfit` PYTHONPATH points at, and write the outcome counts per category.

    PYTHONPATH=/work/main python benchmarks/robustness/fuzz_counts.py --label before -o benchmarks/results/fuzz_before.json
    PYTHONPATH=.          python benchmarks/robustness/fuzz_counts.py --label after  -o benchmarks/results/fuzz_after.json

    python benchmarks/robustness/fuzz_counts.py compare benchmarks/results/fuzz_before.json benchmarks/results/fuzz_after.json

(The corpus is always this checkout's; only the code under test changes.) Outcomes: ok, refused, and the
failures traceback, hang, nan_output, leftover, bad_message, bad_exit, accepted_bad, unexpected_failure.
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import os
import sys
import time

HERE = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))  # benchmarks/
TESTS = os.path.join(os.path.dirname(HERE), "tests")


def _load(path: str, name: str):
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def compare(before_file: str, after_file: str) -> str:
    """Markdown table: per suite and category, cases and failure counts before -> after."""
    before, after = (json.load(open(f)) for f in (before_file, after_file))
    rows = ["| suite | category | cases | tracebacks | hangs | NaN/Inf outputs (exit 0) | leftovers | bad messages "
            "| wrongly accepted | other failures |", "|---|---|---|---|---|---|---|---|---|---|"]
    for suite, r in after["suites"].items():
        b_counts = before["suites"].get(suite, {"counts": {}})["counts"]
        for cat, counts in r["counts"].items():
            bc = b_counts.get(cat, {})
            cell = lambda k: f"{bc.get(k, 0)} → {counts.get(k, 0)}"  # noqa: E731
            other = lambda c: sum(c.get(k, 0) for k in ("bad_exit", "unexpected_failure"))  # noqa: E731
            rows.append(f"| {suite} | {cat} | {sum(counts.values())} | {cell('traceback')} | {cell('hang')} | "
                        f"{cell('nan_output')} | {cell('leftover')} | {cell('bad_message')} | {cell('accepted_bad')} | "
                        f"{other(bc)} → {other(counts)} |")
    return "\n".join(rows) + "\n"


def main(argv=None) -> int:
    if argv is None and len(sys.argv) > 1 and sys.argv[1] == "compare":
        print(compare(sys.argv[2], sys.argv[3]), end="")
        return 0
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--label", required=True)
    ap.add_argument("--only", choices=("renderer", "tiltfit"))
    ap.add_argument("--timeout", type=float, default=20.0, help="seconds per case before it counts as a hang")
    ap.add_argument("-o", "--output", required=True)
    args = ap.parse_args(argv)
    sys.path.insert(0, TESTS)
    import fuzz_harness

    report = {"label": args.label, "code": os.environ.get("PYTHONPATH", ""), "suites": {}}
    # suite name -> (package, corpus file): the first corpora and those of the newer commands (issue 24)
    suites = {"renderer": ("renderer", "test_fuzz.py"), "tiltfit": ("tiltfit", "test_fuzz.py"),
              "renderer-commands": ("renderer", "test_fuzz_commands.py"),
              "tiltfit-commands": ("tiltfit", "test_fuzz_commands.py")}
    for suite, (package, corpus) in suites.items():
        if args.only and package != args.only:
            continue
        mod = _load(os.path.join(TESTS, package, corpus), f"fuzz_{suite.replace('-', '_')}")
        cases = mod.CASES
        results, t0 = [], time.perf_counter()
        failures = []
        for k, case in enumerate(cases):
            res = fuzz_harness.classify(case, importlib.import_module(f"{package}.cli.main").main, package, args.timeout)
            results.append(res)
            if res.outcome in fuzz_harness.FAILURES:
                failures.append({"case": case["name"], "outcome": res.outcome, "detail": res.detail[:300]})
            print(f"[{k + 1}/{len(cases)}] {case['name'][:70]}: {res.outcome} ({res.seconds:.2f} s)",
                  file=sys.stderr, flush=True)
        report["suites"][suite] = {"cases": len(cases), "seconds": round(time.perf_counter() - t0, 1),
                                   "counts": fuzz_harness.tally(cases, results), "failures": failures}
    with open(args.output, "w") as f:
        json.dump(report, f, indent=1)
        f.write("\n")
    for suite, r in report["suites"].items():
        print(f"{args.label} {suite}: {r['cases']} cases in {r['seconds']} s: {r['counts']['total']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
