"""Distortion about a tilted lens's own axis recognised on captures from an independent generator (issue 33 §1):
tests/tiltfit/lens_axis_capture.py traces the chief ray and the aperture's rim through a tilted thin lens with numpy
(radial distortion about the lens axis, k1 −0.12, k2 0.02; corner noise 0.07 px, widths 0.1 px), calibrated as a
user would: `unified` on untilted captures of the same lens, then `joint` from it. The centre and the terms are
chosen together (`tiltfit.calibrate.distortion_centre`): the lens axis with radial terms only, θL within 0.02° and 2σ of the
truth, for 3 views and 6; the OpenCV export then carries τ. A lens whose distortion is about the principal point
keeps that centre, tilted or not.
"""
from __future__ import annotations

import math
import os
import sys

import cv2
import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import lens_axis_capture as gen  # noqa: E402  (the independent generator, beside this file)
from tiltfit.files.calib import calib_dict
from tiltfit.calibrate.flow import calibrate
from tiltfit.files.opencv_file import opencv_text
from tiltfit.calibrate.fit import FitOptions
from tiltfit.calibrate.model import Observations

K = (-0.12, 0.02)
THETA_L = 5.0


def _obs(theta_L_deg, poses, seed, about_axis=True):
    points, corners, widths = gen.capture(theta_L_deg, 0.0, K, poses, seed, about_axis=about_axis)
    return Observations(points, corners, widths, (gen.WIDTH_PX, gen.HEIGHT_PX), gen.PITCH_MM)


def _joint(poses, seed, distortion, board, theta_L_deg=THETA_L, about_axis=True):
    stage1 = calibrate(_obs(0.0, poses, 100 + seed, about_axis), "unified",
                       options=FitOptions(distortion=distortion, board=board))
    obs = _obs(theta_L_deg, poses, 200 + seed, about_axis)
    return obs, calibrate(obs, "joint", init=stage1.camera, options=FitOptions(distortion=distortion, board=board))


@pytest.mark.slow
@pytest.mark.parametrize("poses,distortion,board", [(gen.POSES_3, "auto", "auto"), (gen.POSES_6, "auto", "flat"),
                                                     (gen.POSES_3, "k1k2", "flat"), (gen.POSES_6, "k1k2", "auto")],
                         ids=["3views-auto-board_auto", "6views-auto", "3views-k1k2", "6views-k1k2-board_auto"])
def test_lens_axis_is_chosen_and_theta_L_recovered(poses, distortion, board):
    obs, res = _joint(poses, 0, distortion, board)
    test = res.model_selection.get("distortion_centre")
    assert test is not None and test["chosen"] == "lens_axis", f"the lens axis is chosen: {test}"
    assert res.camera.distortion_centre == "lens_axis", "the fit reported is the lens-axis one"
    assert test["lr_statistic"] > 10, f"the lens-axis fit reached its own optimum (Λ {test['lr_statistic']:.3g})"
    if distortion == "auto":
        assert res.distortion_model in ("k1", "k1k2"), \
            f"radial terms about the axis, not decentring about the principal point: {res.distortion_model}"
    theta, sigma = res.values["theta_L_deg"], res.sigma["theta_L_deg"]
    assert 0.003 < sigma < 0.05, f"σ(θL) {sigma:.3g}° should be positive and small"
    err = abs(theta - THETA_L)
    assert err < 0.02 and err < 2 * sigma, f"θL {theta:.4f} ± {sigma:.4f}° (truth {THETA_L}°)"
    text = opencv_text(calib_dict(res, obs=obs))
    fs = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    dist = fs.getNode("distortion_coefficients").mat().ravel()
    fs.release()
    assert dist.size == 14 and np.degrees(np.hypot(*dist[12:])) == pytest.approx(abs(theta), abs=1e-6), \
        f"the OpenCV export carries τ of the tilt: {dist}"


@pytest.mark.slow
@pytest.mark.parametrize("theta_L_deg", [0.0, THETA_L])
def test_distortion_about_the_principal_point_keeps_its_centre(theta_L_deg):
    obs, res = _joint(gen.POSES_3, 1, "auto", "flat", theta_L_deg=theta_L_deg, about_axis=False)
    test = res.model_selection.get("distortion_centre") or {}
    assert test.get("chosen", "sensor") == "sensor" and res.camera.distortion_centre == "sensor", \
        f"θL {theta_L_deg}°, distortion about the principal point: no lens axis ({test})"
    if theta_L_deg:
        err = abs(res.values["theta_L_deg"] - theta_L_deg)
        assert err < 3 * res.sigma["theta_L_deg"], f"θL {res.values['theta_L_deg']:.4f} (truth {theta_L_deg}°)"


def test_generator_matches_the_documented_lens():
    """The generator's distortion is radial about the lens axis: a point on the axis is not moved, and points at
    one angle from the axis move by the same amount in any direction; with θL = 0 it is OpenCV's plain model."""
    tl, phi = math.radians(THETA_L), math.radians(30.0)
    n = gen.lens_axis(tl, phi)
    on_axis = gen.project(600 * n[None], tl, phi, K)
    assert np.allclose(on_axis, gen.project(600 * n[None], tl, phi, (0.0, 0.0)), atol=1e-9), "the axis is fixed"
    R = gen._frame_to(n)
    ring = np.array([R @ np.array([0.2 * math.cos(a), 0.2 * math.sin(a), 1.0]) for a in np.linspace(0, 6, 7)])
    shift = np.linalg.norm(gen.project(ring, tl, phi, K) - gen.project(ring, tl, phi, (0.0, 0.0)), axis=1)
    assert shift.min() > 1.0, f"the ring is distorted ({shift.min():.3g} px)"
    g = np.random.default_rng(0)
    p = np.c_[g.uniform(-150, 150, (20, 2)), g.uniform(450, 750, 20)]
    f = gen.W_MM / gen.PITCH_MM
    Kcv = np.array([[f, 0, gen.PP_PX[0]], [0, f, gen.PP_PX[1]], [0, 0, 1]])
    ref, _ = cv2.projectPoints(p, np.zeros(3), np.zeros(3), Kcv, np.array([*K, 0, 0, 0]))
    assert np.abs(gen.project(p, 0.0, 0.0, K) - ref.reshape(-1, 2)).max() < 1e-9, "θL = 0: OpenCV's model"
    assert gen.blur_px(p, 0.0, 0.0).min() >= 0, "widths are diameters"
