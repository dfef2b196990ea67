"""A named distortion model the views do not determine is refused (issue 24: `--distortion rational` from one
view wrote coefficients of 3.6e5): the rational model from one GoPro view is refused with one line naming the
model and the view count; from ten views it is fitted, its mapping at the image corner determined to a pixel."""
import json
import os
import sys

import numpy as np
import pytest

from tiltfit.calibrate.flow import calibrate
from tiltfit.calibrate.fit import FitError, FitOptions
from tiltfit.select.held_out import MAX_MAPPING_SIGMA_PX, mapping_sigma_px

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))  # tests/real_detections.py
from real_detections import observations  # noqa: E402

DATA = os.path.join(os.path.dirname(__file__), "..", "..", "data", "real", "gopro_wide")


@pytest.fixture(scope="module")
def gopro():
    obs, _ = observations(DATA, 0.00155)
    return lambda n: obs.subset(range(min(n, obs.n_views)))


def test_rational_from_one_view_is_refused(gopro):
    with pytest.raises(FitError) as e:
        calibrate(gopro(1), "unified", options=FitOptions(distortion="rational"))
    msg = str(e.value)
    assert "\n" not in msg, f"one line: {msg!r}"
    assert "distortion rational" in msg and "too few views (1)" in msg, f"names the model and the views: {msg}"
    assert "--" not in msg, f"a library message without command-line words: {msg}"


def test_rational_from_ten_views_is_refused_and_rational5_fitted_and_determined(gopro):
    """Ten GoPro views pin rational's mapping (±0.6 px at the image corner) but not its coefficients: its
    denominator term k4 trades against the numerator (k4 ≈ 0.9 ± 1.6), so the named model is refused in one line
    saying so (as from one view, where k1 ≈ k4 ≈ 360 ± 1,600 had been accepted); rational5, the model with fewer
    terms the message suggests, is fitted and determined from the same views."""
    with pytest.raises(FitError, match="k4 .* not determined"):
        calibrate(gopro(10), "unified", options=FitOptions(distortion="rational"))
    res = calibrate(gopro(10), "unified", options=FitOptions(distortion="rational5"))
    sigma = mapping_sigma_px(res)
    assert res.distortion_model == "rational5", f"the rational5 model was fitted, not {res.distortion_model}"
    assert 0 < sigma < MAX_MAPPING_SIGMA_PX / 2, f"mapping at the image corner determined: ±{sigma:.3g} px"
    coeffs = np.abs(res.camera.distortion.detach().numpy())
    assert coeffs.max() < 10, f"coefficients of sane size from ten views: {coeffs}"


def test_cli_rational_from_one_view_one_line_exit_2_nothing_written(tmp_path, capsys):
    from tiltfit.cli import main as cli

    with open(os.path.join(DATA, "detections_tiltfit.json"), encoding="utf-8") as f:
        dets = json.load(f)
    name = sorted(k for k, v in dets.items() if "no_board" not in v)[0]
    det = tmp_path / "one.det.json"
    det.write_text(json.dumps(dets[name]))
    out = tmp_path / "calib.json"
    rc = cli.main(["calibrate", str(det), "--target", os.path.join(DATA, "target.json"), "--pixel-pitch-mm", "0.00155",
                   "--distortion", "rational", "-q", "-o", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2, f"refused with exit 2, got {rc}: {err}"
    assert len(err) == 1 and "distortion rational" in err[0] and "too few views (1)" in err[0], f"one line: {err}"
    assert not out.exists(), "no CALIB.json written"
