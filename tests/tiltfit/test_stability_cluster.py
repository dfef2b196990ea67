"""`tiltfit stability --cluster`: the studies as Ray tasks (tiltfit/cluster.py) write what a serial run writes."""
import json

import pytest

ray = pytest.importorskip("ray")

from tiltfit.experiments import stability as st  # noqa: E402

ONLY = ["two_stage", "singular", "coverage"]  # the quickest studies; two_stage fits seeded noisy observations


def _untimed(path):
    data = json.loads(path.read_text())
    data.pop("runtime_s")
    return data


def test_studies_on_cluster_equal_serial_run(cluster, tmp_path, capsys):
    """Same seeds, same outputs: every study's JSON (timing aside), CSV and plot, and the findings."""
    here, spread = tmp_path / "here", tmp_path / "spread"
    st.run(str(here), quick=True, only=ONLY, progress=False)
    serial_out = capsys.readouterr().out
    on_ray = st.run(str(spread), quick=True, only=ONLY, progress=False, cluster="auto")
    assert capsys.readouterr().out == serial_out, "the findings printed differ"
    assert list(on_ray.studies) == ONLY, f"studies in the order asked: {list(on_ray.studies)}"
    for name in ONLY:
        assert _untimed(spread / f"{name}.json") == _untimed(here / f"{name}.json"), f"{name}.json differs"
        for ext in ("csv", "png"):
            assert (spread / f"{name}.{ext}").read_bytes() == (here / f"{name}.{ext}").read_bytes(), (
                f"{name}.{ext} differs")
    rows = {r["theta_L_true_deg"]: r for r in on_ray.studies["two_stage"].rows}
    assert rows[5.0]["two_stage_error_deg"] < -0.1, "the study's result itself (two-stage bias at 5°)"


def test_unreachable_cluster_is_one_line(tmp_path, capsys):
    """A bad --cluster address: one line naming it and exit 2, before any study runs."""
    status = st.main(["--quick", "--only", "singular", "--cluster", "127.0.0.1:1", "-o", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 2, f"exit status {status}"
    assert len(err) == 1 and "127.0.0.1:1" in err[0], f"one line naming the address: {err}"
    assert not (tmp_path / "o" / "singular.json").exists(), "no study ran"
