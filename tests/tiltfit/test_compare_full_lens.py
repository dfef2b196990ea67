"""`tiltfit compare` and the projection uncertainty through the full fitted lens (issue 33 §2): tilt, tilt axis and
the distortion's centre are part of the camera compared and of its σ; what is not a covariance is refused, and
no verdict is given where σ says nothing.

The captures are made by OpenCV (`cv2.projectPoints` with its tilted model, τ from the lens's tilt: a distortion
about the lens axis), not by the model that is fitted.
"""
import json
import math

import cv2
import numpy as np
import pytest
import torch

from renderer.cameras import Lens, Sensor
from tiltfit.files.calib import calib_dict
from tiltfit.cli.main import main
from tiltfit.uncertainty.compare import CompareError, compare
from tiltfit.files.export import opencv_camera
from tiltfit.calibrate.fit import FitOptions, _fit_camera, _set_free
from tiltfit.calibrate.model import Observations, LensCamera, axis_angle_to_matrix, board_points_mm, random_poses
from tiltfit.uncertainty.covariance import calib_lens, covariance_from_calib, projection_difference, projection_sigma

SENSOR = Sensor(1368, 912, 0.02616)
N_VIEWS = 8
BOARD = board_points_mm(7, 5, 25.0).numpy()
# θF 20° (θL 1.71° at U 618 mm), k1 −0.2 about the lens axis: the pair of the issue.
LENS = Lens(55.39, 618.4, 18.81, math.radians(20.0), sensor=SENSOR, principal_point_px=(690.3, 450.8),
            distortion=(-0.2,), distortion_centre="lens_axis")


def _calib(cam: LensCamera) -> dict:
    """The CALIB.json keys of a camera (no fit, no covariance)."""
    s = cam.summary()
    return {"pixel_pitch_mm": cam.pixel_pitch_mm, "image_size_px": list(cam.image_size_px),
            "principal_point_px": s["principal_point_px"], "w_mm": s["w_mm"], "U_mm": s["U_mm"], "d_mm": s["d_mm"],
            "theta_F_deg": s["theta_F_deg"], "theta_L_deg": s["theta_L_deg"], "tilt_axis_deg": s["tilt_axis_deg"],
            "distortion_centre": s["distortion_centre"],
            "distortion": {"model": "brown_conrady", "coefficients": s["distortion"]},
            "views": [{"R": R.tolist(), "T_mm": T.tolist()} for R, T in zip(cam.R.detach(), cam.T_mm.detach())]}


@pytest.fixture(scope="module")
def truth():
    rvec, T = random_poses(N_VIEWS, 3)
    return LensCamera.from_lens(LENS, N_VIEWS, rvec=rvec, T_mm=T)


def _opencv_capture(cam: LensCamera):
    """Clean corners (V, N, 2) from cv2.projectPoints of OpenCV's tilted model of the camera, and blur widths."""
    K, dist, R_cl = opencv_camera(_calib(cam))
    R, T = axis_angle_to_matrix(cam.rvec.detach()).numpy(), cam.T_mm.detach().numpy()
    uv = []
    for v in range(N_VIEWS):
        rv, _ = cv2.Rodrigues(R_cl.T @ R[v])
        uv.append(cv2.projectPoints(BOARD, rv, R_cl.T @ T[v], K, dist)[0].reshape(-1, 2))
    blur = np.stack([LENS.blur_px(BOARD @ R[v].T + T[v]) for v in range(N_VIEWS)])
    return np.stack(uv), blur


def test_distortion_centre_pair_no_longer_compares_equal(truth):
    """Lens axis against principal point, everything else equal: about 0.8 px median after the rotation (the
    lens axis meets the sensor w tan θL = 63 px from the principal point); it was 0 and 1e-12 px when compare
    projected without the tilt."""
    a = _calib(truth)
    b = dict(a, distortion_centre="sensor")
    res = projection_difference(a, b)
    assert 0.3 < res["median_px"] < 3.0 and 1.0 < res["worst_px"] < 10.0, \
        f"centres differ: median {res['median_px']:.3g}, worst {res['worst_px']:.3g} px"
    same = projection_difference(a, dict(a))
    assert same["worst_px"] < 1e-6, f"a calibration against itself: {same['worst_px']:.3g} px"
    # the same directions through the two lenses, no rotation: the difference is the lenses' own
    la, lb = calib_lens(a), calib_lens(b)
    v = torch.tensor([[0.2, -0.15, 1.0]], dtype=torch.float64)
    direct = float((la.project(v) - lb.project(v)).norm())
    plain = projection_difference(a, b, rotation=False)
    assert direct > 1.0 and plain["worst_px"] >= direct * 0.9, f"direct {direct:.3g}, map {plain['worst_px']:.3g}"


@pytest.fixture(scope="module")
def monte_carlo(truth):
    """16 refits of the lens-axis model (θF, w, U, d, k1, principal point, poses) to noisy OpenCV captures:
    each refit's projection difference from the truth and its predicted σ, per grid pixel."""
    uv, blur = _opencv_capture(truth)
    rng = np.random.default_rng(0)
    opts = FitOptions(model_selection=False, free_principal_point=True, distortion="k1", max_rms_px=None)
    truth_calib = _calib(truth)
    d2, s2 = [], []
    for _ in range(16):
        obs = Observations(torch.tensor(BOARD), torch.tensor(uv + rng.normal(0, 0.1, uv.shape)),
                           torch.tensor(blur + rng.normal(0, 0.1, blur.shape)), SENSOR.size_px, SENSOR.pixel_pitch)
        cam = truth.copy()
        _set_free(cam, "joint", True)
        cam.free("k1")
        fit = json.loads(json.dumps(calib_dict(_fit_camera(cam, obs, opts, mode="joint"))))
        assert fit["distortion_centre"] == "lens_axis"
        diff = projection_difference(truth_calib, fit)["difference_px"]
        d2.append(np.array([[np.nan if x is None else x for x in row] for row in diff]) ** 2)
        s2.append(projection_sigma(calib_lens(fit), covariance_from_calib(fit))[2] ** 2)
        last = fit
    return np.array(d2), np.array(s2), last


