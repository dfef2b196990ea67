"""Rendering through a calibration (issue 30 §1): `tiltfit.files.calibrated.Calibration`, the scene-file `calibrated`
camera and `target` shape, `renderer render --camera`.

The round trip: corners of a known lens (`tiltfit.experiments.synth.observe`: the closed-form thin-lens projection, not the
renderer) are calibrated, the calibration is written as CALIB.json, OpenCV FileStorage and mrcal files, and each
file's camera must put the board where the true lens does, within the calibration's own projection σ; the
images rendered through the three files must agree with each other and with the true lens's rendering.
"""
from __future__ import annotations

import json
import sys
import math
import os

import numpy as np
import pytest
import torch

import renderer
from renderer import Lens
from renderer.cameras import ThinLensCamera
from renderer.core.params import SceneError
from renderer import Sensor
from tiltfit.experiments import synth
from tiltfit.files.calib import calib_dict, write_calib
from tiltfit.files.calibrated import Calibration, CalibrationError
from tiltfit.calibrate.flow import calibrate
from tiltfit.files.mrcal_file import write_mrcal
from tiltfit.files.opencv_file import write_opencv
from tiltfit.calibrate.fit import FitOptions
from tiltfit.calibrate.model import Observations
from tiltfit.files.scene_plugins import target_texture
from tiltfit.target.design import design_target
from tiltfit.target.layout import CharucoTarget
from tiltfit.target.raster import rasterise

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SENSOR = Sensor(480, 320, 0.012)  # a small sensor: 5.76 × 3.84 mm
#: (rotation about x °, about y °, distance mm) of the board's views
POSES = ((25.0, 0.0, 520.0), (-20.0, 10.0, 480.0), (0.0, 30.0, 560.0), (10.0, -25.0, 500.0), (-25.0, -15.0, 600.0),
         (20.0, 25.0, 540.0), (5.0, 5.0, 450.0), (-10.0, 30.0, 580.0))
NOISE_PX = 0.05


def _truth() -> Lens:
    return Lens(16.0, 700.0, 1.5, 0.0, SENSOR, (243.3, 157.1), (-0.12, 0.03, 0.0, 0.0, 0.0))


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """(truth lens, target, poses, folder with calib.json, camera.yml, camera.cameramodel, CALIB dict)."""
    from tiltfit.experiments import reproduce

    target = design_target(8, 6, 20.0, w_mm=16.0, distance_mm=520.0, inclination_deg=0.0)
    lens = _truth()
    rng = np.random.default_rng(3)
    P = target.feature_points()
    corners, blur, poses = [], [], []
    for pose in POSES:
        R, T = reproduce.target_pose(target, *pose)
        ob = synth.observe(target, lens, R, T)
        assert ob.in_image.all(), f"pose {pose}: the board leaves the image"
        poses.append((np.asarray(R), np.asarray(T)))
        corners.append(ob.corners_px + rng.normal(0, NOISE_PX, ob.corners_px.shape))
        blur.append(ob.blur_px + rng.normal(0, 0.05, ob.blur_px.shape))
    obs = Observations(P, np.stack(corners), np.stack(blur), SENSOR.size_px, SENSOR.pixel_pitch,
                       [f"view{i}.png" for i in range(len(POSES))])
    res = calibrate(obs, "unified", options=FitOptions(distortion="k1k2", board="flat", free_principal_point=True))
    data = calib_dict(res, obs=obs, target=target.to_dict())
    folder = tmp_path_factory.mktemp("calibrated")
    write_calib(str(folder / "calib.json"), data)
    write_opencv(data, str(folder / "camera.yml"))
    write_mrcal(data, str(folder / "camera.cameramodel"))
    return lens, target, poses, folder, json.loads((folder / "calib.json").read_text())


def _dense_board(target, n=15) -> np.ndarray:
    x0, y0, x1, y1 = target.extent_mm
    X, Y = np.meshgrid(np.linspace(x0, x1, n), np.linspace(y0, y1, n))
    return np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], -1)


