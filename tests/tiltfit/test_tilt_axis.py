"""A lens tilted about a turned axis (a tilt-shift lens's rotation, `Lens.phi`): the calibration tests the tilt
axis's direction φ and frees it only where the data justify it.

Captures: the exact thin-lens corners and blur widths (`tiltfit.experiments.synth.observe`, the blur ellipse's
equivalent-area diameter) of the paper's lens tilted by θL = 5° about an axis at φ, plus Gaussian noise; the
fit starts from the untilted stage-1 fit, as `tiltfit reproduce` does.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from renderer import Lens
from renderer.cameras import EOS_6D
from tiltfit.experiments import synth
from tiltfit.calibrate.flow import calibrate
from tiltfit.experiments import reproduce
from tiltfit.calibrate.fit import FitOptions
from tiltfit.calibrate.model import Observations

POSES = ((30.0, 0.0, 560.0), (-25.0, 0.0, 480.0), (0.0, 35.0, 600.0), (0.0, -30.0, 650.0), (20.0, 20.0, 540.0),
         (-15.0, -20.0, 700.0))
SENSOR = EOS_6D.binned(4)
NOISE_CORNER_PX, NOISE_BLUR_PX = 0.05, 0.1


def _observations(lens: Lens, seed: int) -> Observations:
    target = reproduce.calibration_target(reproduce.SetValues())
    rng = np.random.default_rng(seed)
    corners, blur = [], []
    for pose in POSES:
        ob = synth.observe(target, lens, *reproduce.target_pose(target, *pose))
        assert ob.in_image.all(), f"pose {pose}: the board leaves the image"
        corners.append(ob.corners_px + rng.normal(0, NOISE_CORNER_PX, ob.corners_px.shape))
        blur.append(ob.blur_px + rng.normal(0, NOISE_BLUR_PX, ob.blur_px.shape))
    return Observations(target.feature_points(), np.stack(corners), np.stack(blur), SENSOR.size_px,
                        SENSOR.pixel_pitch)


@pytest.fixture(scope="module")
def stage1():
    untilted = Lens.paper().with_(sensor=SENSOR)
    return calibrate(_observations(untilted, seed=1), "unified", options=FitOptions(model_selection=False))


@pytest.mark.slow
@pytest.mark.parametrize("phi_deg", [35.0, 0.0])
def test_the_tilt_axis_is_freed_only_where_justified(stage1, phi_deg):
    true = Lens.paper()
    lens = Lens.from_tilt(true.w, true.f, math.radians(5.0), true.d, sensor=SENSOR, phi=math.radians(phi_deg))
    obs = _observations(lens, seed=2 + int(phi_deg))
    res = calibrate(obs, "joint", init=stage1.camera, options=FitOptions())
    test = res.model_selection["tilt_axis"]
    v, s = res.values, res.sigma
    if phi_deg:
        assert test["justified"] and test["fitted"], f"φ = {phi_deg}°: freeing the axis is justified: {test}"
        err = v["tilt_axis_deg"] - phi_deg
        assert abs(err) < max(4 * s["tilt_axis_deg"], 0.2) and s["tilt_axis_deg"] < 2.0, \
            f"φ {v['tilt_axis_deg']:.3f} ± {s['tilt_axis_deg']:.3f}° vs {phi_deg}°"
    else:
        assert not test["fitted"] and v["tilt_axis_deg"] == 0.0, f"an x-axis tilt keeps φ held at 0: {test}"
    # Either way the tilt itself is recovered: θL about the (fitted or held) axis.
    tl = math.degrees(lens.theta_L)
    assert abs(v["theta_L_deg"] - tl) < max(4 * s["theta_L_deg"], 0.05), \
        f"θL {v['theta_L_deg']:.4f} ± {s['theta_L_deg']:.4f}° vs {tl:.4f}°"
    assert abs(v["U_mm"] / lens.U - 1) < 0.01, f"U {v['U_mm']:.1f} vs {lens.U:.1f} mm"


@pytest.mark.slow
def test_an_x_axis_fit_of_a_turned_tilt_is_refused_and_the_freed_one_fits(stage1):
    """Held at φ = 0 (model selection off), a tilt about an axis at 60° misfits the blur: the calibration says so
    and reports no focus; with the test on, φ is freed and the blur residuals fall to the noise."""
    true = Lens.paper()
    lens = Lens.from_tilt(true.w, true.f, math.radians(5.0), true.d, sensor=SENSOR, phi=math.radians(60.0))
    obs = _observations(lens, seed=9)
    held = calibrate(obs, "joint", init=stage1.camera, options=FitOptions(model_selection=False))
    assert any("does not describe this lens" in w for w in held.warnings), f"misfit not reported: {held.warnings}"
    assert "U_mm" in held.undetermined, "no focus distance from a misfit blur model"
    freed = calibrate(obs, "joint", init=stage1.camera, options=FitOptions())
    rb = float(np.median([x["rms_blur_px"] for x in freed.views]))
    assert rb < 1.5 * NOISE_BLUR_PX, f"the freed fit reaches the noise: blur RMS {rb:.3f} px"
    assert abs(freed.values["tilt_axis_deg"] - 60.0) < 0.5, f"φ {freed.values['tilt_axis_deg']:.3f}°"


def test_sharp_line_is_where_the_blur_vanishes():
    """`sharp_line`: the board points it reports lie on the plane of focus (zero blur), for a turned tilt."""
    from tiltfit.calibrate.flow import sharp_line

    true = Lens.paper()
    lens = Lens.from_tilt(true.w, true.f, math.radians(5.0), true.d, sensor=SENSOR, phi=math.radians(35.0))
    target = reproduce.calibration_target(reproduce.SetValues())
    R, T = reproduce.target_pose(target, 30.0, 10.0, lens.U)  # the board's centre on the plane of focus
    pts = target.feature_points()
    extent = (pts[:, 0].min(), pts[:, 1].min(), pts[:, 0].max(), pts[:, 1].max())
    line = sharp_line(lens, R, T, extent)
    assert line is not None, "the plane of focus crosses this board"
    ends = np.array([[x, y, 0.0] for x, y in line])
    assert np.linalg.norm(ends[1] - ends[0]) > 50, "a line across the board"
    for X in (ends[0], ends[1], 0.3 * ends[0] + 0.7 * ends[1]):
        assert lens.blur_px((R @ X + T)[None])[0] < 1e-6, f"sharp at {X}"
    far = sharp_line(lens, R, T + np.array([0.0, 0.0, 400.0]), extent)
    assert far is None, "a board far behind the plane of focus has no sharp line"
