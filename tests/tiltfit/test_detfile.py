"""DET and CALIB files: they describe themselves, read back equal, and reading refuses views no fit should use."""
from __future__ import annotations

import json
import os

import numpy as np
import pytest

from tiltfit.files.calib import read_calib, write_calib
from tiltfit.detect.detection import write_det_json
from tiltfit.cli.main import main
from tiltfit.files.det import DET_FORMAT_VERSION, DetFileError, check_view, check_views, describe_detection, read_det
from renderer import Lens, Sensor
from tiltfit.experiments.synth import look_at_pose, observe
from tiltfit.target.layout import target_from_dict

TARGET = target_from_dict({"type": "checkerboard", "x_edges": [0, 25, 50, 75, 100, 125], "y_edges": [0, 30, 55, 75,
                                                                                                       90]})
CAMERA = Lens(35, 700, 6, sensor=Sensor(640, 480, 0.02))


def _view(position=(60, 45, -700)):
    R, T = look_at_pose(TARGET, position)
    o = observe(TARGET, CAMERA, R, T)
    return o.corners_px, o.blur_px


def _det_dict(corners, blur) -> dict:
    return {"image_size_px": [640, 480], "grid_found": True,
            "corners_px": [[float(x), float(y)] for x, y in corners], "blur_px": [float(b) for b in blur]}


def test_det_file_describes_itself_and_reads_back_equal(tmp_path):
    det = describe_detection(_det_dict(*_view()), "photo.png", "T.json", TARGET)
    path = str(tmp_path / "DET.json")
    write_det_json(det, path)
    back = read_det(path, TARGET.n_points)
    assert back == det, "DET.json reads back equal"
    assert back["format_version"] == DET_FORMAT_VERSION and back["image"] == "photo.png", back
    assert back["target"] == {"file": "T.json", "n_points": 12, "x_edges_count": 6, "y_edges_count": 5}, back
    assert "diameter of the blur disc" in back["units"]["blur_px"] and "pixels" in back["units"]["corners_px"]
    assert back["created"].endswith("+00:00") and back["software"].startswith("tiltfit "), back


def test_calib_file_reads_back_equal(tmp_path):
    data = {"pixel_pitch_mm": 0.02, "image_size_px": [640, 480], "principal_point_px": [319.5, 239.5],
            "w_mm": 35.0, "U_mm": 700.0, "d_mm": 6.0, "f_mm": 33.3, "theta_F_deg": 1.5, "theta_L_deg": 0.07,
            "theta_L_paper_deg": 0.07, "views": [{"image": "a.png", "R": np.eye(3).tolist(), "T_mm": [1.0, 2.0, 700.0],
                                                  "rms_reprojection_px": 0.1, "rms_blur_px": None, "n_points": 12}],
            "sigma": {"w_mm": 0.01, "U_mm": 1.0, "d_mm": 0.02, "theta_F_deg": 0.1, "theta_L_deg": 0.01},
            "runtime_s": 1.25}
    path = str(tmp_path / "CALIB.json")
    write_calib(path, data)
    assert read_calib(path) == data, "CALIB.json reads back equal"


@pytest.mark.parametrize("field,value,expected", [
    ("blur_px", -0.5, "blur_px[3]: expected a blur-disc diameter in [0, 800] pixels"),
    ("blur_px", float("nan"), "blur_px[3]: expected a finite number or null, got nan"),
    ("corners_px", [10**400, 5], "corners_px[3]: expected [x, y] (finite numbers) or null"),
    ("corners_px", [900.0, 5.0], "corners_px[3]: [900.0, 5.0] lies outside the 640x480 image"),
])
def test_read_det_refuses_bad_entries_naming_the_field(tmp_path, field, value, expected):
    det = _det_dict(*_view())
    det[field][3] = value
    path = tmp_path / "DET.json"
    path.write_text(json.dumps(det))
    with pytest.raises(DetFileError) as e:
        read_det(str(path), TARGET.n_points)
    assert str(e.value).startswith(f"{path}: ") and expected in str(e.value), str(e.value)