@pytest.mark.parametrize("name", ["calib.json", "camera.yml", "camera.cameramodel"])
def test_each_file_puts_the_board_where_the_true_lens_does(capture, name):
    """Every calibration file's camera, with the calibrated poses, projects the whole board (margin included) where
    the true lens projects it with the same poses' truth: within 2× the calibration's median projection σ (the
    poses' error adds to it), and far better than a lens whose principal point is 2 px off (two-sided)."""
    lens, target, poses, folder, data = capture
    cal = Calibration.read(str(folder / name), pixel_pitch_mm=SENSOR.pixel_pitch)
    assert cal.image_size_px == SENSOR.size_px, f"{name}: image size {cal.image_size_px}"
    pts = _dense_board(target)
    sigma = data["projection_uncertainty"]["median_px"]
    main = Calibration.read(str(folder / "calib.json"))
    errs = []
    for k, (R, T) in enumerate(poses):
        truth = lens.project(pts @ R.T + T)
        if cal.views:
            ours = cal.project(pts, k)
        else:  # an mrcal model holds no views: the poses are given (CALIB.json's)
            Rk, Tk = main.pose(k)
            ours = cal.lens.project(pts @ Rk.T + Tk)
        errs.append(np.sqrt(np.mean(np.sum((ours - truth) ** 2, -1))))
    rms = float(np.median(errs))
    # Measured 0.10 px (σ 0.1 px); the same calibration without its distortion: 0.82 px.
    assert rms < 2 * sigma + 0.05, f"{name}: board projected {rms:.3f} px (median RMS over views) from the truth; " \
                                   f"projection σ {sigma:.3f} px"
    moved = cal.lens.with_(principal_point_px=(cal.lens.principal_point_px[0] + 2.0, cal.lens.principal_point_px[1]))
    R, T = main.pose(0)
    off = np.sqrt(np.mean(np.sum((moved.project(pts @ R.T + T) - lens.project(pts @ poses[0][0].T + poses[0][1])) ** 2,
                                 -1)))
    assert off > 1.0 > rms, f"a 2 px principal-point error shows ({off:.2f} px) where the calibration's does not"


def _scene(folder, view, spp=4, **camera):
    return {"image": {"spp": spp},
            "camera": {"type": "calibrated", "file": str(folder / "calib.json"), "view": view, **camera},
            "lights": [{"type": "ambient", "intensity": [1, 1, 1]}],
            "objects": [{"name": "board", "shape": {"type": "target", "file": str(folder / "calib.json")}}]}


def test_renders_through_the_three_files_agree_with_the_true_lens(capture):
    """The board rendered through CALIB.json, the OpenCV file and the mrcal file (the same calibration) gives the
    same image, and the true lens's rendering of the same view differs only at edges by the calibration's σ."""
    lens, target, poses, folder, data = capture
    images = {}
    R2, T2 = Calibration.read(str(folder / "calib.json")).pose(2)
    for name in ("calib.json", "camera.yml", "camera.cameramodel"):
        pose = dict(R=R2.tolist(), T_mm=T2.tolist()) if name.endswith("cameramodel") else {}  # mrcal: no views
        scene = renderer.load_scene(_scene(folder, 2, file=str(folder / name), pixel_pitch_mm=SENSOR.pixel_pitch,
                                           **pose))
        assert (scene.image.width, scene.image.height) == SENSOR.size_px, "the calibration's image size by default"
        images[name] = renderer.render(scene, spp=4, progress=False, seed=1).image[..., 0].numpy()
    for name in ("camera.yml", "camera.cameramodel"):
        diff = np.abs(images[name] - images["calib.json"])
        assert diff.mean() < 2e-3, f"{name} renders as calib.json does: mean |Δ| {diff.mean():.2e}"
    R, T = poses[2]
    true_scene = renderer.load_scene(_scene(folder, 2))
    cal = Calibration.read(str(folder / "calib.json"))
    true_scene.camera = ThinLensCamera.from_calibration(
        lens.with_(U=cal.lens.U, d=cal.lens.d), torch.as_tensor(R), torch.as_tensor(T))
    truth = renderer.render(true_scene, spp=4, progress=False, seed=1).image[..., 0].numpy()
    diff = np.abs(images["calib.json"] - truth)
    # Measured: 5e-4 (edges moved by the calibration's error, a few hundredths of a pixel); the same calibration
    # without its distortion (k1 −0.12 here) gives 3.2e-3.
    assert diff.mean() < 1.5e-3, f"calibrated vs true lens: mean |Δ| {diff.mean():.4f}"
    assert np.abs(truth.mean() - images["calib.json"].mean()) < 2e-3, "the same board area in both"


