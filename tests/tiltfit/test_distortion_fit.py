"""Distortion in the fit: coefficients recovered from observations made by OpenCV (a different generator),
`auto` choosing the right terms, and sharp images (no usable blur) giving a geometric calibration with U and d
reported undetermined."""
import json
import os

import cv2
import numpy as np
import pytest

from tiltfit.cli import main as cli
from tiltfit.calibrate.fit import FitOptions
from tiltfit.calibrate.flow import calibrate
from tiltfit.calibrate.model import Observations, board_points_mm, random_poses

W, H, F_PX, PITCH = 1280, 960, 560.0, 0.00155
BOARD = board_points_mm(8, 6, 25.0)


def opencv_observations(coeffs, n_views=14, noise_px=0.1, seed=3):
    """Corners by cv2.projectPoints (K with f = 560 px, principal point (650, 500)) with Gaussian noise."""
    rvec, T = random_poses(n_views, seed, distance_mm=(180.0, 320.0), max_angle_deg=35.0, max_roll_deg=20.0,
                           shift_mm=(60.0, 45.0))
    K = np.array([[F_PX, 0, 650.0], [0, F_PX, 500.0], [0, 0, 1]])
    rng = np.random.default_rng(seed)
    C = []
    for r, t in zip(rvec.numpy(), T.numpy()):
        uv, _ = cv2.projectPoints(BOARD.numpy(), r, t, K, np.array(coeffs, dtype=np.float64))
        C.append(uv.reshape(-1, 2) + noise_px * rng.standard_normal((len(BOARD), 2)))
    C = np.array(C)
    inside = (C[..., 0] > 0) & (C[..., 0] < W - 1) & (C[..., 1] > 0) & (C[..., 1] < H - 1)
    C[~inside] = np.nan
    return Observations(BOARD, C, np.full(C.shape[:2], np.nan), (W, H), PITCH)


def fit(obs, model):
    return calibrate(obs, "unified", options=FitOptions(distortion=model, free_principal_point=True,
                                                        model_selection=False, max_rms_px=None))


def test_known_coefficients_are_recovered():
    true = [-0.25, 0.06, 0.001, -0.0005, -0.006]
    res = fit(opencv_observations(true), "opencv5")
    k = res.camera.distortion.detach().numpy()
    assert abs(k[0] / true[0] - 1) < 0.01, f"k1 {k[0]:.5f}, true {true[0]}"
    assert abs(float(res.camera.focal_px.detach()) / F_PX - 1) < 0.002, "focal length"
    pp = res.camera.principal_point_px.detach().numpy()
    assert np.abs(pp - [650.0, 500.0]).max() < 1.0, f"principal point {pp}"
    s = res.sigma["distortion"][0]
    assert 0 < s < 0.01 and abs(k[0] - true[0]) < 4 * s, f"k1 within 4σ (σ = {s:.2g})"


@pytest.mark.parametrize("true,expected", [([0.0] * 5, "none"), ([-0.25, 0.06, 0, 0, 0], "k1k2")],
                         ids=["distortion-free", "k1k2"])
def test_auto_picks_the_terms_in_the_data(true, expected):
    res = fit(opencv_observations(true, seed=5), "auto")
    assert res.distortion_model == expected, f"auto chose {res.distortion_model}: {res.distortion_selection}"


def _write_dets(folder, obs, blur_px):
    paths = []
    for v in range(obs.n_views):
        c = obs.corners_px[v].numpy()
        det = {"image_size_px": [W, H],
               "corners_px": [None if not np.isfinite(p).all() else [float(p[0]), float(p[1])] for p in c],
               "blur_px": [None if not np.isfinite(p).all() else float(b) for p, b in zip(c, blur_px[v])],
               "grid_found": True}
        path = os.path.join(folder, f"view{v:02d}.json")
        with open(path, "w", encoding="utf-8") as f:
            json.dump(det, f)
        paths.append(path)
    return paths


def test_sharp_images_give_exit_0_and_undetermined_focus(tmp_path, capsys):
    """Blur widths all below a pixel (everything in focus): geometric calibration, U and d null."""
    from tiltfit.target.layout import Target

    obs = opencv_observations([-0.25, 0.06, 0, 0, 0], n_views=10, seed=7)
    rng = np.random.default_rng(1)
    blur = 0.5 + 0.15 * rng.standard_normal(obs.corners_px.shape[:2])
    dets = _write_dets(str(tmp_path), obs, blur)
    edges_x = (np.arange(10) * 25.0 - 112.5).tolist()
    edges_y = (np.arange(8) * 25.0 - 87.5).tolist()
    Target(edges_x, edges_y).save(str(tmp_path / "t.json"))
    out = tmp_path / "calib.json"
    rc = cli.main(["calibrate", *dets, "--target", str(tmp_path / "t.json"), "--pixel-pitch-mm", str(PITCH),
                   "--free-principal-point", "-q", "-o", str(out)])
    err = capsys.readouterr().err
    assert rc == 0, f"exit status {rc}: {err}"
    data = json.loads(out.read_text())
    assert data["U_mm"] is None and data["d_mm"] is None, "U and d written as null"
    assert set(data["undetermined"]) >= {"U_mm", "d_mm"}, data["undetermined"]
    assert sum("undetermined" in line for line in err.splitlines()) == 1, f"one clear stderr line: {err}"

    def numbers(x):
        if isinstance(x, dict):
            for v in x.values():
                yield from numbers(v)
        elif isinstance(x, list):
            for v in x:
                yield from numbers(v)
        elif isinstance(x, float):
            yield x

    big = [v for k, v in data.items() if k not in ("views", "target", "distortion_selection", "model_selection")
           for v in numbers(v) if abs(v) > 1e6]
    assert not big, f"nothing absurd in the file: {big}"
    assert abs(data["w_mm"] / PITCH / F_PX - 1) < 0.01, "geometry still calibrated"


@pytest.mark.parametrize("width_px", [1.5, 3.0])
def test_blur_the_same_at_every_depth_calibrates_geometrically(width_px):
    """Blur widths above the sharpness floor but unrelated to depth (a soft lens, detector blur): no focus
    explains them. The fit still calibrates the camera from the corners and reports U and d undetermined
    instead of failing or writing a focus inside the lens (before: U 9 mm for 1.5 px, no convergence for 3)."""
    from dataclasses import replace

    import torch

    obs = opencv_observations([0, 0, 0, 0, 0], n_views=10, seed=7)
    rng = np.random.default_rng(1)
    obs = replace(obs, blur_px=torch.tensor(width_px + 0.2 * rng.standard_normal(obs.corners_px.shape[:2])))
    res = calibrate(obs, "unified", options=FitOptions(distortion="none", free_principal_point=False))
    assert set(res.undetermined) == {"U_mm", "d_mm"}, res.undetermined
    f_px = float(res.camera.w_mm) / PITCH
    assert abs(f_px / F_PX - 1) < 0.005, f"focal length {f_px:.2f} px, true {F_PX}"
    d = float(res.camera.d_mm)
    assert d >= 0 and np.isfinite(d), f"d {d}"
