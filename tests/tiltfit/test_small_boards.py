"""The fitted board on small boards (issue 33 §5): the export carries the fitted points, the automatic choice refuses
a board model the views cannot carry, and the board's uncertainty stays in the lens's σ."""
from __future__ import annotations

import json
import math
from dataclasses import replace

import cv2
import numpy as np
import pytest

from tiltfit.cli import main as cli
from tiltfit.calibrate.model import board_points_mm

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


def blurred_capture(points_mm, nominal_mm, seed=0, n_views=8):
    """Corners and blur widths of `points_mm` seen by a pinhole with k1 and a thin-lens blur circle, written here
    (not tiltfit's camera; as benchmarks/calibration/bench_sigma_honesty.py's capture), with `nominal_mm` as the target's points."""
    import torch

    from tiltfit.calibrate.model import PAPER_LENS, PAPER_SENSOR, Observations, axis_angle_to_matrix, random_poses

    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    w, U, d = PAPER_LENS["w_mm"], PAPER_LENS["U_mm"], PAPER_LENS["d_mm"]
    pitch, size = PAPER_SENSOR["pixel_pitch_mm"], PAPER_SENSOR["image_size_px"]
    rvec, T = random_poses(n_views, 3)
    R, T = axis_angle_to_matrix(rvec).numpy(), T.numpy()
    P = np.asarray(points_mm) - np.asarray(nominal_mm).mean(0)
    pc = np.einsum("vij,nj->vni", R, P) + T[:, None, :]
    xy = pc[..., :2] / pc[..., 2:3]
    xy = xy * (1 - 0.05 * (xy ** 2).sum(-1, keepdims=True))
    cx, cy = (size[0] - 1) / 2 + 12.0, (size[1] - 1) / 2 - 8.0
    uv = np.stack([cx + w / pitch * xy[..., 0], cy + w / pitch * xy[..., 1]], -1) + rng.normal(0, 0.05, xy.shape)
    w_z = 1.0 / (1.0 / (w * U / (w + U)) - 1.0 / pc[..., 2])
    blur = d * np.abs(w - w_z) / w_z / pitch
    blur = blur + rng.normal(0, 0.03 * np.median(blur), blur.shape)
    nominal = np.asarray(nominal_mm) - np.asarray(nominal_mm).mean(0)
    return Observations(torch.tensor(nominal), torch.tensor(uv), torch.tensor(blur), size, pitch)


def test_the_fitted_board_stays_in_the_sigma_of_the_blur_fit():
    """With blur widths the final fit is the corner-and-blur fit: it refits the board beside the lens, so the σ of
    the focal length and principal point include what the board's shape absorbs (the same fit with the board's
    points held as known gives smaller σ), and the board it reports is the one its poses and RMS were fitted with."""
    import torch

    from tiltfit.target.shape import Board, with_points
    from tiltfit.calibrate.flow import calibrate
    from tiltfit.calibrate.fit import FitOptions, without_blur

    nominal = board_points_mm(8, 6, 25.0, centred=False).numpy()
    true = Board(nominal, "warp", torch.tensor([0.8, -0.4, 0.002])).points().numpy()
    obs = blurred_capture(true, nominal, seed=2)
    opts = FitOptions(distortion="k1", free_principal_point=True, model_selection=False, board="free")
    res = calibrate(obs, "unified", options=opts)
    assert "U_mm" not in res.undetermined and res.rss["n_blur"] > 0, f"not the blur fit: {res.notes}"
    assert res.board is not None and res.board.model == "free", res.board
    held = calibrate(with_points(obs, res.board.points()), "unified",  # (a bent board starts no homography)
                     options=replace(opts, board="flat", nominal_focal_mm=res.values["w_mm"]))

    def lens_sigma(r):
        return np.array([r.sigma["w_mm"], *r.sigma["principal_point_px"]])

    ratio = lens_sigma(res) / lens_sigma(held)
    assert ratio.max() > 1.5, f"σ with the board refitted / σ with its points held: {ratio} (the board profiled out)"
    assert (ratio > 0.95).all(), f"σ ratio {ratio}"
    # ... and no more than the corners alone give with the board fitted (the widths only add information).
    corners_only = calibrate(without_blur(obs), "unified", options=opts)
    upper = lens_sigma(res) / lens_sigma(corners_only)
    assert (upper < 1.1).all() and (upper > 0.3).all(), f"σ of the blur fit / σ of the corners-only fit: {upper}"
    # The reported board is the fitted one: its points reproduce the views' RMS.
    with torch.no_grad():
        from tiltfit.calibrate.model import residuals

        rc, _ = residuals(res.camera, with_points(obs, res.board.points())).rms_per_view()
    assert np.allclose(rc.numpy(), [v["rms_reprojection_px"] for v in res.views], rtol=1e-6), "board and views differ"


