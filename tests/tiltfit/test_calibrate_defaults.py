"""`tiltfit calibrate` with only the required flags on the shipped GoPro photos (data/real/gopro_wide) gives what
OpenCV's calibrateCamera gives on the same corners; the blur model, which does not describe this lens, is
refused in one warning line; what it writes is in range and exported.

The corners and blur widths are tiltfit's own detections, cached in data/real/gopro_wide/detections_tiltfit.json
(tests/real_detections.py); one photo is detected again here to check the cache is current.
"""
import json
import os
import sys

import cv2
import numpy as np
import pytest

from tiltfit.cli import main as cli

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import fuzz_harness  # noqa: E402  (tests/fuzz_harness.py: run a command's main in-process)

DATA = os.path.join(os.path.dirname(__file__), "..", "..", "data", "real", "gopro_wide")
TARGET = os.path.join(DATA, "target.json")
PITCH = "0.005"

pytestmark = pytest.mark.slow


def cached_detections(folder):
    with open(os.path.join(folder, "detections_tiltfit.json"), encoding="utf-8") as f:
        return json.load(f)


def write_dets(cache, folder):
    paths = []
    for name in sorted(cache):
        if "no_board" not in cache[name]:
            p = folder / (os.path.splitext(name)[0] + ".json")
            p.write_text(json.dumps(cache[name]))
            paths.append(str(p))
    return paths


def run(args):
    return fuzz_harness.run_command(cli.main, args)  # `tiltfit ARGS` in this process: (exit status, stderr)


def opencv_on(paths):
    """cv2.calibrateCamera with its default flags (free principal point, fx and fy, k1 k2 p1 p2 k3) on the very
    corners of the DET files."""
    obj, img, size = [], [], None
    with open(TARGET, encoding="utf-8") as f:
        t = json.load(f)
    xs, ys = t["x_edges"][1:-1], t["y_edges"][1:-1]
    points = np.array([[x, y, 0.0] for y in ys for x in xs], dtype=np.float32)
    for p in paths:
        with open(p, encoding="utf-8") as f:
            det = json.load(f)
        size = tuple(det["image_size_px"])
        found = [i for i, c in enumerate(det["corners_px"]) if c is not None]
        obj.append(points[found])
        img.append(np.array([det["corners_px"][i] for i in found], dtype=np.float32))
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    rms, K, dist, _, _ = cv2.calibrateCamera(obj, img, size, None, None, criteria=crit)
    return rms, K, dist.ravel()


@pytest.fixture(scope="module")
def gopro(tmp_path_factory):
    folder = tmp_path_factory.mktemp("gopro")
    paths = write_dets(cached_detections(DATA), folder)
    out = folder / "calib.json"
    rc, err = run(["calibrate", *paths, "--target", TARGET, "--pixel-pitch-mm", PITCH, "-o", out])
    assert rc == 0, f"calibrate with the defaults failed: {err}"
    return json.loads(out.read_text()), err, out, paths


def test_cache_is_what_the_detector_finds(tmp_path):
    name = "GOPR0070.jpg"
    out = tmp_path / "det.json"
    rc, err = run(["detect", os.path.join(DATA, name), "--target", TARGET, "-o", out, "-q"])
    assert rc == 0, err
    fresh, cached = json.loads(out.read_text()), cached_detections(DATA)[name]
    diff = np.abs(np.array(fresh["corners_px"], dtype=float) - np.array(cached["corners_px"], dtype=float))
    assert np.nanmax(diff) < 1e-6, f"cached corners differ from a fresh detection by {np.nanmax(diff)} px: rerun " \
                                   f"tests/real_detections.py"
    widths = [np.array([np.nan if b is None else b for b in d["blur_px"]], dtype=float) for d in (fresh, cached)]
    assert np.array_equal(np.isnan(widths[0]), np.isnan(widths[1])), "cached blur widths measured elsewhere"
    wdiff = np.nanmax(np.abs(widths[0] - widths[1]))
    assert wdiff < 1e-6, f"cached blur widths differ from a fresh detection by {wdiff} px: rerun tests/real_detections.py"


