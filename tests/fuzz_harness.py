"""Run a command-line `main(argv)` in-process on one fuzz case and classify what happened.

Shared by tests/renderer/test_fuzz.py, tests/tiltfit/test_fuzz.py and benchmarks/robustness/fuzz_counts.py (which runs
the same corpus against another checkout to count the failures before a change). It uses only OpenImageIO
and the standard library, never the code under test, so it measures any version of the packages.

A case is a dict:
    name       unique id, e.g. "scene/number/objects[0].shape.radius=1e39"
    category   the issue's category (encoding, depth, number, size, physics, overflow, cli, det, calib, ...)
    files      {relative name: bytes | str | a function returning one} written into a fresh folder first (str is
               UTF-8; a function is called then, so an image that takes seconds to make is not made at collection)
    argv       the command line; "{d}" in an argument is replaced by the folder
    output     the output's relative name (checked for NaN/Inf pixels or values after exit 0)
    expect     "refuse" (must exit 2), "ok" (must exit 0) or "either"
    fields     strings the one-line refusal must contain (the file and the field)
Outcomes (`classify`): "ok", "refused", and the failures "traceback", "hang", "nan_output", "leftover",
"bad_message", "bad_exit", "accepted_bad", "unexpected_failure".
"""
from __future__ import annotations

import io
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import threading
import tempfile
import time
import traceback
from dataclasses import dataclass

FAILURES = ("traceback", "hang", "nan_output", "leftover", "bad_message", "bad_exit", "accepted_bad",
            "unexpected_failure")


class Hang(BaseException):
    """Raised by the alarm when a case runs past its time limit."""


@dataclass
class Result:
    outcome: str
    rc: int | None
    stderr: str
    detail: str
    seconds: float


def run_command(main, args, timeout_s: float = 900) -> tuple[int, str]:
    """A command's `main(args)` in this process, for tests of what it does: (exit status, stderr); a traceback
    or no exit within timeout_s fails the calling test."""
    rc, err, tb, hung = run_main(main, [str(a) for a in args], timeout_s)
    assert tb is None and not hung, f"{args[0]}: " + (f"no exit within {timeout_s} s" if hung else tb)
    return rc, err


def _alarm(signum, frame):
    raise Hang


def run_main(main, argv: list[str], timeout_s: float) -> tuple[int | None, str, str | None, bool]:
    """(exit status, everything written to stderr (Python and C level), traceback text or None, hung)."""
    sys.stderr.flush()
    saved_fd = os.dup(2)
    sink = tempfile.TemporaryFile()
    os.dup2(sink.fileno(), 2)
    saved_err, sys.stderr = sys.stderr, io.StringIO()
    old = signal.signal(signal.SIGALRM, _alarm)
    signal.setitimer(signal.ITIMER_REAL, timeout_s)
    rc, tb, hung = None, None, False
    try:
        rc = main(argv)
    except SystemExit as e:
        rc = e.code if isinstance(e.code, int) else (0 if e.code is None else 2)
    except Hang:
        hung = True
    except BaseException:  # noqa: BLE001 - any escape is a traceback the user would have seen
        tb = traceback.format_exc()
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
        py_err, sys.stderr = sys.stderr.getvalue(), saved_err
        os.dup2(saved_fd, 2)
        os.close(saved_fd)
        sink.seek(0)
        c_err = sink.read().decode("utf-8", "replace")
        sink.close()
    return rc, c_err + py_err, tb, hung


def nonfinite_output(path: str) -> bool:
    """True when an output image or JSON file holds NaN or infinite values."""
    if path.lower().endswith(".json"):
        with open(path, encoding="utf-8") as f:
            data = json.load(f)
        stack = [data]
        while stack:
            v = stack.pop()
            if isinstance(v, float) and not math.isfinite(v):
                return True
            if isinstance(v, dict):
                stack.extend(v.values())
            elif isinstance(v, list):
                stack.extend(v)
        return False
    import numpy as np
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(path)
    if inp is None:
        return True
    try:
        px = inp.read_image(0, 0, 0, inp.spec().nchannels, oiio.FLOAT)
    finally:
        inp.close()
    return px is None or not np.isfinite(np.asarray(px)).all()


def _listing(folder: str) -> set[str]:
    out = set()
    for root, dirs, files in os.walk(folder):
        for name in files + dirs:
            out.add(os.path.relpath(os.path.join(root, name), folder))
    return out


def materialise(case: dict, folder: str) -> list[str]:
    """Write the case's files into `folder`; returns argv with {d} replaced."""
    for name, content in case.get("files", {}).items():
        path = os.path.join(folder, name)
        if content is None:  # a folder
            os.makedirs(path, exist_ok=True)
            continue
        os.makedirs(os.path.dirname(path), exist_ok=True)
        content = content() if callable(content) else content
        with open(path, "wb") as f:
            f.write(content.encode("utf-8") if isinstance(content, str) else content)
    return [a.replace("{d}", folder) if isinstance(a, str) else a for a in case["argv"]]


