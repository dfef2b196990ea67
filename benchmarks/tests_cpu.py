"""A pytest plugin: CPU seconds (`time.process_time`, this process's threads; not worker processes) per test, and in
chosen functions. Measures the suite on a shared machine, where wall times are other jobs' as much as the tests'.

    PYTHONPATH=benchmarks python -m pytest -q -n 0 -p tests_cpu tests/tiltfit/test_photometric.py
    TESTS_CPU_IN=tiltfit.photometric:refine_photometric,tiltfit.detect.chessboard:detect PYTHONPATH=benchmarks ...

The summary lists every test's CPU seconds (setup, call and teardown: a module fixture counts in its first test),
then the time spent in each function named by TESTS_CPU_IN (`module:function`, replaced in its module before the
tests import it; nested calls counted once).
"""
from __future__ import annotations

import functools
import importlib
import os
import time

import pytest

_per_test: dict = {}
_in: dict = {}


def _wrap(module: str, name: str) -> None:
    mod = importlib.import_module(module)
    fn = getattr(mod, name)
    depth = [0]

    @functools.wraps(fn)
    def timed(*args, **kwargs):
        depth[0] += 1
        t = time.process_time()
        try:
            return fn(*args, **kwargs)
        finally:
            depth[0] -= 1
            if depth[0] == 0:
                total = _in.setdefault(f"{module}:{name}", [0.0, 0])
                total[0] += time.process_time() - t
                total[1] += 1

    setattr(mod, name, timed)


for _spec in filter(None, os.environ.get("TESTS_CPU_IN", "").split(",")):
    _wrap(*_spec.split(":"))


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    t = time.process_time()
    yield
    _per_test[item.nodeid] = time.process_time() - t


def pytest_terminal_summary(terminalreporter):
    write = terminalreporter.write_line
    write(f"CPU total {time.process_time():.1f} s")
    for nodeid, s in sorted(_per_test.items(), key=lambda kv: -kv[1]):
        write(f"CPU {s:7.1f}  {nodeid}")
    for name, (s, n) in sorted(_in.items(), key=lambda kv: -kv[1][0]):
        write(f"in {name:50s} {s:7.1f} s  {n} calls")