def test_read_det_refuses_a_newer_format(tmp_path):
    path = tmp_path / "DET.json"
    path.write_text(json.dumps({**_det_dict(*_view()), "format_version": DET_FORMAT_VERSION + 1}))
    with pytest.raises(DetFileError, match="format_version: expected 1 to"):
        read_det(str(path), TARGET.n_points)


def test_every_real_view_passes_and_its_mirror_image_is_refused():
    points = TARGET.feature_points()
    for position in ((60, 45, -700), (-200, 0, -650), (300, 150, -600), (60, -250, -600)):
        corners, _ = _view(position)
        check_view("v.json", corners, points)  # a physical view: accepted
        mirrored = corners.copy()
        mirrored[:, 0] = 639 - mirrored[:, 0]
        with pytest.raises(DetFileError, match="v.json: corners_px: the board appears mirrored"):
            check_view("v.json", mirrored, points)


def test_a_mirror_image_labelled_as_a_turned_board_is_flagged_when_rows_are_non_uniform():
    """A detector labels a mirrored photo with an orientation-preserving placement (rows read backwards); with
    non-uniform rows that placement leaves a large homography residual which reading the rows back removes."""
    from tiltfit.files.det import mirrored

    nonuniform = target_from_dict({"type": "checkerboard", "x_edges": [0, 25, 50, 75, 100, 125, 150],
                                   "y_edges": [0, 18, 38, 60, 84, 110]})
    uniform = target_from_dict({"type": "checkerboard", "x_edges": [0, 25, 50, 75, 100, 125, 150],
                                "y_edges": [0, 25, 50, 75, 100, 125]})
    for t, flagged in ((nonuniform, True), (uniform, False)):
        R, T = look_at_pose(t, (75, 55, -700))
        corners = observe(t, CAMERA, R, T).corners_px
        ny, nx = t.grid_shape
        assert not mirrored(corners, t.feature_points()), "the true view is not mirrored"
        image_mirror = corners.copy()
        image_mirror[:, 0] = 639 - image_mirror[:, 0]
        rows_backwards = image_mirror.reshape(ny, nx, 2)[::-1].reshape(-1, 2)  # orientation-preserving labels
        assert mirrored(rows_backwards, t.feature_points()) is flagged, f"non-uniform rows: {flagged}"


WIDE = target_from_dict({"type": "checkerboard", "x_edges": [0, 25, 50, 75, 100, 125, 150, 175, 200],
                         "y_edges": [0, 30, 55, 75, 90]})


def test_collinear_and_too_few_corners_are_refused():
    # a row of 7 corners (more than MIN_CORNERS, so the line check, not the count, refuses it)
    R, T = look_at_pose(WIDE, (100, 45, -800))
    wide = observe(WIDE, CAMERA, R, T).corners_px
    one_row = wide.copy()
    one_row[7:] = np.nan  # the first row only: 7 corners on one target line
    with pytest.raises(DetFileError, match="v.json: corners_px: the 7 found corners lie on one line"):
        check_view("v.json", one_row, WIDE.feature_points())
    check_view("v.json", wide, WIDE.feature_points())  # the whole view: accepted
    points = TARGET.feature_points()
    corners, _ = _view()
    four = corners.copy()
    four[4:] = np.nan  # 4 corners: too few (MIN_CORNERS 6)
    with pytest.raises(DetFileError, match="4 corners found; a view needs at least 6"):
        check_view("v.json", four, points)
    line = np.stack([np.linspace(10, 300, len(corners)), np.linspace(20, 200, len(corners))], -1)
    with pytest.raises(DetFileError, match="lie on one line in the image"):
        check_view("v.json", line, points)
    few = corners.copy()
    few[3:] = np.nan
    with pytest.raises(DetFileError, match="3 corners found; a view needs at least 6"):
        check_view("v.json", few, points)


