"""tiltfit.report.composite: the board rendered through a calibration of real photos lines up with the photo's corners,
and the differential-rendering composite's closed forms."""
import json
import math
import os
import sys

import numpy as np
import pytest

from tiltfit.report import composite
from tiltfit.files.calib import calib_dict
from tiltfit.files.calibrated import Calibration
from tiltfit.calibrate.flow import calibrate
from tiltfit.calibrate.fit import FitOptions
from tiltfit.calibrate.model import Observations
from tiltfit.target.layout import load_target

ROOT = os.path.join(os.path.dirname(__file__), "..", "..")
GOPRO = os.path.join(ROOT, "data", "real", "gopro_wide")
VIEW = "GOPR0043.jpg"
# GOPR0043 and views spread over the set: enough to fix the rational5 distortion in a couple of seconds
VIEWS = [VIEW, "GOPR0034.jpg", "GOPR0038.jpg", "GOPR0045.jpg", "GOPR0049.jpg", "GOPR0053.jpg", "GOPR0057.jpg",
         "GOPR0060.jpg", "GOPR0064.jpg", "GOPR0068.jpg"]
CORNERS = list(range(0, 48, 3))  # 16 of the 48 corners, over the whole board


def _corners(det):
    return np.array([c if c is not None else [math.nan] * 2 for c in det["corners_px"]], dtype=np.float64)


@pytest.fixture(scope="module")
def gopro():
    """(CALIB.json dict of a flat-board calibration of some GoPro views from the cached detections, cache)."""
    target = load_target(os.path.join(GOPRO, "target.json"))
    with open(os.path.join(GOPRO, "detections_tiltfit.json"), encoding="utf-8") as f:
        cache = json.load(f)
    corners = np.stack([_corners(cache[n]) for n in VIEWS])
    blur = np.full(corners.shape[:2], np.nan)
    obs = Observations(target.feature_points(), corners, blur, (1280, 960), 0.005, list(VIEWS))
    result = calibrate(obs, "unified", options=FitOptions(distortion="rational5", board="flat"))
    return calib_dict(result, obs=obs, target=target.to_dict()), cache


def _alignment(data, cache, **kw):
    return composite.board_alignment(Calibration.from_dict(data), VIEW, _corners(cache[VIEW]), spp=8,
                                     corners=CORNERS, **kw)


def test_board_rendered_through_calibration_lines_up_with_the_photo(gopro):
    data, cache = gopro
    a = _alignment(data, cache)
    assert a.n_corners == len(CORNERS), f"{a.n_corners} of {len(CORNERS)} rendered corners measured"
    # the renderer's camera is the calibration's projection, distortion included (the GoPro's is strong)
    assert a.rms_projection_px < 0.1, f"rendered corners {a.rms_projection_px:.3f} px RMS from the calibration's projection"
    # against the photo: the calibration's own residual on these corners, not less (it is the same comparison
    # made through the renderer) and not more than the rendering error adds
    own = composite._rms(a.projected_px[CORNERS], a.photo_px[CORNERS])
    assert 0.8 * own < a.rms_photo_px < 1.25 * own, \
        f"rendered vs photo {a.rms_photo_px:.3f} px RMS, calibration's residual on these corners {own:.3f} px"
    assert a.rms_photo_px < 1.5 * a.rms_reprojection_px, \
        f"rendered vs photo {a.rms_photo_px:.3f} px RMS, view's reprojection RMS {a.rms_reprojection_px:.3f} px"


def test_a_camera_with_the_principal_point_moved_fails_the_check(gopro):
    data, cache = gopro
    moved = dict(data, principal_point_px=[data["principal_point_px"][0] + 3.0, data["principal_point_px"][1] - 2.0])
    a = _alignment(moved, cache)
    assert a.rms_photo_px > 1.5 * a.rms_reprojection_px, \
        f"principal point moved by (3, -2) px, yet rendered vs photo only {a.rms_photo_px:.3f} px RMS"
    original = Calibration.from_dict(data).project(load_target(os.path.join(GOPRO, "target.json")).feature_points(), VIEW)
    far = composite._rms(a.rendered_px[CORNERS], original[CORNERS])
    assert far > 1.0, f"rendered corners of the moved camera only {far:.3f} px from the calibrated projection"


def test_differential_composite_closed_forms():
    rng = np.random.default_rng(0)
    photo = rng.uniform(0.1, 0.9, (4, 5, 3))
    without = rng.uniform(0.2, 1.0, (4, 5, 3))
    with_ = without.copy()
    with_[1] *= 0.5              # a shadow halves the light on row 1
    alpha = np.zeros((4, 5))
    alpha[3] = 1.0               # row 3 is the object
    gain = np.array([1.5, 1.0, 0.5])
    out = composite.differential_composite(photo, with_, without, alpha, gain)
    np.testing.assert_allclose(out[[0, 2]], photo[[0, 2]], err_msg="unshadowed photo pixels changed")
    np.testing.assert_allclose(out[1], 0.5 * photo[1], err_msg="a shadow halving the light must halve the photo")
    np.testing.assert_allclose(out[3], gain * with_[3], err_msg="object pixels must be the render times the gain")
    half = composite.differential_composite(photo, with_, without, np.full((4, 5), 0.5), gain)
    np.testing.assert_allclose(half[0], 0.5 * gain * with_[0] + 0.5 * photo[0], err_msg="α = 0.5 must blend")
    unlit = composite.differential_composite(photo, with_, np.zeros_like(without), alpha, gain)
    np.testing.assert_allclose(unlit[:3], photo[:3], err_msg="pixels the render does not reach must keep the photo")


def test_photo_gain_recovers_exposure_and_white_balance():
    rng = np.random.default_rng(1)
    board = np.where(rng.random((30, 40, 1)) < 0.5, 0.04, 0.8) * np.ones(3)
    photo = board * np.array([0.7, 0.6, 0.5]) * (1 + 0.01 * rng.standard_normal(board.shape))
    np.testing.assert_allclose(composite.photo_gain(photo, board), [0.7, 0.6, 0.5], rtol=0.01,
                               err_msg="per-channel gain of the light squares")


def test_window_around_is_cut_to_the_image():
    assert composite.window_around([[10.2, 5.0], [30.0, 40.7]], (100, 80), margin_px=8) == (2, 0, 37, 50), \
        "window of the points plus 8 px, cut at the top"
    with pytest.raises(ValueError, match="outside the image"):
        composite.window_around([[-50.0, -50.0]], (100, 80), margin_px=8)


@pytest.mark.slow
def test_composite_example_runs(tmp_path, monkeypatch, capsys):
    """`python examples/composite.py --spp 4 --out DIR`, run in this process (its `__main__` guard, argv and exit
    status; a new interpreter would import torch, renderer and tiltfit again: about 3 CPU s)."""
    import runpy

    out = tmp_path / "out"
    script = os.path.join(ROOT, "examples", "composite.py")
    monkeypatch.setattr(sys, "argv", [script, "--spp", "4", "--out", str(out)])
    try:
        runpy.run_path(script, run_name="__main__")
        code = 0
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    printed = capsys.readouterr()
    assert code == 0, f"examples/composite.py failed:\n{printed.out}\n{printed.err[-2000:]}"
    with open(out / "alignment.json", encoding="utf-8") as f:
        check = json.load(f)
    assert check["ok"] and check["rms_rendered_vs_projected_px"] < 0.1, f"alignment check: {check}"
    assert (out / "composite.png").stat().st_size > 100_000, "no full-size composite written"
