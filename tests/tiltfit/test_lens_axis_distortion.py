"""Distortion about a tilted lens's own axis (`renderer.Lens.distortion_centre` "lens_axis") and OpenCV's tilted
model (τx, τy) both ways.

Captures come from a generator other than the fitted model: the corners from `cv2.projectPoints` with OpenCV's
14-coefficient tilted model (τ, K and the poses in OpenCV's lens frame computed here from the lens's axis), the
blur widths from a ray-geometric thin-lens formula written here (the image point of each corner by the Gaussian
lens equation along the tilted lens's axis, the aperture disc projected through it onto the sensor, the
equivalent-area diameter of that outline) — neither calls our projection or blur code.
"""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

from renderer import Lens
from renderer.cameras import EOS_6D, LensCamera
from tiltfit.files.calib import calib_dict, camera_from_calib, validate_calib
from tiltfit.calibrate.flow import calibrate
from tiltfit.experiments import reproduce
from tiltfit.files.opencv_file import opencv_text, read_opencv
from tiltfit.calibrate.fit import FitOptions
from tiltfit.calibrate.model import Observations

SENSOR = EOS_6D.binned(4)
POSES = ((30.0, 0.0, 560.0), (-25.0, 0.0, 480.0), (0.0, 35.0, 600.0), (0.0, -30.0, 650.0), (20.0, 20.0, 540.0),
         (-15.0, -20.0, 700.0))
DISTORTION = (-0.12, 0.02)  # k1, k2 about the lens axis (the capture)
NOISE_CORNER_PX, NOISE_BLUR_PX = 0.05, 0.1
W_MM, F_MM, D_MM = Lens.paper().w, Lens.paper().f, Lens.paper().d
PP = (SENSOR.width_px - 1) / 2.0, (SENSOR.height_px - 1) / 2.0


# ------------------------------------------------------------------------------------------------ the generator

def _axis(theta_L: float, phi: float) -> np.ndarray:
    """The tilted lens's axis, camera frame: the normal of the lens plane spanned by the tilt axis
    a = (cos φ, sin φ, 0) and b cos θL + ẑ sin θL, b = (−sin φ, cos φ, 0)."""
    a = np.array([math.cos(phi), math.sin(phi), 0.0])
    b = np.array([-math.sin(phi), math.cos(phi), 0.0]) * math.cos(theta_L) + np.array([0, 0, math.sin(theta_L)])
    n = np.cross(a, b)
    return n / np.linalg.norm(n)


def _opencv_lens(theta_L: float, phi: float):
    """OpenCV's K, 14 coefficients and camera_from_lens rotation of our lens (the relation derived from OpenCV's
    documentation: its tilt R_y(τy) R_x(τx) maps its camera frame, the lens frame, to the sensor's)."""
    n = _axis(theta_L, phi)
    tx, ty = math.asin(n[1]), math.atan2(-n[0], n[2])
    Rx = np.array([[1, 0, 0], [0, math.cos(tx), math.sin(tx)], [0, -math.sin(tx), math.cos(tx)]])
    Ry = np.array([[math.cos(ty), 0, -math.sin(ty)], [0, 1, 0], [math.sin(ty), 0, math.cos(ty)]])
    R = Ry @ Rx
    assert np.allclose(R[:, 2], n), "OpenCV's tilt turns z onto the lens axis"
    f = W_MM / SENSOR.pixel_pitch / n[2]
    K = np.array([[f, 0, PP[0] + f * n[0]], [0, f, PP[1] + f * n[1]], [0, 0, 1.0]])
    dist = np.zeros(14)
    dist[:2] = DISTORTION
    dist[12:] = tx, ty
    return K, dist, R


def _blur_px(p_cam: np.ndarray, theta_L: float, phi: float) -> np.ndarray:
    """Blur-disc diameters (pixels) of a thin lens of focal length F_MM and aperture D_MM tilted by θL about the
    axis at φ, sensor at z = −W_MM: each point's image P' = −P f / (s − f) (s = n · P, Gaussian lens equation
    along the lens axis), the aperture's rim projected from P' onto the sensor, 2 sqrt(area / π)."""
    n = _axis(theta_L, phi)
    a = np.array([math.cos(phi), math.sin(phi), 0.0])
    b = np.cross(n, a)
    t = np.linspace(0, 2 * math.pi, 4097)[:-1]
    rim = 0.5 * D_MM * (np.cos(t)[:, None] * a + np.sin(t)[:, None] * b)            # (M, 3), lens plane
    s = p_cam @ n
    image = -p_cam * (F_MM / (s - F_MM))[:, None]                                     # (N, 3)
    lam = (-W_MM - rim[None, :, 2]) / (image[:, None, 2] - rim[None, :, 2])          # rim + λ (P' − rim) on z = −w
    on_sensor = rim[None] + lam[..., None] * (image[:, None, :] - rim[None])
    x, y = on_sensor[..., 0], on_sensor[..., 1]
    area = 0.5 * np.abs((x * np.roll(y, -1, 1) - np.roll(x, -1, 1) * y).sum(1))
    return 2 * np.sqrt(area / math.pi) / SENSOR.pixel_pitch


