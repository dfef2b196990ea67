"""Fuzz corpus of the calibrated surface (issue 33: "fuzz the surface you add next the same way"): the scene file's
`calibrated` camera and `target` shape, `renderer render --camera/--view`, the camera files `Calibration.read`
takes (OpenCV FileStorage and mrcal with tiltfit's U/d), `tiltfit report`'s rendering options, the OpenCV JSON
export of a fitted board and examples/composite.py's options. The kept cases are those that failed before their
fix (a traceback, a silent acceptance, a message naming the wrong field); each ends in exit 0 with a finite output,
or exit 2 and one line naming the file and the field (tests/fuzz_harness.py), or, for the API, a ValueError whose
one line names them.
"""
from __future__ import annotations

import json
import os
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import fuzz_harness  # noqa: E402

TARGET = {"type": "checkerboard", "units": "mm", "x_edges": [0, 25, 50, 75, 100], "y_edges": [0, 25, 50, 75, 100],
          "dark_cell": [0, 0], "margin": 25}
N = 9  # feature points of TARGET
HUGE = 10 ** 30


def _calib(**changes) -> dict:
    """A CALIB.json of three views of TARGET, 80x60 px (renders in a fraction of a second)."""
    rng = np.random.default_rng(0)
    views = [{"image": f"img{v}.png", "R": np.eye(3).tolist(), "T_mm": [-50.0 + 5 * v, -50.0, 950.0],
              "rms_reprojection_px": 0.1, "rms_blur_px": 0.05, "n_points": N, "outlier": False,
              "corners_px": rng.uniform(5, 75, (N, 2)).round(3).tolist(),
              "residuals_px": rng.normal(0, 0.1, (N, 2)).round(4).tolist()} for v in range(3)]
    calib = {"pixel_pitch_mm": 0.16, "image_size_px": [80, 60], "principal_point_px": [39.5, 29.5],
             "w_mm": 35.0, "U_mm": 900.0, "d_mm": 8.0, "f_mm": 33.7, "theta_F_deg": 0.0, "theta_L_deg": 0.0,
             "theta_L_paper_deg": 0.0, "views": views, "sigma": {"w_mm": 0.01, "U_mm": 1.0, "d_mm": 0.01},
             "runtime_s": 1.0, "undetermined": [], "distortion_model": "k1",
             "distortion": {"model": "brown_conrady", "coefficients": [0.01, 0, 0, 0, 0]}, "target": TARGET}
    calib.update(changes)
    return calib


def _scene(**camera) -> dict:
    return {"image": {"spp": 1}, "camera": {"type": "calibrated", "file": "C.json", "view": 0, **camera},
            "lights": [{"type": "ambient", "intensity": [1, 1, 1]}],
            "objects": [{"name": "board", "shape": {"type": "target", "file": "T.json"}}]}


def _mrcal(extra: str = "", pitch: str = "0.16") -> str:
    return (f"# tiltfit pixel_pitch_mm = {pitch}\n{extra}"
            "{'lensmodel': 'LENSMODEL_OPENCV4', 'intrinsics': [280.0, 280.0, 39.5, 29.5, 0, 0, 0, 0], "
            "'imagersize': [80, 60]}\n")


def _yml(extra: str = "", pitch: str = "0.16") -> str:
    return ("%YAML:1.0\n---\nimage_width: 80\nimage_height: 60\n" f"pixel_pitch_mm: {pitch}\n"
            "camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
            "   data: [ 280., 0., 39.5, 0., 280., 29.5, 0., 0., 1. ]\n"
            "rvecs: !!opencv-matrix\n   rows: 1\n   cols: 3\n   dt: d\n   data: [ 0., 0., 0. ]\n"
            "tvecs: !!opencv-matrix\n   rows: 1\n   cols: 3\n   dt: d\n   data: [ -50., -50., 950. ]\n" + extra)


# --- the scene file's calibrated camera and target shape (renderer render) -----------------------------------
def _render(name, scene, fields, expect="refuse", files=None, extra=()):
    return {"name": f"scene/{name}", "category": "scene", "expect": expect, "fields": fields, "output": "out.exr",
            "files": {"C.json": json.dumps(_calib()), "T.json": json.dumps(TARGET),
                      "s.json": scene if isinstance(scene, str) else json.dumps(scene), **(files or {})},
            "argv": ["render", "{d}/s.json", "-o", "{d}/out.exr", "--quiet", *extra]}