def test_the_rendered_board_is_the_print(capture):
    """The target shape's albedo at each board point is the print's: cell centres dark or light as the target
    says, the margin light, and the render of a fronto-parallel view matches `tiltfit.target.raster.rasterise`."""
    _, target, _, _, _ = capture
    tex = target_texture(target, (0.04, 0.8))
    x0, y0, x1, y1 = target.extent_mm
    xs = (np.asarray(target.x_edges[:-1]) + np.asarray(target.x_edges[1:])) / 2
    ys = (np.asarray(target.y_edges[:-1]) + np.asarray(target.y_edges[1:])) / 2
    X, Y = np.meshgrid(xs, ys)
    idx = tex.palette_index(torch.as_tensor(X.ravel() - x0), torch.as_tensor(Y.ravel() - y0)).numpy()
    assert np.array_equal(idx.reshape(X.shape).astype(bool), target.cell_colours()), "cell colours as the target's"
    margin = tex.palette_index(torch.tensor([1.0, x1 - x0 - 1.0]), torch.tensor([1.0, y1 - y0 - 1.0])).numpy()
    assert not margin.any(), "the margin is light"


def test_charuco_markers_are_drawn_exactly():
    """A ChArUco board's texture equals the target's exact rasteriser (which draws markers from OpenCV's
    dictionary) at texel centres, except on texels an edge passes through."""
    board = CharucoTarget.board((5, 4), 30.0, 22.0, "DICT_4X4_50")
    tex = target_texture(board, (0.0, 1.0))
    x0, y0, x1, y1 = board.extent_mm
    W, H = 600, 480
    ref = rasterise(board, (x0, x1), (y0, y1), W, H, dark=1.0, white=0.0)  # dark fraction per texel
    u = x0 + (np.arange(W) + 0.5) * (x1 - x0) / W
    v = y0 + (np.arange(H) + 0.5) * (y1 - y0) / H
    V, U = np.meshgrid(v, u, indexing="ij")
    ours = tex.palette_index(torch.as_tensor(U.ravel() - x0), torch.as_tensor(V.ravel() - y0)).numpy().reshape(H, W)
    pure = (ref == 0) | (ref == 1)
    agree = float(np.mean(ours[pure] == ref[pure]))
    assert pure.mean() > 0.8 and agree == 1.0, f"markers and squares as the rasteriser: {agree:.5f} of {pure.mean():.2f}"
    assert 0.3 < ours.mean() < 0.7, f"a ChArUco board is about half dark: {ours.mean():.2f}"


def test_a_smaller_image_renders_the_same_view(capture):
    """image.width at half the calibration's renders the same view: the board's image is the half-size one."""
    _, _, _, folder, _ = capture
    full = renderer.render(renderer.load_scene(_scene(folder, 1)), spp=4, progress=False, seed=2).image[..., 0]
    half_scene = _scene(folder, 1)
    half_scene["image"]["width"] = SENSOR.width_px // 2
    scene = renderer.load_scene(half_scene)
    assert (scene.image.width, scene.image.height) == (SENSOR.width_px // 2, SENSOR.height_px // 2)
    half = renderer.render(scene, spp=4, progress=False, seed=2).image[..., 0]
    pooled = torch.nn.functional.avg_pool2d(full[None, None], 2)[0, 0]
    assert float((pooled - half).abs().mean()) < 0.01, "the half-size render is the full one pooled"
    with pytest.raises(SceneError, match=r"image: 300x300 px: .*aspect ratio"):
        bad = _scene(folder, 1)
        bad["image"].update(width=300, height=300)
        renderer.load_scene(bad)


@pytest.mark.parametrize("change, field", [
    (dict(file="missing.json"), "camera.file"),
    (dict(view=99), "camera.view"),
    (dict(view="nope.png"), "camera.view"),
    (dict(R=[[1, 0, 0], [0, 1, 0]], T_mm=[0, 0, 500]), "camera.R"),
    (dict(R=[[1, 0, 0], [0, 1, 0], [0, 0, 1]]), "camera"),
])
def test_bad_calibrated_camera_is_one_line_naming_the_field(capture, change, field):
    _, _, _, folder, _ = capture
    cfg = _scene(folder, 0)
    cfg["camera"].update({k: (str(folder / v) if k == "file" else v) for k, v in change.items()})
    with pytest.raises(SceneError) as e:
        renderer.load_scene(cfg)
    msg = str(e.value)
    assert msg.startswith(field) and "\n" not in msg, f"one line starting with {field}: {msg!r}"


def test_bad_calibration_file_names_the_file_and_field(tmp_path, capture):
    _, _, _, folder, data = capture
    bad = dict(data)
    bad["w_mm"] = -3.0
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(bad))
    with pytest.raises(ValueError) as e:
        Calibration.read(str(path))
    assert str(path) in str(e.value) and "w_mm" in str(e.value), str(e.value)
    cfg = _scene(folder, 0)
    cfg["camera"]["file"] = str(path)
    with pytest.raises(SceneError, match=r"^camera\.file: .*bad\.json.*w_mm"):
        renderer.load_scene(cfg)
    target_cfg = _scene(folder, 0)
    (tmp_path / "t.json").write_text('{"type": "checkerboard", "x_edges": [0, 1]}')
    target_cfg["objects"][0]["shape"]["file"] = str(tmp_path / "t.json")
    with pytest.raises(SceneError, match=r"objects\[0\]\.shape\.file: .*t\.json"):
        renderer.load_scene(target_cfg)
    with pytest.raises(CalibrationError, match="no such file"):
        Calibration.read(str(tmp_path / "none.json"))