def _observations(theta_L: float, phi: float, seed: int) -> Observations:
    target = reproduce.calibration_target(reproduce.SetValues())
    pts = target.feature_points()
    K, dist, R_cl = _opencv_lens(theta_L, phi)
    rng = np.random.default_rng(seed)
    corners, blur = [], []
    for pose in POSES:
        R, T = reproduce.target_pose(target, *pose)
        rvec, _ = cv2.Rodrigues(R_cl.T @ R)
        uv, _ = cv2.projectPoints(pts, rvec, R_cl.T @ T, K, dist)
        uv = uv.reshape(-1, 2)
        assert ((uv > 0) & (uv < SENSOR.size_px)).all(), f"pose {pose}: the board leaves the image"
        corners.append(uv + rng.normal(0, NOISE_CORNER_PX, uv.shape))
        blur.append(_blur_px(pts @ R.T + T, theta_L, phi) + rng.normal(0, NOISE_BLUR_PX, len(pts)))
    return Observations(pts, np.stack(corners), np.stack(blur), SENSOR.size_px, SENSOR.pixel_pitch)


def test_the_generator_is_a_thin_lens():
    """The blur formula vanishes on the plane of focus of the hinge and Scheimpflug rules (`Lens.from_tilt`), and
    OpenCV's projection of an untilted lens is the plain pinhole: the generator describes the lens we fit."""
    theta_L, phi = math.radians(5.0), math.radians(30.0)
    lens = Lens.from_tilt(W_MM, F_MM, theta_L, D_MM, phi=phi)
    m, U = lens.focus_plane()
    g = np.random.default_rng(0)
    xy = g.uniform(-150, 150, (20, 2))
    sharp = np.c_[xy, (U - m[0] * xy[:, 0] - m[1] * xy[:, 1]) / m[2]]
    assert _blur_px(sharp, theta_L, phi).max() < 1e-4, "no blur on the plane of focus (the area's rounding aside)"
    K, dist, R = _opencv_lens(0.0, 0.0)
    p = np.c_[xy, np.full(20, 600.0)]
    uv, _ = cv2.projectPoints(p, np.zeros(3), np.zeros(3), K, np.zeros(5))
    assert np.allclose(uv.reshape(-1, 2), Lens(W_MM, 600.0, 1.0, sensor=SENSOR).project(p), atol=1e-9), "pinhole"


# ------------------------------------------------------------------------------------------------ calibrations

OPTIONS = FitOptions(distortion="k1k2")
TRUE_THETA_L, TRUE_PHI = 5.0, 30.0


@pytest.fixture(scope="module")
def untilted():
    obs = _observations(0.0, 0.0, seed=1)
    stage1 = calibrate(obs, "unified", options=FitOptions(distortion="k1k2", model_selection=False))
    return obs, stage1


@pytest.fixture(scope="module")
def tilted(untilted):
    obs = _observations(math.radians(TRUE_THETA_L), math.radians(TRUE_PHI), seed=2)
    return obs, calibrate(obs, "joint", init=untilted[1].camera, options=OPTIONS)


@pytest.mark.slow
def test_tilted_lens_axis_distortion_is_chosen_and_recovered(tilted):
    obs, res = tilted
    test = res.model_selection["distortion_centre"]
    assert test["justified"] and test["chosen"] == "lens_axis", f"the lens-axis centre is chosen: {test}"
    assert res.camera.distortion_centre == "lens_axis", "the fit reported is the lens-axis one"
    assert res.model_selection["tilt_axis"]["fitted"], f"the tilt axis is freed: {res.model_selection['tilt_axis']}"
    v, s = res.values, res.sigma
    k1, s_k1 = float(res.camera.dist_k1.detach()), s["distortion"][0]
    for name, value, sigma, truth, bound in (("θL", v["theta_L_deg"], s["theta_L_deg"], TRUE_THETA_L, 0.05),
                                             ("φ", v["tilt_axis_deg"], s["tilt_axis_deg"], TRUE_PHI, 2.0),
                                             ("k1", k1, s_k1, DISTORTION[0], 0.01)):
        assert 0 < sigma < bound, f"{name}: σ {sigma:.3g} should be positive and below {bound}"
        assert abs(value - truth) < 3 * sigma, f"{name} {value:.5f} ± {sigma:.2g} vs {truth} (|err| < 3σ)"


