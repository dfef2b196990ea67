"""tests/scheduling.py under `pytest -n 2`: a module-scoped fixture is built on one worker only, tests of two modules
marked with one xdist_group run on one worker, and the test the recorded times call longest starts first. Run on a
toy suite whose conftest installs it as tests/conftest.py does (without torch, which the real conftest imports:
three processes' start-up saved)."""
import json
import os
import shutil
import subprocess
import sys

import pytest

HERE = os.path.dirname(os.path.abspath(__file__))

TOY = '''
import os
import pytest

def log(line):
    with open(os.environ["TOY_LOG"], "a") as f:
        f.write(os.environ.get("PYTEST_XDIST_WORKER", "main") + " " + line + "\\n")

@pytest.fixture(scope="module")
def expensive():
    log("built")
    return 1

@pytest.mark.parametrize("i", range(12))
def test_uses_the_fixture(expensive, i):
    log(f"ran fixture_{i}")

@pytest.mark.parametrize("i", range(12))
def test_plain(i):
    log(f"ran plain_{i}")

@pytest.mark.xdist_group("once_a_process")
@pytest.mark.parametrize("i", range(6))
def test_marked(i):
    log(f"ran marked_{i + 6}")

def test_last_collected_but_longest():
    log("ran longest")
'''

# A second module: tests of both marked with one xdist_group (a cost each process pays once) share a worker.
TOY_OTHER = '''
import os
import pytest

def log(line):
    with open(os.environ["TOY_LOG"], "a") as f:
        f.write(os.environ.get("PYTEST_XDIST_WORKER", "main") + " " + line + "\\n")

@pytest.mark.xdist_group("once_a_process")
@pytest.mark.parametrize("i", range(6))
def test_marked_here(i):
    log(f"ran marked_{i}")
'''


@pytest.mark.slow  # three Python processes (a controller and two workers): how they share the tests is the subject
def test_shared_fixture_once_and_longest_first(tmp_path):
    shutil.copy(os.path.join(HERE, "scheduling.py"), tmp_path / "scheduling.py")
    (tmp_path / "conftest.py").write_text("import scheduling\n\n\ndef pytest_configure(config):\n"
                                          "    scheduling.install(config)\n")
    (tmp_path / "test_toy.py").write_text(TOY)
    (tmp_path / "test_toy_other.py").write_text(TOY_OTHER)
    # recorded times (as tests/durations.json holds them): the last test collected is the longest
    times = {f"test_toy.py::test_{name}[{i}]": 0.1 for name in ("uses_the_fixture", "plain") for i in range(12)}
    times["test_toy.py::test_last_collected_but_longest"] = 100.0
    (tmp_path / "durations.json").write_text(json.dumps(times))
    log = tmp_path / "log"
    env = {**os.environ, "TOY_LOG": str(log)}
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-n", "2", "-p", "no:cacheprovider", "test_toy.py",
                           "test_toy_other.py"],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    lines = [line.split(" ", 1) for line in log.read_text().splitlines()]
    built = [worker for worker, what in lines if what == "built"]
    assert len(built) == 1, f"the module fixture was built {len(built)} times ({built}); once expected"
    fixture_workers = {worker for worker, what in lines if what.startswith("ran fixture_")}
    assert fixture_workers == set(built), f"tests sharing the fixture ran on {fixture_workers}, built on {built}"
    marked = [worker for worker, what in lines if what.startswith("ran marked_")]
    assert len(marked) == 12 and len(set(marked)) == 1, f"the xdist_group's tests ran on {sorted(set(marked))}"
    first_of = {}
    for worker, what in lines:
        first_of.setdefault(worker, what)
    assert "ran longest" in first_of.values(), f"the longest test did not start first on a worker: {first_of}"