def test_render_command_with_camera(capture, tmp_path):
    """`renderer render SCENE --camera CALIB --view K` renders the scene through the calibration's view K at the
    calibration's image size; --view without --camera is refused."""
    from renderer.cli import main as cli

    _, _, _, folder, _ = capture
    scene = _scene(folder, 0, spp=1)
    scene["camera"] = {"type": "pinhole"}
    scene["image"].update(width=64, height=64)
    (tmp_path / "s.json").write_text(json.dumps(scene))
    out = tmp_path / "o.png"
    assert cli.main(["render", str(tmp_path / "s.json"), "--camera", str(folder / "calib.json"), "--view", "view3.png",
                     "-o", str(out), "--quiet"]) == 0
    img = renderer.read_image(str(out)) if hasattr(renderer, "read_image") else None
    if img is not None:
        assert img.shape[:2] == (SENSOR.height_px, SENSOR.width_px), f"the calibration's size: {img.shape}"
    assert cli.main(["render", str(tmp_path / "s.json"), "--view", "1", "-o", str(tmp_path / "p.png")]) == 2
    assert not (tmp_path / "p.png").exists()


@pytest.mark.parametrize("centre", ["sensor", "lens_axis"])
def test_mitsuba_renders_the_calibrated_camera_as_ours(capture, centre, tmp_path):
    """The same scene through Mitsuba 3 (`renderer.mitsuba.to_mitsuba`: our thin-lens sensor with the calibrated
    distortion, the print as a bitmap): the board lands on the same pixels (llvm where it runs, else a smaller
    image on scalar_rgb, whose Python sensor is slow). `lens_axis`: the same calibration with a lens tilted by
    8° about an axis at 30° and its distortion about the lens axis (OpenCV's tilted model)."""
    mi = pytest.importorskip("mitsuba")
    from renderer.mitsuba.export import develop, to_mitsuba
    from renderer.mitsuba.variants import DEFAULT_VARIANT, jit_variant_runs, load_mitsuba

    _, _, _, folder, data = capture
    if centre == "lens_axis":
        data = dict(data, theta_F_deg=8.0, tilt_axis_deg=30.0, distortion_centre="lens_axis", theta_L_deg=None,
                    theta_L_paper_deg=None)
        (tmp_path / "calib.json").write_text(json.dumps(data))
        folder = tmp_path
    variant = "llvm_ad_rgb" if jit_variant_runs("llvm_ad_rgb") else "scalar_rgb"
    cfg = _scene(folder, 4, spp=8)
    cfg["objects"][0]["shape"]["file"] = str(capture[3] / "calib.json")
    cfg["image"]["width"] = 120 if variant == "llvm_ad_rgb" else 48
    scene = renderer.load_scene(cfg)
    ours = renderer.render(scene, spp=8, progress=False, seed=3).image[..., 0].numpy()
    try:
        m = load_mitsuba(variant)
        m.set_log_level(m.LogLevel.Error)
        ms_dict, dropped = to_mitsuba(scene, 8)
        theirs = develop(scene, m.render(m.load_dict(ms_dict), seed=3, spp=8))[..., 0]
    finally:
        if sys.modules.get("mitsuba") is not None and mi.variant() != DEFAULT_VARIANT:
            load_mitsuba(DEFAULT_VARIANT)
    assert not dropped, f"nothing of the scene is dropped: {dropped}"
    board = (ours > 0) | (theirs > 0)
    diff = np.abs(ours - theirs)[board].mean() / 0.76
    assert diff < 0.05, f"mean |ours − Mitsuba| over the board: {diff:.4f} of the print's contrast"
    assert abs(float((ours > 0.02).mean()) - float((theirs > 0.02).mean())) < 0.01, "the same board area"
