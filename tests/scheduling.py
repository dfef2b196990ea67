"""How `pytest -n N` hands the tests to its workers (tests/conftest.py installs it in place of xdist's `load`).

Two rules, both for wall time on few cores:

- Tests that share a module- or class-scoped fixture go to one worker together, so the fixture is built once in
  the run; so do tests marked with one `@pytest.mark.xdist_group(name)` (a cost paid once a process). xdist's
  `load` hands tests out one by one (its first quarter alternately to each worker), so such a fixture was built
  on both workers; its `--dist loadgroup` cannot help under pytest 9, which no longer reads the
  `item._nodeid` that xdist renames to carry the group.
- The longest units start first (longest-processing-time-first), so the workers end together instead of one of
  them starting a four-minute test near the end. A unit's time is the sum of its tests' times: measured in this
  checkout's last run (pytest's cache, `tests/durations`), else in tests/durations.json (a full run's times, for a
  fresh clone), else a guess.

The order changes when tests run, never what they check. Refresh tests/durations.json after a full run with
`python tests/scheduling.py` (it copies the times pytest's cache holds).
"""
from __future__ import annotations

import json
import os
import shutil
import tempfile
from collections import OrderedDict

import pytest
from xdist.scheduler import LoadScopeScheduling

HERE = os.path.dirname(os.path.abspath(__file__))
SEED_FILE = os.path.join(HERE, "durations.json")
CACHE_KEY = "tests/durations"
SHARED_SCOPES = ("module", "class")  # fixtures built once per module or class: their tests stay on one worker
SLOW_GUESS_S = 20.0  # an unmeasured test marked slow ("more than a few seconds")
QUICK_GUESS_S = 0.2  # any other unmeasured test (tests/durations.json leaves out those under SEED_MIN_S)
SEED_MIN_S = 0.5


def shared_fixture_group(item: pytest.Item) -> str | None:
    """The group of `item`: the name its `xdist_group` mark gives, else its module's path when it uses a module- or
    class-scoped fixture, else None.

    The mark groups tests of several modules that share a cost each process pays once (torch.compile's first
    compilation in a process imports and sets up Inductor and probes the CPU with subprocesses: on one worker it
    is paid once in the run). A marked test in a module with a shared fixture leaves that module's group.
    """
    mark = item.get_closest_marker("xdist_group")
    if mark is not None:
        return "group:" + str(mark.args[0] if mark.args else mark.kwargs.get("name", "default"))
    info = getattr(item, "_fixtureinfo", None)  # pytest keeps a test's fixture definitions only here
    if info is None:
        return None
    for name in info.names_closure:
        defs = info.name2fixturedefs.get(name)
        if defs and defs[-1].scope in SHARED_SCOPES:
            return item.nodeid.split("::", 1)[0]
    return None


def read_seed() -> dict[str, float]:
    """Seconds per test id from tests/durations.json ({} where it is missing or unreadable)."""
    try:
        with open(SEED_FILE) as f:
            return {str(k): float(v) for k, v in json.load(f).items()}
    except (OSError, ValueError, AttributeError):
        return {}


class WorkerPlan:
    """Worker side: writes each test's group and slow mark where the controller's scheduler reads them."""

    def __init__(self, plan_dir: str, worker_id: str):
        self.path = os.path.join(plan_dir, f"{worker_id}.json")

    @pytest.hookimpl(tryfirst=True)  # before xdist tells the controller that collection finished
    def pytest_collection_finish(self, session: pytest.Session) -> None:
        plan = {item.nodeid: {"group": shared_fixture_group(item), "slow": item.get_closest_marker("slow") is not None}
                for item in session.items}
        tmp = self.path + ".tmp"
        with open(tmp, "w") as f:
            json.dump(plan, f)
        os.replace(tmp, self.path)


