"""Findings of the session-10 code review of the ChArUco target, the target command, detection's radial
unfit test and the report: each test failed before its fix."""
from __future__ import annotations

import math
import tracemalloc

import numpy as np
import pytest

from tiltfit.target.layout import Target, TargetError, target_from_dict

CHARUCO = {"type": "charuco", "dictionary": "DICT_5X5_100", "squares": [5, 7], "square_mm": 20.0, "marker_mm": 15.0}


@pytest.mark.parametrize("squares", [[float("inf"), 7], [5, float("nan")], [float("-inf"), 7]])
def test_charuco_squares_not_finite_is_a_one_line_target_error(squares):
    """JSON's Infinity / NaN in `squares` (Python's json reads them) is refused by name, not an OverflowError."""
    with pytest.raises(TargetError) as e:
        target_from_dict({**CHARUCO, "squares": squares}, "t.json")
    assert str(e.value).startswith("t.json: squares:") and "\n" not in str(e.value), f"message {e.value!s}"


# --- tiltfit target design: options that do not apply are refused, not ignored -------------------------------
DESIGN = ["target", "design", "--cols", "5", "--rows", "7", "--square-mm", "20"]


@pytest.mark.parametrize("extra, option", [
    (["--charuco", "DICT_5X5_100", "--inclination-deg", "20"], "--inclination-deg"),
    (["--charuco", "DICT_5X5_100", "--w-mm", "4"], "--w-mm"),
    (["--charuco", "DICT_5X5_100", "--distance-mm", "500"], "--distance-mm"),
    (["--w-mm", "4", "--distance-mm", "500", "--marker-mm", "15"], "--marker-mm"),
])
def test_target_design_refuses_options_that_do_not_apply(tmp_path, capsys, extra, option):
    """A ChArUco board has no design view (uniform squares), and a checkerboard has no markers: an option that
    would change nothing is refused with one line naming it, and nothing is written (it was silently ignored)."""
    from tiltfit.cli.main import main

    out = tmp_path / "t.json"
    rc = main(DESIGN + extra + ["-o", str(out), "-q"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err.startswith(f"tiltfit: {option}:") and "\n" not in err, f"rc {rc}, stderr {err!r}"
    assert not out.exists(), "nothing written"


def test_target_design_charuco_writes_the_board(tmp_path, capsys):
    from tiltfit.cli.main import main
    from tiltfit.target.layout import CharucoTarget, load_target

    out = tmp_path / "t.json"
    rc = main(DESIGN + ["--charuco", "DICT_4X4_50", "--marker-mm", "14", "-o", str(out), "-q"])
    assert rc == 0, capsys.readouterr().err
    t = load_target(str(out))
    assert isinstance(t, CharucoTarget) and t.squares == (5, 7) and t.marker_mm == 14.0 \
        and t.square_mm == 20.0 and t.dictionary == "DICT_4X4_50", f"the board asked for: {t.to_dict()}"


# --- detection: the radial unfit test on a large board ------------------------------------------------------
def _grid_target(nx: int, ny: int) -> Target:
    return target_from_dict({"type": "checkerboard", "x_edges": [10.0 * i for i in range(nx + 2)],
                             "y_edges": [10.0 * j for j in range(ny + 2)]})


def _barrel(target: Target, k: float, size=(4000, 3000)) -> np.ndarray:
    """The target's corners seen face-on filling the image, bent by x_d = c + (x − c)(1 + k r²) (r over the
    half diagonal)."""
    XY = target.feature_points()[:, :2]
    c = np.asarray(size, dtype=np.float64) / 2
    uv = (XY - XY.mean(0)) / np.ptp(XY, 0).max() * 0.9 * size[0] + c
    d = (uv - c) / np.hypot(*c)
    return c + (uv - c) * (1 + k * (d * d).sum(1, keepdims=True))


def test_radial_unfit_keeps_memory_linear_in_the_corners():
    """`labelling_problem`'s radial test on a board of 2,500 corners bent by barrel distortion: its corner spacing
    came from an N × N distance matrix (25 of them, 100 MB each here; a 40,000-corner board asked for 25 GB). The
    bent right board is still accepted, and the peak memory stays that of a few arrays of N points."""
    from tiltfit.detect.chessboard import labelling_problem

    t = _grid_target(50, 50)
    uv = _barrel(t, -0.25)
    tracemalloc.start()
    try:
        problem = labelling_problem(uv, t, (4000, 3000))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert problem == "", f"a bent view of the right board is accepted: {problem!r}"
    assert peak < 20e6, f"peak memory {peak / 1e6:.0f} MB for {t.n_points} corners"


def test_radial_unfit_still_refuses_a_different_board():
    """A board whose columns are unequal (another target) seen through the same lens stays refused."""
    from tiltfit.detect.chessboard import CONTRADICTS, labelling_problem

    t = _grid_target(12, 9)
    xe = np.cumsum([0.0] + [10.0 if i % 2 else 25.0 for i in range(13)])  # another board: unequal columns
    other = target_from_dict({"type": "checkerboard", "x_edges": xe.tolist(), "y_edges": list(t.y_edges)})
    uv = _barrel(other, -0.1)
    problem = labelling_problem(uv, t, (4000, 3000))
    assert problem.startswith(CONTRADICTS), f"a different board is refused: {problem!r}"
    assert labelling_problem(_barrel(t, -0.1), t, (4000, 3000)) == "", "the right board through the same lens"


# --- the report -----------------------------------------------------------------------------------------------
def test_report_distortion_list_keeps_positions():
    """A coefficient that is 0 inside the list is shown, not dropped (dropping it moved the later ones into its
    place: p1 = 0 made k3 read as p1); only the trailing zeros are left out."""
    from tiltfit.report.plots import _rounded_list

    text = _rounded_list([-0.1, 0.02, 0.0, 0.0, 0.003, 0.0, 0.0, 0.0], None)
    assert text == "[-0.1, 0.02, 0, 0, 0.003]", text


def test_report_without_projection_uncertainty_numbers(tmp_path):
    """A CALIB.json whose projection_uncertainty has no median or worst σ (null: not finite), which validate_calib
    accepts, gives a report instead of a TypeError."""
    from tiltfit.files.calib import validate_calib
    from tiltfit.report.plots import write_report

    W, H = 64, 48
    g = np.random.default_rng(0)
    corners = (g.uniform(5, 40, (6, 2))).tolist()
    calib = {"format_version": 1, "image_size_px": [W, H], "pixel_pitch_mm": 0.01, "w_mm": 5.0, "U_mm": 600.0,
             "d_mm": 2.0, "theta_F_deg": 0.0, "rms_reprojection_px": 0.1,
             "views": [{"image": "a.png", "R": np.eye(3).tolist(), "T_mm": [0, 0, 500], "corners_px": corners,
                        "residuals_px": (0.1 * g.normal(size=(6, 2))).tolist(), "rms_reprojection_px": 0.1}],
             "projection_uncertainty": {"median_px": None, "worst_px": None, "grid_x_px": [10.0, 50.0],
                                        "grid_y_px": [10.0, 40.0], "sigma_px": [[None, None], [None, None]]}}
    calib = validate_calib("calib.json", calib)
    write_report(calib, str(tmp_path))
    text = (tmp_path / "report.md").read_text()
    assert "projection uncertainty: median unknown, worst unknown" in text, f"the report says what it knows: {text}"
    assert (tmp_path / "projection_uncertainty.png").is_file(), "the (empty) map is drawn with its title"


# --- the distortion about the lens axis: closed forms the review checked -------------------------------------
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
    from tiltfit.files.export import opencv_text

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


def test_report_board_text_with_null_sigma():
    """A warp board whose `sigma` is null (validate_calib accepts it: σ is optional) is written without σ, not an
    AttributeError."""
    from tiltfit.files.calib import _check_board
    from tiltfit.report.plots import _board_text

    board = {"model": "warp", "parameters": {"sag_x_mm": 0.5, "sag_y_mm": -0.2, "scale_y_minus_1": 1e-4},
             "sigma": None}
    _check_board("calib.json", board)
    assert _board_text(board) == "warp: sag_x_mm 0.5, sag_y_mm -0.2, scale_y_minus_1 0.0001", _board_text(board)


@pytest.mark.parametrize("extra, field", [
    ({"sigma_model": "views"}, "sigma_model"),
    ({"sigma_model": {"name": "views", "design_effect": "x"}}, "sigma_model.design_effect"),
    ({"cross_validation": "yes"}, "cross_validation"),
    ({"cross_validation": {"pairs": [{}]}}, "cross_validation.pairs[0].groups"),
    ({"cross_validation": {"pairs": [{"groups": [1, 2], "median_px": "0.1", "verdict": "ok"}]}},
     "cross_validation.pairs[0].median_px"),
    ({"cross_validation": {"pairs": [{"groups": [1, 2], "median_px": 0.1, "verdict": 3}]}},
     "cross_validation.pairs[0].verdict"),
    ({"projection_uncertainty": {"sigma_px": "x", "grid_x_px": [10.0, 50.0], "grid_y_px": [10.0, 40.0]}},
     "projection_uncertainty.sigma_px"),
    ({"projection_uncertainty": {"sigma_px": [[0.1, 0.2], [0.1, 0.1]], "grid_y_px": [10.0, 40.0]}},
     "projection_uncertainty.grid_x_px"),
    ({"projection_uncertainty": {"sigma_px": [[0.1, 0.2], [0.1, 0.1]], "grid_x_px": [10.0, 50.0],
                                 "grid_y_px": [10.0]}}, "projection_uncertainty.sigma_px"),
    ({"projection_uncertainty": {"sigma_px": [[0.1], [0.2, 0.3]], "grid_x_px": [10.0, 50.0],
                                 "grid_y_px": [10.0, 40.0]}}, "projection_uncertainty.sigma_px"),
])
def test_report_refuses_malformed_uncertainty_extras_in_one_line(tmp_path, capsys, extra, field):
    """`sigma_model` and `cross_validation`, which `tiltfit report` reads, are checked by validate_calib like the
    other extras: a malformed one is one line naming the file and the field (it was a traceback)."""
    import json

    from tiltfit.cli.main import main

    g = np.random.default_rng(0)
    calib = {"image_size_px": [64, 48], "pixel_pitch_mm": 0.01, "w_mm": 5.0, "U_mm": 600.0, "d_mm": 2.0,
             "theta_F_deg": 0.0, "principal_point_px": [31.5, 23.5], "rms_reprojection_px": 0.1,
             "views": [{"image": "a.png", "R": np.eye(3).tolist(), "T_mm": [0, 0, 500],
                        "corners_px": g.uniform(5, 40, (6, 2)).tolist(),
                        "residuals_px": (0.1 * g.normal(size=(6, 2))).tolist(), "rms_reprojection_px": 0.1}]}
    path = tmp_path / "calib.json"
    path.write_text(json.dumps({**calib, **extra}))
    rc = main(["report", str(path), "-o", str(tmp_path / "rep"), "-q"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err.startswith(f"tiltfit: {path}: {field}:") and "\n" not in err, f"rc {rc}: {err!r}"
    assert not (tmp_path / "rep").exists(), "no report written"
    path.write_text(json.dumps(calib))
    assert main(["report", str(path), "-o", str(tmp_path / "rep"), "-q"]) == 0, "the file without the extra"


def test_report_of_a_cross_validation_without_a_finite_median(tmp_path):
    """A pair whose difference had no finite pixel (median null, as `calib_dict` writes NaN) reads 'unknown'."""
    from tiltfit.report.plots import _uncertainty_lines

    lines = _uncertainty_lines({"cross_validation": {"pairs": [{"groups": [1, 2], "median_px": None,
                                                                "predicted_median_px": 0.2, "verdict": "x: y"}]}})
    assert lines == ["- cross-validation, groups 1 and 2: difference median unknown against 0.2 px predicted: x"], lines