def test_defaults_match_opencv_on_the_same_corners(gopro):
    data, _, _, paths = gopro
    rms_cv, K, _ = opencv_on(paths)
    f_px = data["w_mm"] / data["pixel_pitch_mm"]
    for k, fk in (("fx", K[0, 0]), ("fy", K[1, 1])):
        assert abs(f_px / fk - 1) < 0.01, f"focal {f_px:.2f} px vs OpenCV's {k} {fk:.2f} px"
    cx, cy = data["principal_point_px"]
    assert abs(cx - K[0, 2]) < 5 and abs(cy - K[1, 2]) < 5, \
        f"principal point ({cx:.1f}, {cy:.1f}) vs OpenCV's ({K[0, 2]:.1f}, {K[1, 2]:.1f})"
    rms = data["rms_reprojection_px"]
    assert rms <= 1.05 * rms_cv, f"RMS per corner {rms:.4f} px vs OpenCV's {rms_cv:.4f} px"
    board = {e["model"]: e for e in data["board_selection"]}
    if data["board"]["model"] == "flat":  # OpenCV's board: as well as OpenCV, and not better than it can be
        assert 0.9 * rms_cv < rms, f"RMS per corner {rms:.4f} px vs OpenCV's {rms_cv:.4f} px"
    else:  # the board's shape fitted (tiltfit.target.shape): an RMS below OpenCV's, paid for by held-out views
        chosen = board[data["board"]["model"]]
        assert chosen["held_out_rms_px"] < 0.99 * board["flat"]["held_out_rms_px"], f"board selection {board}"
        assert chosen["rms_px"] == pytest.approx(rms), "the RMS written is the chosen board's"
    views = np.array([v["rms_reprojection_px"] for v in data["views"]])
    n = np.array([v["n_points"] for v in data["views"]])
    assert abs(np.sqrt((views ** 2 * n).sum() / n.sum()) - rms) < 1e-9, "per-view RMS per corner, like the total"


def test_principal_point_is_fitted_where_justified(gopro):
    data, err, _, _ = gopro
    pp = data["model_selection"]["principal_point"]
    assert pp["justified"] is True and pp["fitted"] is True and data["principal_point_fitted"] is True, \
        f"the test's answer is acted on: {pp}"
    assert "freeing principal_point is justified" in err, "the verdict is said"


def test_auto_distortion_says_what_and_why(gopro):
    data, err, _, _ = gopro
    sel = {e["model"]: e for e in data["distortion_selection"]}
    chosen = [m for m, e in sel.items() if e["chosen"]]
    assert chosen == [data["distortion_model"]] and "distortion auto: " + chosen[0] in err, \
        f"one model chosen and said: {chosen}"
    best = min(e["held_out_rms_px"] for e in sel.values() if "held_out_rms_px" in e)
    assert sel[chosen[0]]["held_out_rms_px"] <= 1.05 * best, "the chosen model predicts held-out views best"
    assert "folds back" in sel["rational"].get("refused", ""), \
        f"the rational fit folds before its outermost corner: {sel['rational']}"
    board = next(e for e in data["board_selection"] if e["chosen"])  # chosen after the distortion (tiltfit.target.shape)
    if board["model"] == "flat":
        assert data["held_out"]["rms_px"] == pytest.approx(sel[chosen[0]]["held_out_rms_px"]), "held-out written"
    else:  # the distortion chosen again with the fitted board: its held-out error, no worse than the board test's
        assert data["held_out"]["rms_px"] <= 1.01 * board["held_out_rms_px"], \
            f"held-out written {data['held_out']['rms_px']:.4f} px, board selection {data['board_selection']}"
    ms = data["model_selection"]["distortion"]
    assert ms["chosen"] == chosen[0] and "held-out" in ms["criterion"] and chosen[0] in ms["why"], ms


def test_blur_model_is_refused_in_one_warning_line(gopro):
    data, err, _, _ = gopro
    lines = [x for x in err.splitlines() if x.startswith("tiltfit: warning:")]
    assert len(lines) == 1 and "thin-lens blur model does not describe this lens" in lines[0], err
    assert "theta_F" not in data["model_selection"], "the tilt is not tested on a lens the blur model misfits"
    assert data["U_mm"] is None and data["d_mm"] is None and {"U_mm", "d_mm"} <= set(data["undetermined"])


def test_written_values_are_physical_and_exported(gopro, tmp_path):
    data, _, path, _ = gopro
    assert data["w_mm"] > 0 and all(data[k] is None or data[k] > 0 for k in ("U_mm", "f_mm")), "w, U, f > 0"
    assert data["d_mm"] is None or data["d_mm"] >= 0, "d ≥ 0"
    rc, err = run(["export", path, "--to", "opencv", "-o", tmp_path / "cam.yml", "-q"])
    assert rc == 0, f"export refused what calibrate wrote: {err}"


def test_held_out_with_a_free_principal_point(gopro):
    """On main, GoPro with --free-principal-point wrote no held-out error (a fold's fit 'did not converge'); the
    defaults free it here (justified), and the held-out error per corner is written. The fold itself is
    tests/tiltfit/test_distortion_auto_real.py's stopping-rule test."""
    data, _, _, _ = gopro
    assert data["principal_point_fitted"] is True, "principal point free"
    ho = data["held_out"]
    assert ho is not None and ho["folds"] == 5 and data["rms_reprojection_px"] < ho["rms_px"] < 2.5, \
        f"held-out error per corner: {ho}"
