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


@pytest.mark.xdist_group("stability_quick")  # the serial run is test_stability.py's end-to-end run
def test_studies_on_cluster_equal_serial_run(cluster, stability_quick_run, tmp_path, capsys):
    """Same seeds, same outputs: every study's JSON (timing aside), CSV and plot, and the findings, against the serial
    quick run of every study (`stability_quick_run`)."""
    serial, here, printed = stability_quick_run
    assert printed == st.summary_text(serial.studies) + "\n", "the serial run prints each study's findings"
    spread = tmp_path / "spread"
    capsys.readouterr()
    on_ray = st.run(str(spread), quick=True, only=ONLY, progress=False, cluster="auto")
    serial_out = st.summary_text({name: serial.studies[name] for name in ONLY}) + "\n"  # what `run` prints of them
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
