"""`tiltfit report`: the distortion list, a calibration without projection uncertainty, the board text with a
null σ, malformed uncertainty extras refused in one line, a cross-validation without a finite median."""
from __future__ import annotations

import numpy as np
import pytest


def test_report_distortion_list_keeps_positions():
    """A coefficient that is 0 inside the list is shown, not dropped (dropping it moved the later ones into its
    place: p1 = 0 made k3 read as p1); only the trailing zeros are left out."""
    from tiltfit.report.summary import _rounded_list

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


def test_report_board_text_with_null_sigma():
    """A warp board whose `sigma` is null (validate_calib accepts it: σ is optional) is written without σ, not an
    AttributeError."""
    from tiltfit.files.calib import _check_board
    from tiltfit.report.summary import _board_text

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
    from tiltfit.report.summary import _uncertainty_lines

    lines = _uncertainty_lines({"cross_validation": {"pairs": [{"groups": [1, 2], "median_px": None,
                                                                "predicted_median_px": 0.2, "verdict": "x: y"}]}})
    assert lines == ["- cross-validation, groups 1 and 2: difference median unknown against 0.2 px predicted: x"], lines
