"""tiltfit.report.real_vs_rendered and `tiltfit report`'s real-against-rendered page.

The synthetic capture is made by the renderer through a known lens, but not the way the report renders it: a point
light (light falling off over the board), printed reflectances 0.05 / 0.85, 8-bit sRGB, spp 16. The report must
explain it up to its brightness model and the samples, and must see a principal point moved by 3 px.
The real test uses tests/data/real_vs_rendered/gopro_2views.json: views GOPR0032 and GOPR0053 of the defaults'
calibration of data/real/gopro_wide (every view calibrated, 2 kept; images by name, found with --photos).
"""
from __future__ import annotations

import copy
import json
import math
import os
import sys

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.join(ROOT, "tests"))  # fuzz_harness: a command's main run in this process
FIXTURE = os.path.join(ROOT, "tests", "data", "real_vs_rendered", "gopro_2views.json")
GOPRO = os.path.join(ROOT, "data", "real", "gopro_wide")

W, H = 160, 120


def _rotation(rx_deg: float, ry_deg: float) -> np.ndarray:
    a, b = math.radians(rx_deg), math.radians(ry_deg)
    Rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    Ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    return Rx @ Ry


def _calib(image: str) -> dict:
    """A tilted, blurred, distorted lens and one inclined view of a 7x5 board of 15 mm squares (a CALIB dict)."""
    target = {"type": "checkerboard", "units": "mm", "x_edges": [15.0 * i for i in range(8)],
              "y_edges": [15.0 * j for j in range(6)], "dark_cell": [0, 0], "margin": 8}
    R = _rotation(20.0, -10.0)
    centre = np.array([52.5, 37.5, 0.0])
    T = np.array([0.0, 0.0, 560.0]) - R @ centre
    return {"pixel_pitch_mm": 0.02, "image_size_px": [W, H], "principal_point_px": [81.3, 58.2], "w_mm": 16.0,
            "U_mm": 600.0, "d_mm": 5.0, "theta_F_deg": 3.0, "tilt_axis_deg": 0.0,
            "distortion": {"model": "brown_conrady", "coefficients": [-0.3, 0.0, 0.0, 0.0, 0.0]},
            "views": [{"image": image, "R": R.tolist(), "T_mm": T.tolist()}], "target": target}


def _capture(calib: dict, path: str) -> None:
    """The 'photo': a point light, reflectances 0.05/0.85, spp 16, written as 8-bit sRGB."""
    import torch

    import renderer
    from camio.files import write_image
    from renderer.scene.materials import Material
    from renderer.scene.model import ImageSettings, Light, Scene, SceneObject
    from tiltfit.files.calibrated import Calibration
    from tiltfit.files.scene_plugins import TargetBoard

    cal = Calibration.from_dict(calib)
    board = TargetBoard(cal.target, reflectance=(0.05, 0.85))
    light = Light("point", (2.6e5, 2.6e5, 2.6e5), (-150.0, -100.0, -300.0))
    scene = Scene([SceneObject("board", board, Material(texture=board.texture))], [light], cal.camera(0),
                  ImageSettings(W, H, spp=16, background=(0.02, 0.02, 0.02)))
    image = renderer.render(scene, spp=16, workers=1).image
    write_image(path, torch.clamp(image, 0, 1), encoding="srgb")


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    folder = tmp_path_factory.mktemp("rvr")
    photo = str(folder / "capture.png")
    calib = _calib(photo)
    _capture(calib, photo)
    return calib, photo, folder


def _report(calib, folder, name, **kw):
    from tiltfit.report.real_vs_rendered import RealVsRenderedOptions, write_real_vs_rendered

    out = folder / name
    out.mkdir()
    files, summary = write_real_vs_rendered(calib, str(folder / "calib.json"), str(out),
                                            RealVsRenderedOptions(spp=4, **kw))
    return files, summary


def test_true_calibration_explains_a_rendered_capture_and_a_moved_principal_point_does_not(synthetic):
    calib, photo, folder = synthetic
    files, truth = _report(calib, folder, "truth")
    assert "real_vs_rendered/view_00.png" in files, f"no view figure among {files}"
    assert len(truth["views"]) == 1, f"the view was not compared: {truth.get('skipped')}"
    t = truth["views"][0]
    assert set(t["profile_errors"]) == {"row", "column", "diagonal"}, f"lines: {t['profile_errors']}"
    # Only the brightness model (quadratic against a point light's fall-off), samples and 8-bit rounding differ.
    assert 0.05 < t["profile_error"] < 3.0, f"profile error with the true calibration {t['profile_error']:.3f}"
    assert t["rms_board"] < 8.0, f"RMS over the board with the true calibration {t['rms_board']:.3f}"
    for sign in (+1, -1):
        moved = copy.deepcopy(calib)
        moved["principal_point_px"][0] += sign * 3.0
        _, m = _report(moved, folder, f"moved{sign:+d}")
        e = m["views"][0]["profile_error"]
        assert e > 3 * t["profile_error"] and e > 4.0, \
            f"principal point moved {sign * 3} px: profile error {e:.3f} against {t['profile_error']:.3f} (truth)"


