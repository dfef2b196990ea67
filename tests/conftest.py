import contextlib
import importlib.util
import io
import os
import sys

import pytest
import torch


def _load_scheduling():
    """tests/scheduling.py, loaded by its path: putting tests/ on sys.path would let tests/renderer and
    tests/tiltfit shadow the packages of the same names for a bare `pytest`."""
    spec = importlib.util.spec_from_file_location(
        "scheduling", os.path.join(os.path.dirname(os.path.abspath(__file__)), "scheduling.py"))
    module = importlib.util.module_from_spec(spec)
    sys.modules["scheduling"] = module
    spec.loader.exec_module(module)
    return module


scheduling = _load_scheduling()

# Several test modules put tests/ first on sys.path for their helpers (fuzz_harness.py, real_detections.py). The
# repository's root on sys.path keeps `import renderer` and `import tiltfit` the packages for a bare `pytest FILE`
# too: tests/renderer and tests/tiltfit are namespace folders, which lose to a regular package anywhere on the path.
_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if _ROOT not in sys.path:
    sys.path.append(_ROOT)

# Tests check correctness, not speed: one torch thread per process avoids oversubscribing the two cores
# that the two pytest-xdist workers already share.
torch.set_num_threads(1)


def pytest_configure(config):
    """Under `-n N`, the order tests/scheduling.py gives (shared-fixture tests together, longest first); every run
    records its test times for the next one's order."""
    scheduling.install(config)


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)


@pytest.fixture(scope="module")
def cluster():
    """A local Ray with 2 CPUs for one test module (skips where ray is not installed)."""
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False,
             runtime_env={"env_vars": {"OMP_NUM_THREADS": "1"}})
    yield ray
    ray.shutdown()


@pytest.fixture(scope="session")
def stability_quick_run(tmp_path_factory):
    """`tiltfit stability --quick` with every study, once a process: (its StabilityResult, the folder it wrote, what
    it printed). tests/tiltfit/test_stability.py's end-to-end test reads it, and test_stability_cluster.py compares
    the cluster's run of some studies with it (each study draws from its own seeds: a run of some of them writes
    the same files); both are marked `xdist_group("stability_quick")`, so one worker runs it."""
    from tiltfit.experiments import stability

    out = tmp_path_factory.mktemp("stability_quick")
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        result = stability.run(str(out), quick=True, progress=False)
    return result, out, printed.getvalue()