def classify(case: dict, main, prog: str, timeout_s: float = 120.0) -> Result:
    """Run one case in a fresh temporary folder and classify the outcome (see the module docstring).

    timeout_s: past it the case counts as hung. A hang detector, not a speed limit: a default calibration
    (distortion chosen by held-out error, about 30 small fits) takes seconds, and several times that on two
    cores shared with the rest of the suite."""
    folder = tempfile.mkdtemp(prefix="fuzz-")
    try:
        argv = materialise(case, folder)
        before = _listing(folder)
        out = os.path.join(folder, case["output"]) if case.get("output") else None
        out_existed = out is not None and os.path.exists(out)
        out_bytes = open(out, "rb").read() if out_existed and os.path.isfile(out) else None
        t0 = time.perf_counter()
        rc, err, tb, hung = run_main(main, argv, timeout_s)
        seconds = time.perf_counter() - t0
        after = _listing(folder)
        lines = [ln for ln in err.splitlines() if ln.strip()]

        def result(outcome, detail=""):
            return Result(outcome, rc, err, detail, seconds)

        if hung:
            return result("hang", f"no exit within {timeout_s} s")
        if tb is not None:
            return result("traceback", tb.strip().splitlines()[-1])
        made = case.get("output") if rc == 0 else None
        extra = {e for e in after - before if not (made and (e == made or e.startswith(made + os.sep)))}
        extra = {e for e in extra if not any(e.startswith(p + os.sep) for p in extra)}
        if extra:
            return result("leftover", ", ".join(sorted(extra)))
        if rc == 0:
            outputs = [out] if out is not None and os.path.isfile(out) else []
            if out is not None and os.path.isdir(out):
                outputs = [os.path.join(out, f) for f in sorted(os.listdir(out))
                           if f.lower().endswith((".png", ".exr", ".tif", ".json"))]
            outputs = [f for f in outputs if f.lower().endswith((".png", ".exr", ".tif", ".tiff", ".hdr", ".json"))]
            if any(nonfinite_output(f) for f in outputs):
                return result("nan_output", "NaN/Inf values in the output with exit 0")
            if case["expect"] == "refuse":
                return result("accepted_bad", "exit 0 where a refusal was expected")
            return result("ok")
        if out_bytes is not None and (not os.path.isfile(out) or open(out, "rb").read() != out_bytes):
            return result("leftover", "the existing output was changed by a failed run")
        if rc != 2:
            return result("bad_exit", f"exit {rc}")
        if case["expect"] == "ok":
            return result("unexpected_failure", lines[-1] if lines else "")
        argparse_error = bool(lines) and lines[0].startswith("usage:") and "error:" in lines[-1]
        message = lines[-1] if lines else ""
        if not argparse_error and (len(lines) != 1 or not message.startswith(prog + ":")):
            return result("bad_message", " | ".join(lines)[:300])
        missing = [f for f in case.get("fields", ()) if f not in message]
        if missing:
            return result("bad_message", f"{message[:200]} (does not name {missing})")
        return result("refused")
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def tally(cases: list[dict], results: list[Result]) -> dict:
    """{category: {outcome: count}} plus a "total" row."""
    table: dict[str, dict[str, int]] = {}
    for case, res in zip(cases, results):
        for key in (case["category"], "total"):
            row = table.setdefault(key, {})
            row[res.outcome] = row.get(res.outcome, 0) + 1
    return table


def interrupt_after_progress(argv: list[str], sig, marker: str, timeout_s: float = 300) -> tuple[int, list[str]]:
    """Run `python -m ...argv` in a subprocess, send `sig` once a stderr line contains `marker`; returns
    (exit status, stderr lines). timeout_s only guards against a hang (a loaded 2-core machine can take minutes
    to start a render and wind its workers down): the process is killed and the test fails past it."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p), "OMP_NUM_THREADS": "1"}
    # A command started in the background by a non-interactive shell (as CI may start the suite) inherits an
    # ignored SIGINT; give the child the default disposition, as a terminal would.
    proc = subprocess.Popen([sys.executable, "-m", *argv], stderr=subprocess.PIPE, stdout=subprocess.DEVNULL,
                            env=env, text=True, bufsize=1,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    lines, seen = [], threading.Event()

    def reader():
        for chunk in iter(lambda: proc.stderr.readline(), ""):
            lines.extend(part for part in chunk.replace("\r", "\n").splitlines() if part.strip())
            if marker in chunk:
                seen.set()

    t = threading.Thread(target=reader, daemon=True)
    t.start()
    seen.wait(timeout_s)
    time.sleep(0.3)
    proc.send_signal(sig)
    try:
        proc.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        raise AssertionError(f"{argv[0]} did not end within {timeout_s} s of {sig!r}: {lines[-3:]}") from None
    t.join(timeout=5)
    return proc.returncode, lines


def unique(cases: list[dict]) -> list[dict]:
    """The corpus, checked for unique case names (they are the test ids)."""
    names = [c["name"] for c in cases]
    assert len(names) == len(set(names)), "fuzz case names are unique"
    return cases


def check(case: dict, prog: str) -> None:
    """Run one case through `prog`'s CLI main (`renderer` or `tiltfit`) and fail on a bad outcome."""
    import importlib

    res = classify(case, importlib.import_module(f"{prog}.cli.main").main, prog)
    assert res.outcome not in FAILURES, f"{case['name']}: {res.outcome}: {res.detail}"
