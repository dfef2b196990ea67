"""tiltfit's cameras are the renderer's one camera model: the calibration's camera is renderer.LensCamera (one name),
the synthetic camera's projection and blur agree with it.
(The photometric fit renders through `LensCamera.view_camera` itself: tests/tiltfit/test_photometric.py.)"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import renderer
from renderer import Lens, Sensor
from tiltfit.experiments import synth
from tiltfit.calibrate.model import LensCamera


def test_the_calibration_camera_is_the_renderers():
    from tiltfit.calibrate import model

    assert LensCamera is renderer.LensCamera, "the calibration's camera is the renderer's class"
    alias = "Tilt" + "LensCamera"
    assert not hasattr(model, alias), f"one class, one name (the {alias} alias is gone)"


@pytest.mark.parametrize("phi_deg", [0.0, 40.0])
def test_synth_camera_projects_and_blurs_as_the_lens_camera(phi_deg):
    sc = Lens(50.0, 700.0, 12.0, sensor=Sensor(801, 533, 0.01), theta_F=math.radians(25.0),
              principal_point_px=(410.5, 260.25), phi=math.radians(phi_deg))
    R, T = synth.pose_from_axis_angle([0.2, -0.15, 0.05], [10.0, -5.0, 650.0])
    lc = LensCamera.from_lens(sc, 1, R=R[None], T_mm=T[None])
    X = np.random.default_rng(2).uniform(-60, 60, (40, 3)) * np.array([1, 1, 0])
    p_cam = X @ R.T + T
    with torch.no_grad():
        uv_lens = lc.project(torch.tensor(X), 0).numpy()
        b_lens = lc.blur(torch.tensor(X), 0).numpy()
    assert np.abs(sc.project(p_cam) - uv_lens).max() < 1e-9, "Lens.project = LensCamera.project"
    assert np.abs(sc.blur_px(p_cam) - b_lens).max() < 1e-9, "Lens.blur_px = LensCamera.blur (ellipse)"
    # pose_from_axis_angle is the renderer's Rodrigues (checked against OpenCV in tests/renderer).
    assert np.allclose(R, lc.R[0].detach().numpy(), atol=1e-12), "one Rodrigues"


def test_scene_keys_build_the_same_lens():
    from tiltfit.experiments.scenes import boxes_scene

    lens = Lens.from_theta_L(55.0, 640.0, 18.0, math.radians(5.0))
    cam = boxes_scene(lens, downscale=64).camera
    tan_F = (640.0 + 55.0) * math.tan(math.radians(5.0)) / 55.0  # Scheimpflug, exact
    assert (cam.lens.w, cam.lens.U, cam.lens.d) == (55.0, 640.0, 18.0), "w, U, d as given"
    assert math.tan(cam.lens.theta_F) == pytest.approx(tan_F, rel=1e-12), "θF from θL by the exact Scheimpflug rule"