@pytest.mark.slow
def test_sensor_centred_model_is_kept_on_untilted_captures(untilted):
    obs, stage1 = untilted
    res = calibrate(obs, "joint", init=stage1.camera, options=OPTIONS)
    test = res.model_selection["distortion_centre"]
    assert not test["justified"] and test["chosen"] == "sensor", f"no evidence for the lens axis: {test}"
    assert res.camera.distortion_centre == "sensor", "the simpler, usual centre is kept"


# ------------------------------------------------------------------------------------------------ OpenCV τ files

def _cv_projection(text: str, points: np.ndarray) -> np.ndarray:
    """(V, N, 2) cv2.projectPoints of every view of an OpenCV FileStorage text."""
    fs = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    K, dist = fs.getNode("camera_matrix").mat(), fs.getNode("distortion_coefficients").mat()
    rv, tv = fs.getNode("rvecs").mat(), fs.getNode("tvecs").mat()
    fs.release()
    return np.stack([cv2.projectPoints(points, rv[v], tv[v], K, dist)[0].reshape(-1, 2) for v in range(len(rv))])


def _camera(theta_L_deg: float, phi_deg: float) -> LensCamera:
    gen = torch.Generator().manual_seed(3)
    rvec = 0.3 * (2 * torch.rand(4, 3, generator=gen, dtype=torch.float64) - 1)
    T = torch.tensor([[10.0, -20.0, 600.0], [-30.0, 15.0, 520.0], [0.0, 0.0, 700.0], [25.0, 25.0, 560.0]])
    lens = Lens.from_tilt(W_MM, F_MM, math.radians(theta_L_deg), D_MM, sensor=SENSOR, phi=math.radians(phi_deg),
                          principal_point_px=(690.3, 450.8), distortion=(-0.12, 0.02, 4e-4, -3e-4, 0.01),
                          distortion_centre="lens_axis")
    return LensCamera.from_lens(lens, 4, rvec=rvec, T_mm=T)


def _dict(cam: LensCamera) -> dict:
    """The CALIB.json keys `tiltfit export` reads, of a camera."""
    s = cam.summary()
    return {"pixel_pitch_mm": cam.pixel_pitch_mm, "image_size_px": list(cam.image_size_px),
            "principal_point_px": s["principal_point_px"], "w_mm": s["w_mm"], "U_mm": s["U_mm"],
            "d_mm": s["d_mm"], "theta_F_deg": s["theta_F_deg"], "theta_L_deg": s["theta_L_deg"],
            "tilt_axis_deg": s["tilt_axis_deg"], "distortion_centre": s["distortion_centre"],
            "distortion": {"model": "brown_conrady", "coefficients": s["distortion"]},
            "views": [{"R": R.tolist(), "T_mm": T.tolist()} for R, T in zip(cam.R.detach(), cam.T_mm.detach())]}


@pytest.mark.parametrize("theta_L_deg,phi_deg", [(5.0, 0.0), (-5.0, 0.0), (5.0, -40.0), (-5.0, 65.0)])
def test_exported_tau_model_projects_as_ours(theta_L_deg, phi_deg):
    cam = _camera(theta_L_deg, phi_deg)
    X = reproduce.calibration_target(reproduce.SetValues()).feature_points()
    text = opencv_text(_dict(cam))
    with torch.no_grad():
        ours = cam(torch.as_tensor(X), with_blur=False)[0].numpy()
    worst = float(np.abs(_cv_projection(text, X) - ours).max())
    assert worst < 0.01, f"θL {theta_L_deg}°, φ {phi_deg}°: cv2.projectPoints differs by {worst:.2g} px"
    fs = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    K = fs.getNode("camera_matrix").mat()
    fs.release()
    with torch.no_grad():
        axis_px = cam.lens.lens_axis_px
    assert np.allclose(K[:2, 2], axis_px, atol=1e-9), f"OpenCV's principal point {K[:2, 2]} is where the lens " \
        f"axis meets the sensor {axis_px}"
    shift = math.hypot(axis_px[0] - 690.3, axis_px[1] - 450.8) * SENSOR.pixel_pitch
    assert shift == pytest.approx(W_MM * math.tan(math.radians(abs(theta_L_deg))), rel=1e-9), \
        "w tan θL from the principal point"
    assert "tau" in text and "not represented" in text, "the file says what OpenCV cannot hold"