def test_a_wrong_blur_shows_in_the_profiles(synthetic):
    calib, photo, folder = synthetic
    _, truth = _report(calib, folder, "blur_truth")
    sharp = copy.deepcopy(calib)
    sharp["d_mm"] = 40.0  # ~3 px of blur where the capture has well under 1
    _, s = _report(sharp, folder, "blur_wrong")
    assert s["views"][0]["profile_error"] > 1.5 * truth["views"][0]["profile_error"], \
        f"a wrong blur: {s['views'][0]['profile_error']:.3f} against {truth['views'][0]['profile_error']:.3f}"


def test_photo_found_by_name_and_missing_photo_skipped(synthetic, tmp_path):
    from tiltfit.report.real_vs_rendered import find_photo

    calib, photo, folder = synthetic
    assert find_photo("elsewhere/capture.png", None, [str(folder)]) == os.path.join(str(folder), "capture.png")
    assert find_photo("nowhere.png", None, [str(folder)]) is None
    lost = copy.deepcopy(calib)
    lost["views"][0]["image"] = "nowhere/capture_lost.png"
    files, s = _report(lost, tmp_path, "lost")
    assert s["views"] == [] and s["skipped"][0]["reason"].startswith("photo not found"), f"{s}"
    assert files == ["real_vs_rendered.json"], f"files written for a missing photo: {files}"


def test_pick_views_and_scale():
    from tiltfit.report.real_vs_rendered import RealVsRenderedError, RealVsRenderedOptions, comparison_scale, pick_views

    assert pick_views(35, RealVsRenderedOptions()) == [0, 7, 14, 20, 27, 34]
    assert pick_views(3, RealVsRenderedOptions()) == [0, 1, 2]
    assert pick_views(10, RealVsRenderedOptions(views=(3, -1))) == [3, 9]
    with pytest.raises(RealVsRenderedError, match="view 10 does not exist"):
        pick_views(10, RealVsRenderedOptions(views=(10,)))
    assert comparison_scale((1280, 1024), RealVsRenderedOptions()) == 2
    assert comparison_scale((1280, 960), RealVsRenderedOptions(max_width_px=320)) == 4
    assert comparison_scale((640, 480), RealVsRenderedOptions()) == 1
    with pytest.raises(RealVsRenderedError, match="scale: 7 does not divide"):
        comparison_scale((640, 480), RealVsRenderedOptions(scale=7))


def _cli(*args):
    """`tiltfit ARGS` in this process, no interpreter start-up: (exit status, everything written to stderr, C level
    too); a traceback fails the test (tests/fuzz_harness.py)."""
    import fuzz_harness
    from tiltfit.cli import main as cli

    return fuzz_harness.run_command(cli.main, args)


@pytest.mark.slow
def test_report_on_real_gopro_views(tmp_path):
    """Two real GoPro photos against the target rendered through their calibration: the board lines up (profile
    errors of a few grey levels: glare and the print's gloss remain), and a principal point 8 px off does not."""
    out = tmp_path / "rep"
    rc, err = _cli("report", FIXTURE, "-o", str(out), "--photos", GOPRO, "--scale", "4", "--spp", "2")
    assert rc == 0, err
    assert "Traceback" not in err, err
    s = json.loads((out / "real_vs_rendered.json").read_text())
    assert [v["view"] for v in s["views"]] == [0, 1], f"views compared: {s['views']}, skipped {s['skipped']}"
    for v in s["views"]:
        assert 1.0 < v["profile_error"] < 10.0, f"{v['image']}: profile error {v['profile_error']:.2f}"
        assert (out / "real_vs_rendered" / f"view_{v['view']:02d}.png").stat().st_size > 20_000
    md = (out / "report.md").read_text()
    assert "## Real against rendered" in md and "GOPR0032.jpg" in md, md[-800:]

    from tiltfit.files.calib import read_calib
    from tiltfit.report.real_vs_rendered import RealVsRenderedOptions, write_real_vs_rendered

    moved = read_calib(FIXTURE)
    moved["principal_point_px"][0] += 8.0
    (tmp_path / "m").mkdir()
    _, m = write_real_vs_rendered(moved, FIXTURE, str(tmp_path / "m"),
                                  RealVsRenderedOptions(views=(0,), photos_dirs=(GOPRO,), scale=4, spp=2))
    assert m["views"][0]["profile_error"] > 2 * s["views"][0]["profile_error"], \
        f"principal point +8 px: {m['views'][0]['profile_error']:.2f} against {s['views'][0]['profile_error']:.2f}"


def test_cli_bad_options_are_one_line(tmp_path, capsys):
    from tiltfit.cli import main as cli

    for args, needle in ((["--views", "0,x"], "--views"), (["--views", "5"], "view 5 does not exist"),
                         (["--spp", "0"], "--spp"), (["--photos", str(tmp_path / "none")], "not a folder")):
        rc = cli.main(["report", FIXTURE, "-o", str(tmp_path / "out"), *args])
        err = capsys.readouterr().err
        assert rc == 2, f"{args}: exit {rc}, {err}"
        assert needle in err and "Traceback" not in err and len(err.strip().splitlines()) == 1, f"{args}: {err}"
        assert not (tmp_path / "out").exists(), f"{args}: output left behind"