def _scene_cases() -> list[dict]:
    eye = np.eye(3).tolist()
    out = [_render("ok", _scene(), (), expect="ok"),
           _render("own-pose-ok", _scene(R=eye, T_mm=[-50, -50, 950]), (), expect="ok"),
           # tracebacks before: the plugin read the file before the key was checked / np.isfinite of a big int
           _render("pixel_pitch_mm-string", _scene(file="N.cameramodel", pixel_pitch_mm="x"),
                   ("s.json", "camera.pixel_pitch_mm"), files={"N.cameramodel": _mrcal(pitch="")}),
           _render("pixel_pitch_mm-list", _scene(file="N.cameramodel", pixel_pitch_mm=[0.16]),
                   ("s.json", "camera.pixel_pitch_mm"), files={"N.cameramodel": _mrcal(pitch="")}),
           _render("R-huge-int", _scene(R=[[HUGE, 0, 0], [0, 1, 0], [0, 0, 1]], T_mm=[0, 0, 950]),
                   ("s.json", "camera.R")),
           # silently rendered before
           _render("T-huge-int", _scene(R=eye, T_mm=[0, 0, HUGE]), ("s.json", "camera.T_mm")),
           _render("T-1e30", _scene(R=eye, T_mm=[0, 0, 1e30]), ("s.json", "camera.T_mm")),
           _render("position-ignored", _scene(position=[0, 0, 5]), ("s.json", "camera.position")),
           _render("up-ignored", _scene(up=[0, 1, 0]), ("s.json", "camera.up")),
           _render("R-bool", _scene(R=[[True, 0, 0], [0, 1, 0], [0, 0, 1]], T_mm=[0, 0, 950]), ("s.json", "camera.R")),
           # messages that named camera.file for another field
           _render("R-without-T", _scene(R=eye), ("s.json", "camera.T_mm")),
           _render("aspect", {**_scene(), "image": {"spp": 1, "width": 40, "height": 40}},
                   ("s.json", "image", "80x60")),
           _render("width-1-gives-1x1", {**_scene(), "image": {"spp": 1, "width": 1}}, ("s.json", "image")),
           _render("no-views", _scene(), ("s.json", "camera.file", "no views"),
                   files={"C.json": json.dumps(_calib(views=[]))})]
    no_target = _scene()
    no_target["objects"][0]["shape"]["file"] = "C.json"
    out.append(_render("target-of-a-calib-without-one", no_target, ("s.json", "shape.file", "C.json", "target"),
                       files={"C.json": json.dumps(_calib(target=None))}))
    return out


def _cli_cases() -> list[dict]:
    def c(name, extra, fields, expect="refuse", files=None):
        return _render(f"cli-{name}", _scene(), fields, expect, files, extra)

    return [c("view-name", ["--camera", "{d}/C.json", "--view", "img1.png"], (), expect="ok"),
            c("view-3", ["--camera", "{d}/C.json", "--view", "3"], ("--view", "C.json", "0 to 2")),
            c("view-huge", ["--camera", "{d}/C.json", "--view", str(HUGE)], ("--view", "C.json")),
            c("view-unknown-name", ["--camera", "{d}/C.json", "--view", "img1"], ("--view", "img1.png")),
            c("camera-folder", ["--camera", "{d}/sub"], ("--camera", "sub"), files={"sub": None}),
            c("camera-no-views", ["--camera", "{d}/V.json"], ("--camera", "V.json", "no views"),
              files={"V.json": json.dumps(_calib(views=[]))}),
            c("camera-aspect", ["--camera", "{d}/C.json", "--set", "image.width=40", "--set", "image.height=40"],
              ("s.json", "image")),
            c("mitsuba-view-9", ["--camera", "{d}/C.json", "--view", "9", "--backend", "mitsuba"], ("--view",))]


# --- tiltfit report's rendering options --------------------------------------------------------------------
def _report(name, extra, fields, expect="refuse", calib=None):
    return {"name": f"report/{name}", "category": "report", "expect": expect, "fields": fields, "output": "rep",
            "files": {"C.json": json.dumps(calib or _calib())},
            "argv": ["report", "{d}/C.json", "-o", "{d}/rep", "-q", "--max-views", "0", *extra]}


def _report_cases() -> list[dict]:
    return [_report("spp-1e9", ["--spp", "1000000000"], ("--spp", "1024")),  # a 32 GB allocation before
            _report("scale-7", ["--scale", "7"], ("--scale", "80x60")),  # every view skipped, exit 0 before
            _report("scale-huge", ["--scale", str(HUGE)], ("--scale",)),
            _report("views-99", ["--views", "99"], ("--views", "0 to 2")),  # named the calibration's `views`
            _report("views-negative", ["--views", "-4"], ("--views",)),
            _report("no-views", [], ("C.json", "views", "no views"), calib=_calib(views=[]))]