def _calibrate_dets(tmp_path, views, capsys):
    tfile = tmp_path / "T.json"
    TARGET.save(str(tfile))
    paths = []
    for i, (corners, blur) in enumerate(views):
        path = tmp_path / f"v{i}.json"
        det = _det_dict(corners, blur)
        det["corners_px"] = [c if np.isfinite(c).all() else None for c in det["corners_px"]]  # not found: null
        path.write_text(json.dumps(det))
        paths.append(str(path))
    out = tmp_path / "CALIB.json"
    rc = main(["calibrate", *paths, "--target", str(tfile), "--pixel-pitch-mm", "0.02", "--distortion", "none",
               "--board", "flat", "-q", "-o", str(out)])
    return rc, capsys.readouterr().err, out, paths


@pytest.mark.parametrize("n_found", [4, 5])
def test_a_partial_view_is_skipped_naming_it_and_the_run_goes_on(tmp_path, capsys, n_found):
    """A DET file whose view has 4 or 5 corners (fewer than MIN_CORNERS) is skipped with one line, listed under
    CALIB.json's `skipped`; the other views calibrate."""
    views = [_view(p) for p in ((60, 45, -700), (-200, 0, -650), (300, 150, -600), (60, -250, -600))]
    partial = views[1][0].copy()
    partial[n_found:] = np.nan
    views.insert(2, (partial, views[1][1]))
    rc, err, out, paths = _calibrate_dets(tmp_path, views, capsys)
    assert rc == 0, err
    lines = [s for s in err.splitlines() if paths[2] in s]
    assert len(lines) == 1 and f"{n_found} corners found; a view needs at least 6" in lines[0] \
        and lines[0].endswith("skipped"), err
    calib = json.loads(out.read_text())
    assert [s["image"] for s in calib["skipped"]] == [paths[2]], calib["skipped"]
    assert [v["image"] for v in calib["views"]] == paths[:2] + paths[3:], "the four full views calibrate"


def test_too_few_views_left_after_skipping_partial_ones_stops(tmp_path, capsys):
    views = [_view(p) for p in ((60, 45, -700), (-200, 0, -650), (300, 150, -600))]
    views[2] = (np.where(np.arange(12)[:, None] < 5, views[2][0], np.nan), views[2][1])
    rc, err, out, paths = _calibrate_dets(tmp_path, views, capsys)
    assert rc == 2 and "only 2 of 3 images have a board with 6 corners or more" in err, err
    assert len(err.strip().splitlines()) == 2 and "Traceback" not in err, f"a warning and the error: {err}"
    assert not out.exists(), "no output file left behind"


def test_repeated_views_are_refused_naming_both_files():
    a, _ = _view((60, 45, -700))
    b, _ = _view((-200, 0, -650))
    check_views(["a.json", "b.json"], np.stack([a, b]))
    with pytest.raises(DetFileError, match="c.json: corners_px: the same detections as a.json"):
        check_views(["a.json", "b.json", "c.json"], np.stack([a, b, a + 1e-9]))


def test_detect_writes_a_self_describing_det_file(tmp_path):
    from renderer import write_image
    from tiltfit.experiments.synth import render_view

    tfile = tmp_path / "T.json"
    TARGET.save(str(tfile))
    R, T = look_at_pose(TARGET, (60, 45, -700))
    view = render_view(TARGET, CAMERA, R, T, noise_sigma=0.002, seed=1)
    write_image(str(tmp_path / "board.png"), view.image)
    out = tmp_path / "DET.json"
    rc = main(["detect", str(tmp_path / "board.png"), "--target", str(tfile), "-o", str(out), "-q"])
    assert rc == 0, "detect succeeds on a rendered board"
    det = read_det(str(out), TARGET.n_points)
    assert det["image"] == str(tmp_path / "board.png") and det["target"]["file"] == str(tfile), det
    assert det["format_version"] == DET_FORMAT_VERSION and "created" in det, det
    mode = os.stat(out).st_mode & 0o777
    umask = os.umask(0)
    os.umask(umask)
    assert mode == 0o666 & ~umask, f"mode {oct(mode)}"
