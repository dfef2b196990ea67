"""tiltfit on the shipped real photos (data/real/gopro_wide, 8×6 corners, strong barrel distortion), against
OpenCV's calibrateCamera on the very same corners (cv2.findChessboardCornersSB, cached beside the photos).

Both fits: one focal length (OpenCV with CALIB_FIX_ASPECT_RATIO), free principal point, the same distortion
terms. RMS in OpenCV's definition (per corner)."""
import json
import math
import os

import cv2
import numpy as np
import pytest

from tiltfit.calibrate.fit import FitOptions
from tiltfit.calibrate.flow import calibrate
from tiltfit.calibrate.model import Observations
from tiltfit.target.layout import load_target

DATA = os.path.join(os.path.dirname(__file__), "..", "..", "data", "real", "gopro_wide")
FLAGS = {"k1k2": cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST, "opencv5": 0, "rational": cv2.CALIB_RATIONAL_MODEL,
         "rational5": cv2.CALIB_RATIONAL_MODEL | cv2.CALIB_FIX_K3 | cv2.CALIB_FIX_K5 | cv2.CALIB_FIX_K6}


@pytest.fixture(scope="module")
def real():
    target = load_target(os.path.join(DATA, "target.json"))
    with open(os.path.join(DATA, "corners_opencv.json"), encoding="utf-8") as f:
        dets = json.load(f)
    names = sorted(k for k, v in dets.items() if v)
    C = np.array([dets[n]["corners_px"] for n in names], dtype=np.float64)
    obs = Observations(target.feature_points(), C, np.full(C.shape[:2], np.nan), (1280, 960), 0.00155, names)
    return obs, len(dets)


def opencv(obs, model):
    obj = [obs.points_mm.numpy().astype(np.float32)] * obs.n_views
    img = [c.numpy().astype(np.float32) for c in obs.corners_px]
    K0 = np.array([[500.0, 0, 639.5], [0, 500.0, 479.5], [0, 0, 1]])
    rms, K, dist, _, _ = cv2.calibrateCamera(obj, img, obs.image_size_px, K0, None,
                                             flags=FLAGS[model] | cv2.CALIB_FIX_ASPECT_RATIO,
                                             criteria=(cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12))
    return rms, K, dist.ravel()


def test_reference_corners_cover_the_set(real):
    obs, n = real
    assert n == 36 and obs.n_views >= 34, f"findChessboardCornersSB found {obs.n_views} of {n} boards"


@pytest.mark.parametrize("model", ["k1k2", "opencv5", "rational5", "rational"])
def test_calibration_matches_opencv_on_the_same_corners(real, model):
    obs, _ = real
    res = calibrate(obs, "unified", options=FitOptions(distortion=model, free_principal_point=True,
                                                       model_selection=False, max_rms_px=None))
    rms = math.sqrt(res.rss["corners"] / (res.rss["n_corners"] / 2))
    rms_cv, K, _ = opencv(obs, model)
    F = float(res.camera.focal_px.detach())
    assert rms <= rms_cv * (1 + 1e-6), f"{model}: RMS {rms:.5f} px, OpenCV {rms_cv:.5f} px"
    assert abs(F / K[0, 0] - 1) < 0.01, f"{model}: focal {F:.2f} px vs OpenCV {K[0, 0]:.2f} px"
    assert res.undetermined == ["U_mm", "d_mm"], f"no blur widths: U and d undetermined ({res.undetermined})"


def test_auto_frees_terms_the_real_lens_needs(real):
    obs, _ = real
    res = calibrate(obs, "unified", options=FitOptions(distortion="auto", free_principal_point=True,
                                                       model_selection=False))
    assert res.distortion_model in ("opencv5", "rational5", "rational"), f"auto chose {res.distortion_model}"
    steps = [e["model"] for e in res.distortion_selection]
    assert steps[:4] == ["none", "k1", "k1k2", "opencv5"], f"tried in order: {steps}"