@pytest.mark.slow
def test_projection_sigma_matches_monte_carlo_of_refits(monte_carlo):
    d2, s2, fit = monte_carlo
    names = fit["intrinsics_covariance"]["names"]
    assert "theta_L_deg" in names and "tilt_axis_deg" in names, names
    for scale in (1.0, 0.5, 2.0):
        ratio = math.sqrt(np.nanmean(d2) / np.nanmean(s2 * scale ** 2))
        ok = 0.7 < ratio < 1.4
        assert ok == (scale == 1.0), f"σ × {scale}: RMS refit difference / RMS predicted σ = {ratio:.3f}"
    pu = fit["projection_uncertainty"]
    mine = projection_sigma(calib_lens(fit), covariance_from_calib(fit), nx=24)[2]
    assert pu["median_px"] == pytest.approx(float(np.nanmedian(mine)), rel=1e-6), \
        "CALIB.json's projection_uncertainty is the full lens's"


# --- what is not a covariance, and where σ says nothing -----------------------------------------------------------

@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """A small calibration with a covariance (8 views of the paper's lens, k1), written to a file."""
    from tiltfit.calibrate.flow import calibrate
    from tiltfit.calibrate.model import PAPER_LENS, PAPER_SENSOR, synthesize_observations

    rvec, T = random_poses(8, 1)
    cam = LensCamera(8, **PAPER_SENSOR, **PAPER_LENS, rvec=rvec, T_mm=T, distortion=[-0.05])
    obs = synthesize_observations(cam, board_points_mm(7, 5, 25.0), 0.1, 0.05, seed=1)
    opts = FitOptions(model_selection=False, free_principal_point=True, distortion="k1", max_rms_px=None)
    data = json.loads(json.dumps(calib_dict(calibrate(obs, "unified", options=opts))))
    path = tmp_path_factory.mktemp("cov") / "a.json"
    json.dump(data, open(path, "w"))
    return str(path), data


def _broken(data, case):
    bad = json.loads(json.dumps(data))
    m = bad["intrinsics_covariance"]["matrix"]
    if case == "negative":
        m[0][0] = -abs(m[0][0]) - 1.0
    elif case == "absurd":
        m[1][1] = 1e300
    elif case == "asymmetric":
        m[0][1], m[1][0] = m[0][1] + 1.0, m[1][0] - 1.0
    elif case == "indefinite":
        s = math.sqrt(m[1][1] * m[2][2])
        m[1][2] = m[2][1] = 3.0 * s
    return bad


@pytest.mark.parametrize("case", ["negative", "absurd", "asymmetric", "indefinite"])
def test_what_is_not_a_covariance_is_refused(fitted, tmp_path, capsys, case):
    path, data = fitted
    bad = _broken(data, case)
    b = tmp_path / "b.json"
    json.dump(bad, open(b, "w"))
    assert main(["compare", path, str(b)]) == 2, f"{case}: expected exit status 2"
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "intrinsics_covariance" in err and "b.json" in err, f"{case}: {err!r}"
    with pytest.raises(CompareError, match="intrinsics_covariance"):
        compare(data, bad)
    assert main(["compare", path, path]) == 0, "the intact file compares"
    capsys.readouterr()


def test_non_finite_covariance_is_refused(fitted, tmp_path, capsys):
    path, data = fitted
    bad = json.loads(json.dumps(data))
    bad["intrinsics_covariance"]["matrix"][0][0] = float("nan")
    b = tmp_path / "b.json"
    b.write_text(json.dumps(bad))  # NaN as Python writes it
    assert main(["compare", path, str(b)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "b.json" in err, err


def test_no_verdict_where_sigma_says_nothing(fitted):
    """Two 1×1-pixel calibrations whose focal lengths differ by 60 px, and a σ larger than the image, get no
    verdict (they were called consistent)."""
    _, data = fitted
    tiny = json.loads(json.dumps(data))
    tiny |= {"image_size_px": [1, 1], "principal_point_px": [0.0, 0.0]}
    other = json.loads(json.dumps(tiny))
    other["w_mm"] += 60 * other["pixel_pitch_mm"]
    res = compare(tiny, other)
    assert res["consistent"] is None and res["verdict"].startswith("no verdict") and "1×1" in res["verdict"], \
        res["verdict"]
    huge = json.loads(json.dumps(data))
    m = huge["intrinsics_covariance"]["matrix"]
    m[0][0] = 1e10  # σ of the focal length 1e5 px: a covariance, but one that says nothing
    far = json.loads(json.dumps(data))
    far["w_mm"] += 60 * far["pixel_pitch_mm"]
    res = compare(huge, far)
    assert res["consistent"] is None and "larger than the image" in res["verdict"], res["verdict"]
    res = compare(data, far)
    assert res["consistent"] is False, f"60 px of focal length with the real σ: {res['verdict']}"