@pytest.mark.slow
def test_exported_calibration_round_trips_through_cv2(tilted):
    obs, res = tilted
    data = calib_dict(res, obs=obs)
    assert data["distortion_centre"] == "lens_axis", "CALIB.json names the centre"
    validate_calib("calib.json", data)
    text = opencv_text(data)
    with torch.no_grad():
        ours = res.camera(obs.points_mm, with_blur=False)[0].numpy()
    worst = float(np.abs(_cv_projection(text, obs.points_mm.numpy()) - ours).max())
    assert worst < 0.01, f"cv2.projectPoints of the exported calibration differs by {worst:.2g} px"


def test_import_of_an_opencv_tau_file_projects_as_opencv(tmp_path):
    g = np.random.default_rng(7)
    f = 1900.0 + 200 * g.random()
    K = np.array([[f, 0, 650 + 40 * g.random()], [0, f, 470 + 40 * g.random()], [0, 0, 1]])
    dist = np.zeros(14)
    dist[:8] = [-0.15, 0.03, 6e-4, -4e-4, 0.005, 0.01, -0.004, 0.002] * (0.5 + g.random(8))
    dist[12:] = np.radians(g.uniform(-6, 6, 2))
    rv = g.uniform(-0.3, 0.3, (3, 3))
    tv = np.c_[g.uniform(-40, 40, (3, 2)), g.uniform(450, 700, 3)]
    path = str(tmp_path / "tilted.yml")
    fs = cv2.FileStorage(path, cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 1368)
    fs.write("image_height", 912)
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", dist.reshape(1, -1))
    fs.write("rvecs", rv)
    fs.write("tvecs", tv)
    fs.write("pixel_pitch_mm", SENSOR.pixel_pitch)
    fs.release()
    data = validate_calib(path, read_opencv(path))
    assert data["distortion_centre"] == "lens_axis" and abs(data["theta_L_deg"]) > 0.1, "a tilted lens"
    cam = camera_from_calib(data)
    X = reproduce.calibration_target(reproduce.SetValues()).feature_points()
    with torch.no_grad():
        ours = cam(torch.as_tensor(X), with_blur=False)[0].numpy()
    theirs = np.stack([cv2.projectPoints(X, rv[v], tv[v], K, dist)[0].reshape(-1, 2) for v in range(3)])
    worst = float(np.abs(ours - theirs).max())
    assert worst < 0.01, f"the imported τ camera differs from OpenCV's projection by {worst:.2g} px"
    back = _cv_projection(opencv_text({**data, "U_mm": None, "d_mm": None}), X)
    assert float(np.abs(back - theirs).max()) < 0.01, "exported again, OpenCV projects the same"


def test_rendered_rays_follow_the_lens_axis_distortion():
    """The renderer's camera of such a lens (`ThinLensCamera.from_calibration`) traces each pixel through its
    ideal position, undistorted in the lens frame: the chief ray of the pixel a point projects to passes through
    that point; θL = 0 gives the same rays as the distortion about the principal point."""
    from renderer import ThinLensCamera

    lens = _camera(5.0, 30.0).lens
    with torch.no_grad():
        lens = Lens(float(lens.w), float(lens.U), float(lens.d), float(lens.theta_F), SENSOR,
                    tuple(float(c) for c in lens.principal_point_px), tuple(float(k) for k in lens.distortion),
                    float(lens.phi), "lens_axis")
    cam = ThinLensCamera.from_calibration(lens, torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64))
    g = np.random.default_rng(5)
    p = np.c_[g.uniform(-200, 200, 40), g.uniform(-130, 130, 40), g.uniform(450, 800, 40)]
    uv = torch.as_tensor(lens.project(p))
    rays = cam.generate_rays(uv)
    assert bool(rays.valid.all()), "every pixel has an undistorted direction"
    d = rays.direction.numpy()
    off = np.linalg.norm(np.cross(d, p / np.linalg.norm(p, axis=1, keepdims=True)), axis=1).max()
    assert off < 1e-7, f"the chief rays pass through the points (sine of the angle {off:.2g}; 1e-7 is 2e-4 px)"
    flat = lens.with_(theta_F=0.0)
    a = ThinLensCamera.from_calibration(flat, torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64))
    b = ThinLensCamera.from_calibration(flat.with_(distortion_centre="sensor"), torch.eye(3, dtype=torch.float64),
                                        torch.zeros(3, dtype=torch.float64))
    assert torch.equal(a.generate_rays(uv).direction, b.generate_rays(uv).direction), "θL = 0: the same rays"


