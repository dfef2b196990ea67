"""The command line on the real photo set's corners: a photo without a board is skipped, CALIB.json format 2
holds what the report needs, `tiltfit report` and `tiltfit export` write their files."""
import json
import os

import numpy as np
import pytest

from tiltfit.cli import main as cli

DATA = os.path.join(os.path.dirname(__file__), "..", "..", "data", "real", "gopro_wide")
TARGET = os.path.join(DATA, "target.json")


@pytest.fixture(scope="module")
def dets(tmp_path_factory):
    folder = tmp_path_factory.mktemp("dets")
    with open(os.path.join(DATA, "corners_opencv.json"), encoding="utf-8") as f:
        found = json.load(f)
    paths = []
    for name in sorted(k for k, v in found.items() if v)[:10]:
        p = folder / name.replace(".jpg", ".json")
        p.write_text(json.dumps(found[name]))
        paths.append(str(p))
    blank = folder / "blank.png"
    from renderer import write_image

    write_image(str(blank), np.full((96, 128, 3), 0.5, dtype=np.float32))
    return paths, str(blank)


@pytest.fixture(scope="module")
def calib(dets, tmp_path_factory):
    paths, blank = dets
    out = tmp_path_factory.mktemp("out") / "calib.json"
    rc = cli.main(["calibrate", *paths, blank, "--target", TARGET, "--pixel-pitch-mm", "0.00155",
                   "--free-principal-point", "--distortion", "opencv5", "--held-out", "5", "-q", "-o", str(out)])
    assert rc == 0, "a photo without a board does not abort the calibration"
    return json.loads(out.read_text()), out


def test_photo_without_a_board_is_skipped(calib, dets):
    data, _ = calib
    assert [s["image"] for s in data["skipped"]] == [dets[1]], f"skipped: {data['skipped']}"
    assert len(data["views"]) == 10, "the other photos are calibrated"


def test_calib_file_format_2(calib):
    data, _ = calib
    assert data["format_version"] == 2 and data["created"].endswith("+00:00"), "version and UTC time"
    assert data["target"]["x_edges"][1] == 25.0, "target stored"
    assert data["distortion"]["model"] == "brown_conrady" and len(data["distortion"]["coefficients"]) == 8
    assert data["distortion_model"] == "opencv5" and data["undetermined"] == ["U_mm", "d_mm"]
    assert data["U_mm"] is None and data["d_mm"] is None and data["f_mm"] is None, "undetermined are null"
    ho = data["held_out"]["rms_px"]
    assert data["rms_reprojection_px"] < ho < 5 * data["rms_reprojection_px"], \
        f"held-out {ho} px beside fit {data['rms_reprojection_px']} px"
    v = data["views"][0]
    assert len(v["corners_px"]) == len(v["residuals_px"]) == 48, "per-view corners and residuals"
    r = np.array(v["residuals_px"], dtype=float)
    assert abs(np.sqrt((r ** 2).sum(1).mean()) - v["rms_reprojection_px"]) < 1e-9, \
        "residuals match the view RMS (per corner, OpenCV's definition)"


def test_report_and_export(calib, tmp_path):
    _, path = calib
    assert cli.main(["report", str(path), "-o", str(tmp_path / "rep"), "-q"]) == 0, "report"
    for name in ("per_view_rms.png", "residual_vectors.png", "residual_histogram.png", "blur_vs_depth.png",
                 "coverage.png", "report.md"):
        assert (tmp_path / "rep" / name).stat().st_size > 500, f"{name} written"
    assert cli.main(["export", str(path), "--to", "opencv", "-o", str(tmp_path / "cam.yml"), "-q"]) == 0
    assert "camera_matrix" in (tmp_path / "cam.yml").read_text(), "FileStorage written"


def test_too_few_photos_with_a_board_is_an_error(dets, tmp_path, capsys):
    paths, blank = dets
    rc = cli.main(["calibrate", paths[0], paths[1], blank, "--target", TARGET, "--pixel-pitch-mm", "0.00155",
                   "-q", "-o", str(tmp_path / "c.json")])
    err = capsys.readouterr().err
    assert rc == 2 and "only 2 of 3 images have a board" in err, err
    assert not (tmp_path / "c.json").exists(), "no output file left behind"
