import pytest
import torch

# Tests check correctness, not speed: one torch thread per process avoids oversubscribing the two cores
# that the two pytest-xdist workers already share.
torch.set_num_threads(1)


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


def pytest_configure(config):
    # Registered here too, so the mark below is known when pytest-xdist is not loaded (-p no:xdist).
    config.addinivalue_line("markers", "xdist_group(name): run these tests on one pytest-xdist worker")


@pytest.hookimpl(tryfirst=True)  # before pytest-xdist's own hook turns the mark into the node id's "@group"
def pytest_collection_modifyitems(items):
    """Tests that share a module-scoped fixture run on one worker (`make test`: `--dist loadgroup`).

    A module-scoped fixture is built once per worker process that runs a test needing it; with tests handed
    out in chunks (`--dist load`) a module whose tests straddle two chunks had its fixture (a calibration, a set
    of renders) built by both workers. Tests that use none stay free to go to either worker."""
    for item in items:
        info = getattr(item, "_fixtureinfo", None)
        if info is None:
            continue
        if any(defs[-1].scope == "module" for name, defs in info.name2fixturedefs.items()
               if name in item.fixturenames and defs):
            item.add_marker(pytest.mark.xdist_group(item.nodeid.split("::")[0]))