def test_scene_file_thin_lens_with_distortion_about_its_axis():
    """A scene file's `camera.distortion.centre: "lens_axis"` on a tilted thin lens: the camera projects as OpenCV's
    tilted model of that lens (built here from the lens's axis), and every lens sample's ray at the distorted pixel
    of a point on the plane of focus passes through it; a wrong centre is refused by name."""
    from renderer.core.params import SceneError
    from renderer.scene.file import build_scene

    W, H, pitch = SENSOR.width_px, SENSOR.height_px, SENSOR.pixel_pitch
    theta_L, phi = math.radians(5.0), math.radians(30.0)
    cfg = {"image": {"width": W, "height": H},
           "camera": {"type": "thin_lens", "w": W_MM, "f": F_MM, "d": D_MM, "sensor_size": [W * pitch, H * pitch],
                      "theta_L_deg": 5.0, "tilt_axis_deg": 30.0,
                      "distortion": {"model": "brown_conrady", "coefficients": list(DISTORTION), "centre": "lens_axis"}},
           "objects": []}
    cam = build_scene(cfg).camera
    m, U = cam.lens.focus_plane()
    g = np.random.default_rng(8)
    xy = g.uniform(-150, 150, (12, 2))
    p = np.c_[xy, (U - m[0] * xy[:, 0] - m[1] * xy[:, 1]) / m[2]]       # on the plane of focus
    uv = cam.project(torch.as_tensor(p)).to(torch.float64)
    K, dist, R = _opencv_lens(theta_L, phi)
    ref, _ = cv2.projectPoints(p @ R, np.zeros(3), np.zeros(3), K, dist)
    assert np.abs(uv.numpy() - ref.reshape(-1, 2)).max() < 1e-4, \
        "the chief ray projects as OpenCV's tilted model (to the scene camera's float32 pose)"
    lens_uv = torch.rand(12, 64, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    rays = cam.generate_rays(uv[:, None].expand(12, 64, 2), lens_uv)
    o, d = rays.origin.to(torch.float64), rays.direction.to(torch.float64)
    pt = torch.as_tensor(p)[:, None]
    miss = torch.linalg.cross(pt - o, d).norm(dim=-1).max()          # distance of each ray from its point
    assert bool(rays.valid.all()) and miss < 1e-3, f"rays meet at the point: {miss:.2g} mm"
    bad = dict(cfg, camera=dict(cfg["camera"], distortion={"coefficients": [-0.1], "centre": "axis"}))
    with pytest.raises(SceneError, match="camera.distortion.centre"):
        build_scene(bad)


def test_what_other_tools_cannot_hold_is_said_and_bad_tau_files_are_refused(tmp_path):
    from tiltfit.files.export import ExportError
    from tiltfit.files.mrcal_file import mrcal_text

    data = _dict(_camera(5.0, 30.0))
    assert "approximates" in mrcal_text(data), "mrcal has no tilted model: the file says the distortion is approximate"
    for centre, n in (("sensor", 5), ("lens_axis", 14)):
        fs = cv2.FileStorage(opencv_text(dict(data, distortion_centre=centre)),
                             cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
        count = fs.getNode("distortion_coefficients").mat().size
        fs.release()
        assert count == n, f"distortion about the {centre}: {n} coefficients (τ only for the lens axis), got {count}"
    for dist, field in ((np.r_[np.zeros(8), 0.01, 0, 0, 0, 0.02, 0], "thin-prism"),
                        (np.r_[np.zeros(12), 2.0, 0.0], "tau_x, tau_y")):
        path = str(tmp_path / "bad.yml")
        fs = cv2.FileStorage(path, cv2.FILE_STORAGE_WRITE)
        fs.write("image_width", 640)
        fs.write("image_height", 480)
        fs.write("camera_matrix", np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]]))
        fs.write("distortion_coefficients", dist.reshape(1, -1))
        fs.release()
        with pytest.raises(ExportError, match=f"distortion_coefficients: {field}"):
            read_opencv(path, 0.005)
