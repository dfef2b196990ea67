"""The loop closed on rendered photos (issue 30): a capture rendered with known parameters (distortion and
defocus), calibrated from its photos as a user would (`tiltfit.calibrate_photos`: detection, corner-and-blur
fit, defaults), and rendered again through its CALIB.json, OpenCV and mrcal files gives the captured images
back, within what the calibration's own projection σ moves them.

The yardstick is measured, not guessed: the image difference that a principal-point shift by the calibration's
median projection σ causes, plus the render noise (the same camera with another seed). A camera 3 px off must
exceed it (two-sided).
"""
from __future__ import annotations

import os

import numpy as np
import pytest
import torch

import renderer
from renderer import Lens, Sensor
from renderer.cameras import ThinLensCamera
from tiltfit import calibrate_photos
from tiltfit.files.calibrated import Calibration
from tiltfit.files.mrcal_file import write_mrcal
from tiltfit.files.opencv_file import write_opencv
from tiltfit.target.design import design_target

pytestmark = pytest.mark.slow

SENSOR = Sensor(480, 320, 0.012)
TRUTH = Lens(16.0, 540.0, 8.0, 0.0, SENSOR, (236.4, 163.2), (-0.15, 0.02))
#: (rotation about x °, about y °, distance mm)
POSES = ((25.0, 0.0, 520.0), (-20.0, 12.0, 470.0), (0.0, 30.0, 600.0), (12.0, -28.0, 500.0), (-25.0, -15.0, 640.0),
         (20.0, 25.0, 560.0))
SPP = 16


def _scene(target_path: str):
    return renderer.load_scene({
        "image": {"width": SENSOR.width_px, "height": SENSOR.height_px, "spp": SPP},
        "camera": {"type": "pinhole", "fov_deg": 40},  # replaced by the views' thin-lens cameras
        "lights": [{"type": "ambient", "intensity": [1, 1, 1]}],
        "objects": [{"name": "board", "shape": {"type": "target", "file": target_path}}]})


def _render(scene, camera, seed=0) -> np.ndarray:
    scene.camera = camera
    return renderer.render(scene, spp=SPP, progress=False, seed=seed).image[..., 0].numpy()


@pytest.fixture(scope="module")
def loop(tmp_path_factory):
    from tiltfit.experiments import reproduce

    folder = tmp_path_factory.mktemp("loop")
    target = design_target(8, 6, 18.0, w_mm=16.0, distance_mm=520.0, inclination_deg=0.0)
    target_path = str(folder / "target.json")
    target.save(target_path)
    scene = _scene(target_path)
    photos, captures = [], []
    for i, pose in enumerate(POSES):
        R, T = reproduce.target_pose(target, *pose)
        cam = ThinLensCamera.from_calibration(TRUTH, torch.as_tensor(np.asarray(R)), torch.as_tensor(np.asarray(T)))
        img = _render(scene, cam, seed=i)
        path = str(folder / f"view{i}.png")
        renderer.write_image(path, np.repeat(img[..., None], 3, -1))  # 8-bit sRGB, as a camera writes
        photos.append(path)
        captures.append(renderer.read_image(path)[..., 0])  # what the photo holds, linear
    calib = calibrate_photos(photos, target_path, SENSOR.pixel_pitch)
    calib.save(str(folder / "calib.json"))
    write_opencv(calib.data, str(folder / "camera.yml"))
    write_mrcal(calib.data, str(folder / "camera.cameramodel"))
    return folder, target_path, calib, captures


def test_the_calibration_recovers_the_rendered_lens(loop):
    _, _, calib, _ = loop
    s = calib.data["sigma"]
    assert abs(calib.focal_px - TRUTH.focal_px) < max(4 * s["w_mm"] / SENSOR.pixel_pitch, 0.002 * TRUTH.focal_px), \
        f"focal length {calib.focal_px:.2f} px, truth {TRUTH.focal_px:.2f}"
    assert calib.blur_known and abs(calib.lens.d - TRUTH.d) < 0.15 * TRUTH.d, \
        f"the blur is calibrated: d {calib.lens.d}, truth {TRUTH.d}"


#: The view rendered again through each file.
VIEW = 3


@pytest.fixture(scope="module")
def yardstick(loop):
    """What the calibration's own uncertainty and the render noise move the photo of VIEW by (the same for every
    file): the mean |difference| that a principal-point shift by the median projection σ causes, and that another
    seed causes; and a camera 3 px off, which must exceed the limit they set."""
    folder, target_path, calib, captures = loop
    scene = _scene(target_path)
    sigma_px = calib.data["projection_uncertainty"]["median_px"]
    k = VIEW
    R, T = calib.pose(k)
    lens = calib.lens
    moved = lens.with_(principal_point_px=(lens.principal_point_px[0] + sigma_px, lens.principal_point_px[1]))
    base = _render(scene, calib.camera(k), seed=200 + k)
    by_sigma = float(np.abs(_render(scene, ThinLensCamera.from_calibration(
        moved, torch.as_tensor(R), torch.as_tensor(T)), seed=200 + k) - base).mean())
    noise = float(np.abs(_render(scene, calib.camera(k), seed=300 + k) - base).mean())
    far = lens.with_(principal_point_px=(lens.principal_point_px[0] + 3.0, lens.principal_point_px[1] - 2.0))
    off = float(np.abs(_render(scene, ThinLensCamera.from_calibration(
        far, torch.as_tensor(R), torch.as_tensor(T)), seed=100 + k) - captures[k]).mean())
    return {"sigma_px": sigma_px, "by_sigma": by_sigma, "noise": noise, "off": off}


@pytest.mark.parametrize("name", ["calib.json", "camera.yml", "camera.cameramodel"])
def test_rendering_through_each_file_gives_the_photos_back(loop, yardstick, name):
    folder, target_path, calib, captures = loop
    cal = Calibration.read(str(folder / name), pixel_pitch_mm=SENSOR.pixel_pitch)
    scene = _scene(target_path)
    k = VIEW
    R, T = calib.pose(k)
    again = _render(scene, cal.camera(R=R, T_mm=T), seed=100 + k)
    err = float(np.abs(again - captures[k]).mean())
    y = yardstick
    limit = 2 * y["by_sigma"] + 2 * y["noise"] + 0.004  # 0.004: the photos' 8-bit quantisation (1/255 in sRGB)
    assert err < limit < y["off"], (
        f"{name} view {k}: mean |rendered again − photo| {err:.4f}, limit {limit:.4f} (σ {y['sigma_px']:.3f} px "
        f"moves it {y['by_sigma']:.4f}, noise {y['noise']:.4f}); 3 px off: {y['off']:.4f}")
