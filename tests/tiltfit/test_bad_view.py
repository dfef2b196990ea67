"""Issue 33 §3(a): one sharp view of very low contrast among good ones does not sink the calibration.

A photo at 0.3 % contrast in 8 bits is under one grey level of signal: its corners survive, its blur widths are the
detector's answer to a staircase (industrial_ds1's photo 8 scaled about mid-grey: 160 corners, widths median
0.003 px where the other views' are 2.3 px). Before, those widths made the thin-lens blur model look wrong for
the whole lens (U and d not reported). Now the view is named in one line and left out of the blur fit; its
corners stay.
"""
import json
import math
import os
import sys

import numpy as np
import pytest

from tiltfit.calibrate.blur_views import BLUR_VIEW_OUTLIER_FACTOR
from tiltfit.calibrate.flow import calibrate
from tiltfit.cli.main import main
from tiltfit.calibrate.fit import FitOptions

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))  # tests/real_detections.py
from real_detections import REAL, observations, photos  # noqa: E402

OPTS = FitOptions(distortion="k1", board="flat", model_selection=False)
GOOD, BAD = [0, 5, 10], 8


@pytest.fixture(scope="module")
def industrial():
    return observations(os.path.join(REAL, "industrial_ds1"), 0.0048)[0]


def _with_widths(obs, view, widths):
    from tiltfit.calibrate.model import Observations

    blur = obs.blur_px.numpy().copy()
    blur[view] = widths
    return Observations(obs.points_mm, obs.corners_px, blur, obs.image_size_px, obs.pixel_pitch_mm, list(obs.names))


@pytest.mark.parametrize("kind", ["staircase", "random"])
def test_one_view_of_disagreeing_widths_is_left_out_of_the_blur_fit_and_named(industrial, kind):
    obs = industrial.subset(GOOD + [BAD])
    rng = np.random.default_rng(3)
    n = obs.blur_px.shape[1]
    # 8-bit 0.3 % contrast: widths near 0 (the detector on a one-level step), or random over the detector's range
    widths = rng.uniform(0.0, 0.08, n) if kind == "staircase" else rng.uniform(0.0, 6.0, n)
    bad = _with_widths(obs, 3, widths)
    fit = calibrate(bad, "unified", options=OPTS)
    named = [s for s in fit.notes if "left out of the blur fit" in s]
    assert len(named) == 1 and named[0].startswith(obs.names[3] + ":"), f"one line naming the view: {fit.notes}"
    assert "U_mm" not in fit.undetermined and "d_mm" not in fit.undetermined, \
        f"the other views' widths still determine the focus: {fit.undetermined} {fit.warnings}"
    assert fit.views[3]["n_points"] == 160, "the view's corners are kept"
    # the focus is the one the good views' widths give with the bad view's widths simply absent (two-sided)
    absent = calibrate(_with_widths(obs, 3, np.nan), "unified", options=OPTS)
    for k in ("U_mm", "d_mm"):
        assert abs(fit.values[k] - absent.values[k]) <= 0.1 * fit.sigma[k], \
            f"{k}: {fit.values[k]:.4g} against {absent.values[k]:.4g} ± {fit.sigma[k]:.2g} without the widths"


def test_good_views_are_not_flagged(industrial):
    """Negative control: the same four views with their own widths (one of them near focus) keep every width."""
    fit = calibrate(industrial.subset(GOOD + [BAD]), "unified", options=OPTS)
    assert not [s for s in fit.notes if "left out of the blur fit" in s], fit.notes
    rms = [v["rms_blur_px"] for v in fit.views]
    assert max(rms) < BLUR_VIEW_OUTLIER_FACTOR * float(np.median(rms)), f"no view stands out: {rms}"


@pytest.mark.slow
def test_cli_with_a_low_contrast_8_bit_photo_names_it_and_converges(tmp_path, industrial):
    """The reporter's path: `tiltfit calibrate` with defaults, three good views and one 8-bit 0.3 %-contrast
    photo (detected here; the good views from DET files of tiltfit's cached detections)."""
    import cv2

    from tiltfit.files.det import describe_detection
    from tiltfit.target.layout import load_target

    folder = os.path.join(REAL, "industrial_ds1")
    tfile = os.path.join(folder, "target.json")
    target = load_target(tfile)
    cache = json.load(open(os.path.join(folder, "detections_tiltfit.json"), encoding="utf-8"))
    inputs = []
    for v in GOOD:
        path = tmp_path / f"good{v}.json"
        path.write_text(json.dumps(describe_detection(cache[industrial.names[v]], industrial.names[v], tfile, target)))
        inputs.append(str(path))
    grey = cv2.imread(photos(folder)[BAD], cv2.IMREAD_GRAYSCALE).astype(np.float64) / 255.0
    b0 = str(tmp_path / "b0.png")
    cv2.imwrite(b0, np.round((0.5 + (grey - 0.5) * 0.003) * 255).astype(np.uint8))
    out = tmp_path / "CALIB.json"
    import contextlib
    import io

    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        rc = main(["calibrate", b0, *inputs, "--target", tfile, "--pixel-pitch-mm", "0.0048", "-o", str(out), "-q"])
    lines = [s for s in err.getvalue().splitlines() if "left out of the blur fit" in s]
    assert rc == 0, err.getvalue()
    assert len(lines) == 1 and b0 in lines[0], f"one line naming {b0}: {err.getvalue()}"
    calib = json.loads(out.read_text())
    assert calib["U_mm"] is not None and math.isfinite(calib["U_mm"]), f"U determined: {calib.get('undetermined')}"
    assert len(calib["views"]) == 4, "the photo's corners are used"
