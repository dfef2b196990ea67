"""tiltfit.files.export: OpenCV FileStorage round trip through cv2.projectPoints, --init from an OpenCV file, kornia."""
import json
import os
import sys

import cv2
import numpy as np
import pytest
import torch

from tiltfit.cli import main as cli
from tiltfit.files.calib import calib_dict, camera_from_calib, read_calib
from tiltfit.files.export import ExportError, kornia_camera
from tiltfit.files.opencv_file import read_opencv, write_opencv
from tiltfit.calibrate.fit import FitOptions
from tiltfit.calibrate.flow import calibrate
from tiltfit.target.layout import load_target

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))  # tests/real_detections.py
from real_detections import observations  # noqa: E402

DATA = os.path.join(os.path.dirname(__file__), "..", "..", "data", "real", "gopro_wide")


@pytest.fixture(scope="module")
def real_calib():
    target = load_target(os.path.join(DATA, "target.json"))
    obs = observations(DATA, 0.00155, "corners_opencv.json")[0].subset(range(12))
    res = calibrate(obs, "unified", options=FitOptions(distortion="rational5", free_principal_point=True,
                                                       model_selection=False))
    return obs, res, calib_dict(res, obs=obs, target=target.to_dict())


def test_opencv_round_trip_projects_within_a_hundredth_of_a_pixel(real_calib, tmp_path):
    obs, res, data = real_calib
    path = str(tmp_path / "camera.yml")
    write_opencv(data, path)
    fs = cv2.FileStorage(path, cv2.FILE_STORAGE_READ)
    K, dist = fs.getNode("camera_matrix").mat(), fs.getNode("distortion_coefficients").mat()
    rv, tv = fs.getNode("rvecs").mat(), fs.getNode("tvecs").mat()
    assert (fs.getNode("image_width").real(), fs.getNode("image_height").real()) == (1280, 960), "image size"
    fs.release()
    assert dist.size == 8, "rational5 (OpenCV's rational model, k3 k5 k6 = 0): 8 coefficients"
    with torch.no_grad():
        ours = res.camera(obs.points_mm, with_blur=False)[0].numpy()
    worst = 0.0
    for v in range(obs.n_views):
        uv, _ = cv2.projectPoints(obs.points_mm.numpy(), rv[v], tv[v], K, dist)
        worst = max(worst, float(np.abs(uv.reshape(-1, 2) - ours[v]).max()))
    assert worst < 0.01, f"cv2.projectPoints differs from our projection by {worst:.2g} px"


def test_tilted_lens_is_noted_in_the_file(real_calib, tmp_path):
    _, _, data = real_calib
    tilted = dict(data, theta_F_deg=40.0, theta_L_deg=3.0, U_mm=650.0, d_mm=18.0)
    path = str(tmp_path / "tilted.yml")
    write_opencv(tilted, path)
    text = open(path, encoding="utf-8").read()
    assert "tilted" in text and "not represented" in text, "the file says what OpenCV cannot represent"


def test_init_from_opencv_file(real_calib, tmp_path):
    obs, res, data = real_calib
    path = str(tmp_path / "camera.yml")
    write_opencv(data, path)
    back = read_opencv(path)
    assert abs(back["w_mm"] - data["w_mm"]) < 1e-9 and back["U_mm"] is None, "focal length read back"
    assert np.allclose(back["distortion"]["coefficients"], data["distortion"]["coefficients"]), "distortion"
    cam = camera_from_calib(back)
    assert np.allclose(cam.distortion.detach().numpy(), data["distortion"]["coefficients"]), "camera built"
    dets = []
    for v in range(obs.n_views):
        p = tmp_path / f"d{v}.json"
        p.write_text(json.dumps({"image_size_px": [1280, 960], "corners_px": obs.corners_px[v].tolist(),
                                 "blur_px": [None] * obs.corners_px.shape[1], "grid_found": True}))
        dets.append(str(p))
    out = tmp_path / "calib.json"
    rc = cli.main(["calibrate", *dets, "--target", os.path.join(DATA, "target.json"), "--pixel-pitch-mm",
                   "0.00155", "--init", path, "--distortion", "rational5", "--free-principal-point", "--board", "flat", "--held-out",
                   "0", "-q", "-o", str(out)])
    assert rc == 0, "calibrate --init camera.yml"
    new = read_calib(str(out))
    assert abs(new["w_mm"] / data["w_mm"] - 1) < 1e-6, "same calibration from the OpenCV start"
    bad = tmp_path / "bad.yml"
    fs = cv2.FileStorage(str(bad), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 10)
    fs.release()
    with pytest.raises(ExportError, match="camera_matrix"):
        read_opencv(str(bad), 0.001)


def test_kornia_pinhole_camera_projects_like_the_model(real_calib):
    obs, res, data = real_calib
    no_dist = dict(data, distortion={"model": "brown_conrady", "coefficients": [0.0] * 5})
    cam = kornia_camera(no_dist)
    assert cam.batch_size == obs.n_views, "one camera per view"
    with pytest.raises(ExportError, match="distortion"):
        kornia_camera(data)
    ours = camera_from_calib(no_dist)
    X = obs.points_mm[None].expand(obs.n_views, -1, -1)
    with torch.no_grad():
        uv_k = cam.project(X)
        uv = ours(obs.points_mm, with_blur=False)[0]
    assert (uv_k - uv).abs().max() < 1e-6, "kornia projects as the model does"