class Timings:
    """Controller side (or a run without workers): each test's setup + call + teardown seconds, kept in pytest's
    cache for the next run's order."""

    def __init__(self, config: pytest.Config):
        self.config = config
        self.seconds: dict[str, float] = {}
        self.per_worker: dict[str, float] = {}

    def pytest_runtest_logreport(self, report: pytest.TestReport) -> None:
        self.seconds[report.nodeid] = self.seconds.get(report.nodeid, 0.0) + report.duration
        node = getattr(report, "node", None)  # the worker that ran it, under xdist
        if node is not None:
            worker = node.gateway.id
            self.per_worker[worker] = self.per_worker.get(worker, 0.0) + report.duration

    def pytest_terminal_summary(self, terminalreporter) -> None:
        if self.per_worker:  # whether the workers ended together
            terminalreporter.write_line("test seconds per worker: " + ", ".join(
                f"{w} {s:.0f}" for w, s in sorted(self.per_worker.items())))

    def pytest_sessionfinish(self) -> None:
        cache = getattr(self.config, "cache", None)
        if cache is None or not self.seconds:
            return
        known = dict(cache.get(CACHE_KEY, {}))
        known.update({k: round(v, 2) for k, v in self.seconds.items()})
        cache.set(CACHE_KEY, known)


class LongestFirstScheduling(LoadScopeScheduling):
    """xdist's scope scheduling with a unit per shared-fixture module (else per test), longest unit first."""

    def __init__(self, config: pytest.Config, plan_dir: str, log=None):
        super().__init__(config, log)
        self.plan_dir = plan_dir
        self.plan: dict[str, dict] = {}
        self.seconds = read_seed()
        cache = getattr(config, "cache", None)
        if cache is not None:
            self.seconds.update(cache.get(CACHE_KEY, {}))

    def _split_scope(self, nodeid: str) -> str:
        return (self.plan.get(nodeid) or {}).get("group") or nodeid

    def _read_plan(self) -> None:
        for name in sorted(os.listdir(self.plan_dir)):
            if name.endswith(".json"):
                with open(os.path.join(self.plan_dir, name)) as f:
                    self.plan = json.load(f)
                return

    def _guess(self, nodeid: str) -> float:
        if nodeid in self.seconds:
            return self.seconds[nodeid]
        return SLOW_GUESS_S if (self.plan.get(nodeid) or {}).get("slow") else QUICK_GUESS_S

    def schedule(self) -> None:
        if self.collection is not None or not self.collection_is_completed:
            return super().schedule()
        self._read_plan()
        super().schedule()  # builds the units in collection order and hands out the first ones (refilled below)

    def _assign_work_unit(self, node) -> None:
        if not getattr(self, "_ordered", False):
            self._order_workqueue()
        super()._assign_work_unit(node)

    def _order_workqueue(self) -> None:
        cost = {scope: sum(self._guess(nodeid) for nodeid in unit) for scope, unit in self.workqueue.items()}
        self.workqueue = OrderedDict(sorted(self.workqueue.items(), key=lambda kv: -cost[kv[0]]))
        self._ordered = True


class Scheduler:
    """The plugin tests/conftest.py registers on the controller of an `-n N` run."""

    def __init__(self):
        self.plan_dir = tempfile.mkdtemp(prefix="pytest-plan-")

    def pytest_configure_node(self, node) -> None:
        node.workerinput["test_plan_dir"] = self.plan_dir

    def pytest_xdist_make_scheduler(self, config: pytest.Config, log):
        if config.getoption("dist") != "load":  # an explicit other --dist is obeyed
            return None
        return LongestFirstScheduling(config, self.plan_dir, log)

    def pytest_unconfigure(self) -> None:
        shutil.rmtree(self.plan_dir, ignore_errors=True)


def install(config: pytest.Config) -> None:
    """Register the plugins of this run's process (tests/conftest.py's `pytest_configure` calls it)."""
    workerinput = getattr(config, "workerinput", None)
    if workerinput is not None:
        if "test_plan_dir" in workerinput:
            config.pluginmanager.register(WorkerPlan(workerinput["test_plan_dir"], workerinput["workerid"]))
        return
    config.pluginmanager.register(Timings(config))
    if config.pluginmanager.hasplugin("xdist") and config.getoption("dist", "no") != "no":
        config.pluginmanager.register(Scheduler())


def write_seed() -> None:
    """Copy the test times of this checkout's last run (pytest's cache) into tests/durations.json."""
    path = os.path.join(os.path.dirname(HERE), ".pytest_cache", "v", *CACHE_KEY.split("/"))
    with open(path) as f:
        seconds = json.load(f)
    merged = {**read_seed(), **seconds}
    with open(SEED_FILE, "w") as f:
        json.dump({k: round(merged[k], 1) for k in sorted(merged) if merged[k] >= SEED_MIN_S}, f, indent=0)
        f.write("\n")
    print(f"{SEED_FILE}: the tests of {SEED_MIN_S} s or more of {len(merged)}")


if __name__ == "__main__":
    write_seed()