# --- camera files read by Calibration.read ------------------------------------------------------------------
CAMERA_FILES = {  # name: (file name, text, what the one line must name)
    "mrcal-U-without-d": ("c.cameramodel", _mrcal("# tiltfit U_mm = 900.0\n"), "# tiltfit d_mm: missing"),
    "mrcal-d-without-U": ("c.cameramodel", _mrcal("# tiltfit d_mm = 8.0\n"), "# tiltfit U_mm: missing"),
    "mrcal-U-text": ("c.cameramodel", _mrcal("# tiltfit U_mm = far\n# tiltfit d_mm = 8\n"), "U_mm: expected a "
                     "positive length in mm, got 'far'"),
    "opencv-U-without-d": ("c.yml", _yml("tiltfit_U_mm: 900.\n"), "tiltfit_d_mm: missing"),
    "opencv-U-text": ("c.yml", _yml("tiltfit_U_mm: far\ntiltfit_d_mm: 8.\n"), "tiltfit_U_mm: expected a positive "
                      "length in mm, got 'far'"),
    "opencv-pitch-1e308": ("c.yml", _yml(pitch="1e308"), "camera_matrix, pixel_pitch_mm"),
    "opencv-rvec-1e308": ("c.yml", _yml().replace("data: [ 0., 0., 0. ]", "data: [ 1e308, 0., 0. ]"), "rvecs"),
}


@pytest.mark.parametrize("name", sorted(CAMERA_FILES))
def test_camera_file_refused_with_one_line_naming_the_field(tmp_path, name):
    from tiltfit.files.calibrated import Calibration

    file, text, field = CAMERA_FILES[name]
    (tmp_path / file).write_text(text)
    with pytest.raises(ValueError) as e:
        Calibration.read(tmp_path / file)
    msg = str(e.value)
    assert "\n" not in msg and str(tmp_path / file) in msg and field in msg, f"{name}: {msg!r}"


def test_camera_file_with_U_and_d_renders_their_blur(tmp_path):
    """The control of the cases above: both lines given, the blur is known and U, d are the file's."""
    from tiltfit.files.calibrated import Calibration

    (tmp_path / "c.cameramodel").write_text(_mrcal("# tiltfit U_mm = 900.0\n# tiltfit d_mm = 8.0\n"))
    cal = Calibration.read(tmp_path / "c.cameramodel")
    assert cal.blur_known and (cal.lens.U, cal.lens.d) == (900.0, 8.0), (cal.blur_known, cal.lens)


# --- Calibration's API: a pose of one's own, image sizes, points ------------------------------------------------
@pytest.mark.parametrize("R, T, field", [
    ((2 * np.eye(3)).tolist(), [0, 0, 900], "R"),  # accepted before: a scaled "rotation"
    (np.diag([1.0, 1.0, -1.0]).tolist(), [0, 0, 900], "R"),  # a mirror
    (np.eye(3).tolist(), [0, float("nan"), 900], "T_mm"),  # accepted before
    (np.eye(3).tolist(), [0, 0, 1e30], "T_mm"),
    (np.eye(3).tolist(), [0, 0], "T_mm"),
    ("eye", [0, 0, 900], "R"),
])
def test_camera_pose_of_ones_own_is_checked(tmp_path, R, T, field):
    from tiltfit.files.calibrated import Calibration, PoseError

    (tmp_path / "C.json").write_text(json.dumps(_calib()))
    cal = Calibration.read(tmp_path / "C.json")
    with pytest.raises(PoseError) as e:
        cal.camera(0, None, R, T)
    assert e.value.field == field and f": {field}: " in str(e.value) and "C.json" in str(e.value), str(e.value)


def test_camera_pose_of_ones_own_is_used(tmp_path):
    """The control: a valid pose is the camera's (its translation is the given T)."""
    from tiltfit.files.calibrated import Calibration

    (tmp_path / "C.json").write_text(json.dumps(_calib()))
    cal = Calibration.read(tmp_path / "C.json")
    p = cal.project(np.array([[0.0, 0.0, 0.0]]), 0)
    assert np.all(np.isfinite(p)), p
    cam = cal.camera(0, None, np.eye(3).tolist(), [1.0, 2.0, 500.0])
    assert cam is not None


