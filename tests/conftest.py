import os
import sys

import pytest
import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # tests/scheduling.py
import scheduling  # noqa: E402

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
