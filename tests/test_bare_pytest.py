"""A bare `pytest FILE` (the console script, run from any folder: no repository root on sys.path) collects a test
module that puts tests/ first on sys.path and then imports the packages: `renderer` must be the package, not the
tests/renderer folder of the same name."""
import os
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_a_bare_pytest_of_one_file_imports_the_packages_not_the_test_folders(tmp_path):
    # this module puts tests/ first on sys.path, then imports `from renderer import Lens`
    target = os.path.join(ROOT, "tests", "tiltfit", "test_fuzz_files.py")
    code = ("import sys, pytest; sys.exit(pytest.main(['--collect-only', '-q', '-p', 'no:cacheprovider', "
            f"'-p', 'no:xdist', {target!r}]))")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    run = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True,
                         timeout=300)
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]
    assert "ImportError" not in run.stdout