@pytest.mark.parametrize("size", [(80.5, 60), ("80", "60"), (True, 60), (80,)])
def test_image_size_must_be_two_integers(tmp_path, size):
    from tiltfit.files.calibrated import Calibration, CalibrationError

    (tmp_path / "C.json").write_text(json.dumps(_calib()))
    with pytest.raises(CalibrationError, match="image size: expected two integers"):
        Calibration.read(tmp_path / "C.json").lens_for_image(size)


def test_project_refuses_points_that_are_not_n_by_3(tmp_path):
    from tiltfit.files.calibrated import Calibration, CalibrationError

    (tmp_path / "C.json").write_text(json.dumps(_calib()))
    with pytest.raises(CalibrationError, match=r"C.json: project: expected \(N, 3\)"):
        Calibration.read(tmp_path / "C.json").project([[0.0, 0.0]], 0)


def test_sampler_refuses_more_samples_per_pixel_than_the_scene_limit():
    """`renderer.render(spp=1e9)` drew a pixel's samples at once (32 GB); the scene files' limit holds there too."""
    from renderer.core.params import MAX_SPP
    from renderer.tracing.sampling import Sampler

    with pytest.raises(ValueError, match=f"spp: expected an integer in 1..{MAX_SPP}"):
        Sampler("sobol", 10 ** 9)
    assert Sampler("sobol", MAX_SPP).spp == MAX_SPP


# --- export of a fitted board (object_points) to OpenCV's JSON ------------------------------------------------
@pytest.mark.parametrize("image", ["img0.png", "John's board.png"])
def test_opencv_json_export_of_a_fitted_board_is_json(tmp_path, image):
    """OpenCV's JSON writer escaped the note's apostrophes ("the target's fitted shape") as \\', which no JSON
    reader takes; the file must parse as JSON and read back through OpenCV with the same points and names."""
    import cv2

    from tiltfit.cli.main import main

    grid = [[x, y, 0.1 * x] for y in (25, 50, 75) for x in (25, 50, 75)]
    calib = _calib(board={"model": "free", "points_mm": grid})
    calib["views"][0]["image"] = image
    (tmp_path / "C.json").write_text(json.dumps(calib))
    rc, err = fuzz_harness.run_command(main, ["export", tmp_path / "C.json", "-o", tmp_path / "cam.json", "-q"])
    assert rc == 0, err
    data = json.loads((tmp_path / "cam.json").read_text())
    assert "target's fitted shape" in data["tiltfit_note"] and data["images"][0] == image, data["tiltfit_note"]
    fs = cv2.FileStorage(str(tmp_path / "cam.json"), cv2.FILE_STORAGE_READ)
    points, name = fs.getNode("object_points").mat(), fs.getNode("images").at(0).string()
    fs.release()
    assert np.allclose(points, grid) and name == image, (points, name)


# --- examples/composite.py's options, refused before the calibration ---------------------------------------------
@pytest.mark.parametrize("argv, flag", [
    (["--spp", "0"], "--spp"), (["--spp", "1000000000"], "--spp"),  # tracebacks after a 6-s calibration before
    (["--out", "{f}"], "--out"),  # FileExistsError before
    (["--picture", "{d}/no/dir/p.png"], "--picture"), (["--picture", "{d}/p.txt"], "--picture"),
    (["--view", "nope.png"], "--view"),  # left calib.json behind after the calibration before
])
def test_composite_example_refuses_bad_options_first(tmp_path, argv, flag):
    sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "examples"))
    try:
        import composite
    finally:
        sys.path.pop(0)
    (tmp_path / "f").write_text("x")
    argv = [a.replace("{f}", str(tmp_path / "f")).replace("{d}", str(tmp_path)) for a in argv]
    out = [] if "--out" in argv else ["--out", str(tmp_path / "o")]
    rc, err = fuzz_harness.run_command(composite.main, argv + out, timeout_s=60)
    lines = err.strip().splitlines()
    assert rc == 2 and len(lines) == 1 and lines[0].startswith(f"composite.py: {flag}:"), (rc, err)
    assert sorted(os.listdir(tmp_path)) == ["f"], os.listdir(tmp_path)


CASES = fuzz_harness.unique(_scene_cases() + _cli_cases() + _report_cases())


@pytest.mark.parametrize("case", CASES, ids=[c["name"] for c in CASES])
def test_fuzz_case(case):
    fuzz_harness.check(case, "tiltfit" if case["category"] == "report" else "renderer")
