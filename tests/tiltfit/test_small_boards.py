"""The fitted board on small boards (issue 33 §5): the export carries the fitted points, the automatic choice refuses
a board model the views cannot carry, and the board's uncertainty stays in the lens's σ."""
from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from tiltfit import cli
from tiltfit.model import board_points_mm

W, H = 1280, 1024
K_TRUE = np.array([[2000.0, 0, 650.0], [0, 2000.0, 505.0], [0, 0, 1]])
D_TRUE = np.array([-0.1, 0.05, 0, 0, 0])


def bent_board(cols=9, rows=7, pitch=15.0, seed=0):
    """(nominal, true) points: a board bowed by 0.5 mm along X with each point moved by ~0.05 mm in its plane (a
    print's errors): what no flat board explains."""
    rng = np.random.default_rng(seed)
    nominal = board_points_mm(cols, rows, pitch, centred=False).numpy()
    true = nominal.copy()
    u = (true[:, 0] - true[:, 0].mean()) / np.ptp(true[:, 0]) * 2
    true[:, 2] = 0.5 * (1 - u * u)
    true[:, :2] += rng.normal(0, 0.05, (len(true), 2))
    return nominal, true


def project_views(points_mm, n_views=8, seed=0, noise_px=0.05):
    """Corners of `points_mm` projected by OpenCV (K_TRUE, D_TRUE), random poses, Gaussian noise: (V, N, 2)."""
    rng = np.random.default_rng(seed)
    P = np.asarray(points_mm, np.float64)
    centre = P.mean(0)
    out = []
    for _ in range(n_views):
        rv = rng.uniform(-1, 1, 3) * np.radians([30, 30, 10])
        R = cv2.Rodrigues(rv)[0]
        t = np.array([rng.uniform(-30, 30), rng.uniform(-25, 25), rng.uniform(500, 700)]) - R @ centre
        uv = cv2.projectPoints(P, rv, t, K_TRUE, D_TRUE)[0][:, 0]
        out.append(uv + rng.normal(0, noise_px, uv.shape))
    return np.stack(out)


def write_inputs(tmp_path, corners, cols, rows, pitch):
    """DET.json files of the views and the target file (`cols`×`rows` inner corners of `pitch` mm squares)."""
    target = tmp_path / "target.json"
    target.write_text(json.dumps({"type": "checkerboard", "units": "mm",
                                  "x_edges": [pitch * i for i in range(-1, cols + 1)],
                                  "y_edges": [pitch * i for i in range(-1, rows + 1)], "margin": 5}))
    dets = []
    for v, c in enumerate(corners):
        p = tmp_path / f"v{v:02d}.json"
        p.write_text(json.dumps({"image_size_px": [W, H], "corners_px": c.tolist(), "blur_px": [None] * len(c),
                                 "grid_found": True}))
        dets.append(str(p))
    return str(target), dets


@pytest.mark.parametrize("board", ["free", "warp"])
def test_export_carries_the_fitted_board_and_reproduces_the_residuals(tmp_path, board):
    """`tiltfit export --to opencv` of a calibration with a fitted board writes the fitted points as object_points,
    and cv2.projectPoints of them with the exported camera and poses gives CALIB.json's residuals per view (the
    target file's flat points do not)."""
    cols, rows, pitch = 9, 7, 15.0
    nominal, true = bent_board(cols, rows, pitch)
    corners = project_views(true, seed=3)
    target, dets = write_inputs(tmp_path, corners, cols, rows, pitch)
    calib_path, yml = tmp_path / "calib.json", tmp_path / "camera.yml"
    assert cli.main(["calibrate", *dets, "--target", target, "--pixel-pitch-mm", "0.005", "--board", board,
                     "--distortion", "k1k2", "--free-principal-point", "--held-out", "0", "-q",
                     "-o", str(calib_path)]) == 0
    calib = json.loads(calib_path.read_text())
    assert calib["board"]["model"] == board, calib["board"]
    assert cli.main(["export", str(calib_path), "--to", "opencv", "-o", str(yml), "-q"]) == 0
    fs = cv2.FileStorage(str(yml), cv2.FILE_STORAGE_READ)
    K, D = fs.getNode("camera_matrix").mat(), fs.getNode("distortion_coefficients").mat().ravel()
    rv, tv, P = (fs.getNode(k).mat() for k in ("rvecs", "tvecs", "object_points"))
    note = fs.getNode("tiltfit_note").string()
    fs.release()
    assert P is not None and P.shape == nominal.shape, f"object_points: {None if P is None else P.shape}"
    assert "object_points" in note, f"the note does not say where the fitted board is: {note}"

    def per_view_rms(points):
        out = []
        for v, c in enumerate(corners):
            uv = cv2.projectPoints(points, rv[v], tv[v], K, D)[0][:, 0]
            out.append(math.sqrt(((uv - c) ** 2).sum(1).mean()))
        return np.array(out)

    ours = np.array([v["rms_reprojection_px"] for v in calib["views"]])
    exported = per_view_rms(P)
    assert np.allclose(exported, ours, rtol=1e-4, atol=1e-5), f"exported {exported} vs CALIB.json {ours}"
    flat = per_view_rms(nominal)
    assert np.median(flat) > 2 * np.median(ours), \
        f"the flat points reproduce the residuals too ({np.median(flat):.3f} vs {np.median(ours):.3f} px): no test"


def test_export_of_a_flat_board_has_no_object_points(tmp_path):
    cols, rows, pitch = 9, 7, 15.0
    nominal, _ = bent_board(cols, rows, pitch)
    target, dets = write_inputs(tmp_path, project_views(nominal, n_views=5, seed=5), cols, rows, pitch)
    calib_path, yml = tmp_path / "calib.json", tmp_path / "camera.yml"
    assert cli.main(["calibrate", *dets, "--target", target, "--pixel-pitch-mm", "0.005", "--board", "flat",
                     "--distortion", "k1", "--held-out", "0", "-q", "-o", str(calib_path)]) == 0
    assert cli.main(["export", str(calib_path), "--to", "opencv", "-o", str(yml), "-q"]) == 0
    fs = cv2.FileStorage(str(yml), cv2.FILE_STORAGE_READ)
    assert fs.getNode("object_points").empty(), "a flat board's points are the target file's: nothing to export"
    fs.release()
