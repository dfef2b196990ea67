"""The distortion about the lens axis in closed form: OpenCV's tilted model round trip and axis, the
lens-axis model at zero tilt equal to the sensor model, and export of a lens-axis calibration without θL."""
from __future__ import annotations

import math

import numpy as np


def test_opencv_tilt_round_trip_and_axis():
    """R(τx, τy) of `opencv_tilt(θL, φ)` has the lens axis (sin θL sin φ, −sin θL cos φ, cos θL) as its third column,
    and `lens_tilt_from_opencv` gives (θL, φ) back with φ in (−90°, 90°] (the opposite tilt about the same axis
    otherwise), over both signs of both angles."""
    from renderer.cameras.lens import lens_tilt_from_opencv, opencv_tilt, tilt_rotation

    for th in np.radians([-12.0, -3.0, 4.0, 11.0]):
        for ph in np.radians([-89.0, -40.0, 0.0, 30.0, 90.0]):
            R = tilt_rotation(*opencv_tilt(th, ph))
            n = np.array([math.sin(th) * math.sin(ph), -math.sin(th) * math.cos(ph), math.cos(th)])
            assert np.allclose(R[:, 2], n, atol=1e-15) and np.allclose(R @ R.T, np.eye(3), atol=1e-15), \
                f"θL {math.degrees(th)}, φ {math.degrees(ph)}: R's third column is the lens axis, R a rotation"
            th2, ph2 = lens_tilt_from_opencv(*opencv_tilt(th, ph))
            assert -math.pi / 2 < ph2 <= math.pi / 2 + 1e-12, f"φ {math.degrees(ph2)}° outside (−90°, 90°]"
            same = abs(th2 - th) < 1e-12 and abs(ph2 - ph) < 1e-12
            flipped = abs(th2 + th) < 1e-12 and abs(abs(ph2 - ph) - math.pi) < 1e-12
            assert same or flipped, f"({math.degrees(th)}, {math.degrees(ph)})° came back as " \
                f"({math.degrees(th2)}, {math.degrees(ph2)})°"


def test_lens_axis_distortion_at_zero_tilt_is_the_sensor_model():
    """θF = 0 (so θL = 0) with the tilt axis turned: the lens-axis camera (its frame computed, no shortcut) projects
    as the distortion about the principal point, tangential terms included; a small tilt moves the points."""
    import torch

    from renderer.cameras import LensCamera

    def camera(centre, theta_F):
        return LensCamera(2, (1368, 912), 0.026, 55.0, 620.0, 18.0, theta_F, T_mm=[[10.0, -5.0, 600.0]] * 2,
                          principal_point_px=(690.0, 449.0), distortion=[-0.12, 0.02, 4e-4, -3e-4, 0.01], phi=0.9,
                          distortion_centre=centre)

    X = torch.tensor([[x, y, 0.0] for x in (-150.0, 0.0, 150.0) for y in (-100.0, 0.0, 100.0)], dtype=torch.float64)
    with torch.no_grad():
        axis, sensor = camera("lens_axis", 0.0), camera("sensor", 0.0)
        assert axis.distortion_frame is not None, "the lens-axis camera computes its frame"
        diff = float((axis(X, with_blur=False)[0] - sensor(X, with_blur=False)[0]).abs().max())
        moved = float((camera("lens_axis", 0.3)(X, with_blur=False)[0]
                       - camera("sensor", 0.3)(X, with_blur=False)[0]).abs().max())
    assert diff < 1e-9, f"θL = 0: the two centres differ by {diff:.2g} px"
    assert moved > 0.05, f"θF 0.3 rad: the lens axis should move the distorted points ({moved:.2g} px)"


def test_export_of_a_lens_axis_calibration_without_theta_L_deg():
    """A hand-made CALIB.json (theta_L_deg is not among the keys a start needs) with the distortion about the lens
    axis, θF and U: `camera_from_calib` tilts the distortion's frame by the θL of θF, so the export must too
    (it wrote OpenCV's plain model, and a note that the projection was exact)."""
    import cv2
    import torch

    from renderer import Lens
    from renderer.cameras import EOS_6D, LensCamera
    from tiltfit.files.calib import camera_from_calib, validate_calib
    from tiltfit.files.opencv_file import opencv_text

    sensor = EOS_6D.binned(4)
    lens = Lens.from_tilt(55.39, 45.0, math.radians(4.0), 16.0, sensor=sensor, phi=math.radians(25.0),
                          principal_point_px=(690.3, 450.8), distortion=(-0.12, 0.02), distortion_centre="lens_axis")
    cam = LensCamera.from_lens(lens, 1, T_mm=[[10.0, -20.0, 600.0]])
    s = cam.summary()
    data = {"pixel_pitch_mm": cam.pixel_pitch_mm, "image_size_px": list(cam.image_size_px),
            "principal_point_px": s["principal_point_px"], "w_mm": s["w_mm"], "U_mm": s["U_mm"], "d_mm": s["d_mm"],
            "theta_F_deg": s["theta_F_deg"], "tilt_axis_deg": s["tilt_axis_deg"], "distortion_centre": "lens_axis",
            "distortion": {"model": "brown_conrady", "coefficients": s["distortion"]},
            "views": [{"R": np.eye(3).tolist(), "T_mm": [10.0, -20.0, 600.0]}]}
    data = validate_calib("calib.json", data)
    X = np.array([[x, y, 0.0] for x in (-150.0, 0.0, 150.0) for y in (-100.0, 0.0, 100.0)])
    with torch.no_grad():
        ours = camera_from_calib(data)(torch.as_tensor(X), with_blur=False)[0][0].numpy()
    fs = cv2.FileStorage(opencv_text(data), cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    K, dist = fs.getNode("camera_matrix").mat(), fs.getNode("distortion_coefficients").mat()
    rv, tv, note = fs.getNode("rvecs").mat(), fs.getNode("tvecs").mat(), fs.getNode("tiltfit_note").string()
    fs.release()
    theirs = cv2.projectPoints(X, rv[0], tv[0], K, dist)[0].reshape(-1, 2)
    worst = float(np.abs(theirs - ours).max())
    assert worst < 0.01, f"cv2.projectPoints of the export differs from the file's camera by {worst:.2g} px"
    assert "tau" in note and "exact" in note, f"the note names OpenCV's tilted model: {note}"