def test_held_out_gain_is_a_paired_t_over_the_views():
    """A gain every view shares is many standard errors; the same mean gain carried by one view of six is not."""
    import torch

    from tiltfit.select.board import held_out_gain
    from tiltfit.calibrate.model import Observations

    obs = Observations(board_points_mm(4, 3, 10.0), torch.zeros(6, 12, 2), torch.full((6, 12), math.nan), (64, 48), 0.01)
    simple = {"per_view_px": [0.30] * 6}
    even = held_out_gain(simple, {"per_view_px": [0.29, 0.291, 0.289, 0.29, 0.292, 0.288]}, obs)
    assert even > 10, f"a gain shared by every view: {even:.3g} standard errors"
    lone = math.sqrt(0.30 ** 2 - 6 * (0.30 ** 2 - 0.29 ** 2))  # the same total gain, all in one view
    one = held_out_gain(simple, {"per_view_px": [lone, 0.3, 0.3, 0.3, 0.3, 0.3]}, obs)
    assert 0.5 < one < 2.0, f"a gain carried by one view of six: {one:.3g} standard errors (a t of 1 expected)"
    assert held_out_gain(simple, {"per_view_px": [0.3] * 5}, obs) is None, "views missing: no comparison"


def test_small_board_keeps_the_board_the_views_carry():
    """sony_small (13 real views of a 4×6-corner board, cached detections): `free` (65 parameters) predicts held-out
    views better by 12 %, but by less than 2 standard errors over the views; it was chosen and moved the principal
    point 30 px from OpenCV's (and BoofCV's reference, 308.5 / 246.8). The defaults keep a board the views carry
    and a principal point near OpenCV's on the same corners, with a σ that holds what the free board would have
    moved (its weight in `sigma_model.model_choice`) and covers the reference."""
    import os
    import sys

    root = os.path.join(os.path.dirname(__file__), "..", "..")
    sys.path.insert(0, os.path.join(root, "tests"))
    from real_detections import observations

    from tiltfit.calibrate.flow import calibrate
    from tiltfit.calibrate.fit import FitOptions
    from tiltfit.detect.opencv import opencv_calibrate

    obs, _ = observations(os.path.join(root, "benchmarks", "small_sets", "sony_small"), 0.0096)
    res = calibrate(obs, "unified", options=FitOptions(distortion="auto", board="auto"))
    free = next(e for e in res.board_selection if e["model"] == "free")
    assert res.board is None or res.board.model != "free", f"free chosen: {res.board_selection}"
    assert "not_chosen" in free, f"the free board's entry does not say why it was not chosen: {free}"
    _, K, _ = opencv_calibrate(obs)
    pp, s = np.array(res.values["principal_point_px"]), np.array(res.sigma["principal_point_px"])
    off = pp - K[:2, 2]
    assert np.all(np.abs(off) < 12), f"principal point {pp} vs OpenCV's {K[:2, 2]} (σ {s})"
    assert np.all(s > 0.5) and np.all(s < 20), f"σ of the principal point {s} px on 13 views of 24 corners"
    assert np.all(np.abs(pp - [308.5, 246.8]) < 2 * s), f"principal point {pp} ± {s} against the reference's"
    choice = res.sigma_model.get("model_choice")
    assert choice and choice["weights"]["board"]["free"] > 0.01, f"the free board's weight in σ: {choice}"
