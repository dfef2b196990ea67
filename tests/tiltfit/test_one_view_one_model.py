"""Issue 33 §3: one model from one view, one corner count.

(b) `--distortion rational5` from one view of a narrow lens (industrial_ds1, tiltfit's cached corners) fitted
    k1 ≈ k4 ≈ 260 ± 594 and was accepted (the mapping at the image corner is pinned while the terms trade); it is
    refused now, like the same lens from 12 views (k4 −7.2 ± 8.3), while 3 views that determine it (k4 −24.5 ± 1.7)
    are kept; and a fit without a covariance is refused as undetermined, not taken as 0 px.
(c) One number of corners a view (`tiltfit.calibrate.model.MIN_CORNERS`): the fit's `min_corners`, the DET check and
    `tiltfit target design`, which refuses boards that can never be calibrated.
"""
import math
import os
import sys

import pytest

from tiltfit.calibrate.flow import calibrate
from tiltfit.cli.main import main
from tiltfit.calibrate.fit import FitError, FitOptions, fit_geometry, without_blur
from tiltfit.calibrate.model import MIN_CORNERS
from tiltfit.calibrate.start import initialize
from tiltfit.select.held_out import mapping_sigma_px, undetermined_distortion

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))  # tests/real_detections.py
from real_detections import observations  # noqa: E402

REAL = os.path.join(os.path.dirname(__file__), "..", "..", "data", "real")
OPTS = FitOptions(distortion="rational5", board="flat")


@pytest.fixture(scope="module")
def industrial():
    return observations(os.path.join(REAL, "industrial_ds1"), 0.0048)[0]


@pytest.mark.parametrize("views,refused", [([12], True), ([0, 5, 10], False)])
def test_rational5_from_one_view_is_refused_like_twelve(industrial, views, refused):
    sub = industrial.subset(views)
    if not refused:
        fit = calibrate(sub, "unified", options=OPTS)
        assert fit.distortion_model == "rational5", "3 views determine rational5 here (k4 −24.5 ± 1.7)"
        return
    with pytest.raises(FitError) as e:
        calibrate(sub, "unified", options=OPTS)
    msg = str(e.value)
    assert "rational5" in msg and "k4" in msg and "not determined" in msg and "\n" not in msg, msg


@pytest.mark.slow
def test_rational5_from_twelve_views_is_refused_too(industrial):
    with pytest.raises(FitError, match="denominator term k4"):
        calibrate(industrial.subset(list(range(12))), "unified", options=OPTS)


def test_no_covariance_is_undetermined_not_zero(industrial):
    obs = without_blur(industrial.subset([0, 5, 10]))
    opts = FitOptions(distortion="rational5", board="flat", uncertainties=False, free_principal_point=False)
    fit = fit_geometry(initialize(obs, "unified", options=opts, blur=False), obs, opts)
    assert fit.covariance is None
    assert math.isinf(mapping_sigma_px(fit)), "no covariance is no evidence of a determined mapping"
    why = undetermined_distortion(fit, "rational5", 3)
    assert why and "no covariance" in why, why


def test_min_corners_is_one_number():
    assert FitOptions().min_corners == MIN_CORNERS == 6, (FitOptions().min_corners, MIN_CORNERS)
    from tiltfit.files.formats import build

    text = build()["file_formats.md"]
    assert f"at least {MIN_CORNERS} corners" in text and "at least 4 corners" not in text, "docs say the number"


@pytest.mark.parametrize("extra,cells", [([], (2, 2)), ([], (3, 3)), (["--charuco", "DICT_4X4_50"], (2, 2)),
                                         (["--charuco", "DICT_4X4_50"], (3, 3))])
def test_target_design_refuses_boards_that_cannot_calibrate(tmp_path, capsys, extra, cells):
    out = tmp_path / "t.json"
    design = ["--w-mm", "50", "--distance-mm", "600"] if not extra else []
    args = ["target", "design", "--cols", str(cells[0]), "--rows", str(cells[1]), "--square-mm", "20", *design,
            *extra, "-o", str(out)]
    assert main(args) == 2, f"{cells}: expected exit status 2"
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--cols" in err and f"at least {MIN_CORNERS}" in err, err
    assert not out.exists(), "no file written"
    ok = ["target", "design", "--cols", "4", "--rows", "3", "--square-mm", "20", *design, *extra, "-o", str(out)]
    assert main(ok) == 0, capsys.readouterr().err
    assert out.exists(), "3 × 2 = 6 inner corners: written"
