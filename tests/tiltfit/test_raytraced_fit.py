"""A joint fit on images made by the ray tracer (renderer's thin-lens camera, Monte Carlo aperture sampling),
not by the model being fitted: the lens of the simulated camera tilted by θL = 5° about its centre, five
target views at 1/8 of the EOS 6D's resolution (684 × 456), 16 samples per pixel, corners and blur from
`tiltfit.detect.chessboard`."""
import math
import os
import shutil
import sys

import numpy as np
import pytest
import torch

from renderer import Lens
from tiltfit.experiments import synth
from tiltfit.experiments import reproduce
from tiltfit.calibrate.fit import FitOptions
from tiltfit.calibrate.flow import calibrate
from tiltfit.calibrate.model import Observations

THETA_L_DEG = 5.0
DOWNSCALE = 8


@pytest.mark.slow
def test_joint_fit_on_ray_traced_tilted_images():
    detect = pytest.importorskip("tiltfit.detect.chessboard").detect
    torch.manual_seed(0)
    cam0 = reproduce.SimulatedCamera().untilted
    cam = Lens.from_tilt(cam0.w, cam0.f, math.radians(THETA_L_DEG), cam0.d, sensor=cam0.sensor.binned(DOWNSCALE))
    U = cam.U
    target = reproduce.calibration_target(reproduce.SetValues())
    C, B = [], []
    for v, pose in enumerate(reproduce.TARGET_VIEWS):
        R, T = reproduce.target_pose(target, *pose)
        view = synth.render_view(target, cam, R, T, method="renderer", spp=16, seed=v)
        det = detect(view.image, target)
        C.append(det.corners_px)
        B.append(det.blur_px)
    obs = Observations(target.feature_points(), np.array(C), np.array(B), cam.sensor.size_px, cam.sensor.pixel_pitch)
    assert int(obs.corner_mask.sum()) >= 0.9 * obs.corner_mask.numel(), "the detector finds the corners"
    res = calibrate(obs, "joint", options=FitOptions(model_selection=False))
    v, s = res.values, res.sigma
    msg = {k: (round(v[k], 4), round(s[k], 4)) for k in ("w_mm", "U_mm", "d_mm", "theta_L_deg")}
    assert res.undetermined == [], f"blurred images determine U and d: {res.undetermined}"
    assert abs(v["theta_L_deg"] - THETA_L_DEG) < 0.15, f"θL {msg}"
    assert abs(v["w_mm"] / cam0.w - 1) < 0.003, f"w {msg}"
    assert abs(v["U_mm"] / U - 1) < 0.005, f"U {msg} (true {U:.2f})"
    assert abs(v["d_mm"] / cam0.d - 1) < 0.01, f"d {msg}"
    for key, true in (("theta_L_deg", THETA_L_DEG), ("U_mm", U), ("d_mm", cam0.d), ("w_mm", cam0.w)):
        assert abs(v[key] - true) < 5 * s[key], f"{key}: error {v[key] - true:+.4g} beyond 5σ ({s[key]:.3g})"


def test_views_of_one_board_share_one_texture_file(monkeypatch, tmp_path):
    """`synth.render_with_renderer` rasterises and writes a board's texture once a process (one grey channel), not
    once a view: two views of one board make one texture, a third board another, and each image is the one an RGB
    texture written for that view alone gives, to the bit."""
    import renderer
    from tiltfit.target import raster
    from tiltfit.target.layout import Target

    made = []
    plain = raster.target_texture
    monkeypatch.setattr(raster, "target_texture", lambda *a, **k: made.append(a[0]) or plain(*a, **k))
    monkeypatch.setattr(synth, "_TEXTURES", {})
    board = Target((0.0, 20.0, 40.0, 60.0), (0.0, 20.0, 40.0), (0, 0), 10.0)
    other = Target((0.0, 25.0, 50.0, 75.0), (0.0, 25.0, 50.0), (0, 0), 10.0)
    cam = Lens(16.0, 400.0, 4.0, 0.0, renderer.Sensor(48, 32, 0.05))
    images = []
    for k, target in enumerate((board, board, other)):
        R, T = reproduce.target_pose(target, 10.0 * k, 5.0, 400.0)
        images.append(synth.render_with_renderer(target, cam, R, T, 0.05, 0.8, 0.3, spp=2, seed=k))
        # The reference: the board's RGB texture written for this view alone, through the same scene.
        tex = str(tmp_path / f"rgb{k}.exr")
        renderer.write_image(tex, plain(target, 10.0, 0.05, 0.8))
        scene = synth.renderer_scene(target, cam, R, T, tex, spp=2)
        scene["image"]["background"] = [0.3] * 3
        want = renderer.render(renderer.load_scene(scene), spp=2, seed=k, dtype=torch.float32).image.mean(-1)
        assert np.array_equal(images[-1], want.numpy().astype(np.float64)), f"view {k}: not the RGB texture's image"
    assert made == [board, other], f"textures rasterised for {len(made)} views of 2 boards"


def test_texture_folders_of_ended_processes_are_removed(monkeypatch):
    """A pool's terminated worker skips its exit handlers and leaves its texture folder: a process making its first
    texture removes the folders of processes that have ended (named by their process ids), not those of live ones."""
    import subprocess
    import tempfile

    from tiltfit.target.layout import Target

    ended = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                           text=True, check=True).stdout.strip()
    dead = tempfile.mkdtemp(prefix=f"{synth.TEXTURE_PREFIX}{ended}-")
    alive = tempfile.mkdtemp(prefix=f"{synth.TEXTURE_PREFIX}{os.getppid()}-")
    open(os.path.join(dead, "target1.exr"), "wb").close()
    try:
        monkeypatch.setattr(synth, "_TEXTURES", {})
        monkeypatch.setattr(synth, "_TEXTURE_FOLDER", {})
        path = synth._texture_file(Target((0.0, 20.0, 40.0), (0.0, 20.0, 40.0), (0, 0), 10.0), 2.0, 0.05, 0.8)
        assert os.path.isfile(path) and f"{synth.TEXTURE_PREFIX}{os.getpid()}-" in path, path
        assert not os.path.exists(dead), "the ended process's texture folder is left"
        assert os.path.isdir(alive), "a live process's texture folder was removed"
    finally:
        shutil.rmtree(dead, True)
        shutil.rmtree(alive, True)
        shutil.rmtree(synth._TEXTURE_FOLDER.get("folder", dead), True)
