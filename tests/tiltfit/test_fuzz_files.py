"""Fuzz corpus of issue 33 §4 (bad input outside detection): camera files given to `calibrate --init` (a 400-digit
mrcal intrinsic, tilts τ that put the optical axis off the image, negative focal lengths), `export` of a
lens-axis calibration whose θL is undetermined, `report` of a fitted board with the wrong number of points,
`--refine photometric` with a ChArUco target or DET files, a parser's message naming the file once and binary
junk. Run in-process through tests/fuzz_harness.py: exit 0 with a finite output, or exit 2 and one line
`tiltfit: <file>: <field>: ...`; no traceback, hang or file left behind.
"""
from __future__ import annotations

import json
import os
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import fuzz_harness  # noqa: E402

N = 12  # feature points of TARGET
TARGET = {"type": "checkerboard", "units": "mm", "x_edges": [0, 25, 50, 75, 100], "y_edges": [0, 25, 50, 75, 100],
          "dark_cell": [0, 0], "margin": 25}
CHARUCO = {"type": "charuco", "dictionary": "DICT_4X4_50", "squares": [5, 4], "square_mm": 30, "marker_mm": 22}
HUGE = "1" + "0" * 400  # a 401-digit integer
_DETS: dict = {}


def _dets() -> dict:
    """Four DET.json files of TARGET seen by a synthetic thin-lens camera (w 35 mm, U 900 mm, d 8 mm)."""
    if not _DETS:
        from renderer import Lens, Sensor
        from tiltfit.experiments.synth import look_at_pose, observe
        from tiltfit.target.layout import target_from_dict

        t = target_from_dict(TARGET)
        cam = Lens(35, 900, 8, sensor=Sensor(640, 480, 0.02))
        for i, pos in enumerate(((100, 75, -950), (-150, 20, -900), (330, 160, -880), (120, -200, -900))):
            o = observe(t, cam, *look_at_pose(t, pos))
            _DETS[f"v{i}.json"] = json.dumps({
                "image_size_px": [640, 480], "grid_found": True,
                "corners_px": [[round(x, 4), round(y, 4)] if ok else None
                               for (x, y), ok in zip(o.corners_px.tolist(), o.in_image)],
                "blur_px": [round(b, 4) for b in o.blur_px.tolist()]})
    return dict(_DETS)


def _calib(**changes) -> dict:
    """A CALIB.json of three views of TARGET as `tiltfit calibrate` writes it (the keys report/export read)."""
    rng = np.random.default_rng(0)
    views = [{"image": f"img{v}.png", "R": np.eye(3).tolist(), "T_mm": [-50.0 + v, -50.0, 950.0],
              "rms_reprojection_px": 0.1, "rms_blur_px": 0.05, "n_points": N, "outlier": False,
              "corners_px": rng.uniform(50, 590, (N, 2)).round(3).tolist(),
              "residuals_px": rng.normal(0, 0.1, (N, 2)).round(4).tolist()} for v in range(3)]
    calib = {"pixel_pitch_mm": 0.02, "image_size_px": [640, 480], "principal_point_px": [319.5, 239.5],
             "w_mm": 35.0, "U_mm": 900.0, "d_mm": 8.0, "f_mm": 33.7, "theta_F_deg": 0.0, "theta_L_deg": 0.0,
             "theta_L_paper_deg": 0.0, "views": views, "sigma": {"w_mm": 0.01, "U_mm": 1.0, "d_mm": 0.01},
             "runtime_s": 1.0, "undetermined": [], "distortion_model": "k1",
             "distortion": {"model": "brown_conrady", "coefficients": [0.01, 0, 0, 0, 0]}}
    calib.update(changes)
    return calib


def _board(points, sigma=None) -> dict:
    grid = [[x, y, 0.0] for y in (25, 50, 75) for x in (25, 50, 75, 100)][:N]
    out = {"model": "free", "points_mm": grid[:points] if isinstance(points, int) else points,
           "max_offset_in_plane_mm": 0.1, "max_offset_out_of_plane_mm": 0.1}
    if sigma is not None:
        out["sigma_points_mm"] = [[0.01, 0.01, 0.01]] * sigma
    return out


# --- calibrate --init with camera files ----------------------------------------------------------------------
def _init(name, text, fields, expect="refuse", init="cam.yml"):
    return {"name": f"init/{name}", "category": "init", "expect": expect, "fields": fields, "output": "C.json",
            "files": {"T.json": json.dumps(TARGET), **_dets(), init: text},
            "argv": ["calibrate", *[f"{{d}}/v{i}.json" for i in range(4)], "--target", "{d}/T.json",
                     "--pixel-pitch-mm", "0.02", "-o", "{d}/C.json", "-q", "--fit", "joint", "--init",
                     "{d}/" + init, "--max-iterations", "1"]}


def _mrcal(intrinsics, size="[640, 480]", pitch="0.02", model="LENSMODEL_OPENCV4") -> str:
    return (f"# tiltfit pixel_pitch_mm = {pitch}\n"
            f"{{'lensmodel': '{model}', 'intrinsics': [{intrinsics}], 'imagersize': {size}}}\n")


def _yml(K="1750., 0., 319.5, 0., 1750., 239.5, 0., 0., 1.", dist=None) -> str:
    text = ("%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\npixel_pitch_mm: 0.02\n"
            f"camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ {K} ]\n")
    if dist is not None:
        text += (f"distortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: {len(dist)}\n   dt: d\n"
                 f"   data: [ {', '.join(map(str, dist))} ]\n")
    return text


def _init_cases() -> list[dict]:
    rest = "1750.0, 319.5, 239.5, 0, 0, 0, 0"
    out = [_init("mrcal-ok", _mrcal(f"1750.0, {rest}"), (), expect="either", init="c.cameramodel"),
           # a finite but absurd start: OpenCV's solvePnP asserted (a traceback) on the corners it undistorts
           _init("mrcal-p1-1e300", _mrcal("1750.0, 1750.0, 319.5, 239.5, 0, 0, 1e300, 0"), (), expect="either",
                 init="c.cameramodel")]
    for name, intr, field in (
            ("mrcal-fx-400-digits", f"{HUGE}, {rest}", "intrinsics"),
            ("mrcal-fx-minus-400-digits", f"-{HUGE}, {rest}", "intrinsics"),
            ("mrcal-k1-400-digits", f"1750.0, 1750.0, 319.5, 239.5, {HUGE}, 0, 0, 0", "intrinsics"),
            ("mrcal-fx-negative", f"-1750.0, {rest}", "not positive"),
            ("mrcal-both-negative", "-1750.0, -1750.0, 319.5, 239.5, 0, 0, 0, 0", "not positive"),
            ("mrcal-fx-zero", f"0, {rest}", "not positive"),
            ("mrcal-fx-bool", f"True, {rest}", "intrinsics"),
            ("mrcal-fx-string", f"'1750', {rest}", "intrinsics"),
            ("mrcal-fx-1e308x10", f"1e309, {rest}", "intrinsics"),
            ("mrcal-fx-differs", f"1800.0, {rest}", "differ by more than 1 %")):
        out.append(_init(name, _mrcal(intr), ("c.cameramodel", field), init="c.cameramodel"))
    for name, size in (("mrcal-size-400-digits", f"[{HUGE}, 480]"), ("mrcal-size-negative", "[-640, 480]")):
        out.append(_init(name, _mrcal(f"1750.0, {rest}", size=size), ("c.cameramodel", "imagersize"),
                         init="c.cameramodel"))
    for name, pitch in (("mrcal-pitch-400-digits", HUGE), ("mrcal-pitch-negative", "-0.02")):
        out.append(_init(name, _mrcal(f"1750.0, {rest}", pitch=pitch), ("c.cameramodel", "pixel_pitch_mm"),
                         init="c.cameramodel"))
    tau = lambda tx, ty: [0.0] * 12 + [tx, ty]  # noqa: E731
    out.append(_init("opencv-tau-small", _yml(dist=tau(0.02, 0.01)), (), expect="either"))
    for name, t, field in (("opencv-tau-1.5-1.5", tau(1.5, 1.5), "tau_x, tau_y"),
                           ("opencv-tau-1.5-0", tau(1.5, 0.0), "tau_x, tau_y"),
                           ("opencv-tau-0--1.4", tau(0.0, -1.4), "tau_x, tau_y"),
                           ("opencv-tau-1.6", tau(1.6, 0.0), "tau_x, tau_y"),
                           ("opencv-tau-nan", tau(float("nan"), 0.0), "distortion_coefficients")):
        out.append(_init(name, _yml(dist=[".nan" if v != v else v for v in t]), ("cam.yml", field)))
    for name, K in (("opencv-fx-negative", "-1750., 0., 319.5, 0., 1750., 239.5, 0., 0., 1."),
                    ("opencv-fy-negative", "1750., 0., 319.5, 0., -1750., 239.5, 0., 0., 1."),
                    ("opencv-both-negative", "-1750., 0., 319.5, 0., -1750., 239.5, 0., 0., 1."),
                    ("opencv-fx-zero", "0., 0., 319.5, 0., 1750., 239.5, 0., 0., 1.")):
        out.append(_init(name, _yml(K=K), ("cam.yml", "camera_matrix", "not positive")))
    return out


# --- export and report of hand-made calibrations -----------------------------------------------------------
def _export(name, calib, fields=(), expect="refuse", to="opencv", output="cam.yml"):
    return {"name": f"export/{name}", "category": "export", "expect": expect, "fields": fields, "output": output,
            "files": {"I.json": calib if isinstance(calib, (str, bytes)) else json.dumps(calib)},
            "argv": ["export", "{d}/I.json", "--to", to, "-o", "{d}/" + output, "-q"]}


def _report(name, calib, fields=(), expect="refuse"):
    return {"name": f"report/{name}", "category": "report", "expect": expect, "fields": fields, "output": "rep",
            "files": {"I.json": calib if isinstance(calib, (str, bytes)) else json.dumps(calib)},
            "argv": ["report", "{d}/I.json", "-o", "{d}/rep", "-q"]}


def _export_cases() -> list[dict]:
    axis = dict(distortion_centre="lens_axis", U_mm=None, undetermined=["U_mm"], theta_L_deg=None,
                theta_L_paper_deg=None, f_mm=None)
    out = [_export("axis-theta-L-null", _calib(**axis, theta_F_deg=5.0), ("I.json", "theta_L_deg")),
           _export("axis-theta-L-null-theta-F-null", _calib(**{**axis, "theta_F_deg": None}),
                   ("I.json", "theta_L_deg")),
           _export("axis-theta-L-null-negative-theta-F", _calib(**axis, theta_F_deg=-30.0), ("I.json", "theta_L_deg")),
           _export("axis-theta-L-null-json", _calib(**axis, theta_F_deg=5.0), ("I.json", "theta_L_deg"),
                   output="cam.json"),
           _export("axis-theta-F-0", _calib(**axis, theta_F_deg=0.0), expect="ok"),
           _export("axis-theta-L-3", _calib(**{**axis, "theta_L_deg": 3.0}, theta_F_deg=40.0), expect="ok"),
           _export("axis-theta-L-null-mrcal", _calib(**axis, theta_F_deg=5.0), expect="ok", to="mrcal",
                   output="c.cameramodel"),
           _export("sensor-theta-L-null", _calib(**{**axis, "distortion_centre": "sensor"}, theta_F_deg=5.0),
                   expect="ok")]
    return out


def _report_cases() -> list[dict]:
    out = [_report("board-ok", _calib(board=_board(N, sigma=N)), expect="ok")]
    for name, board, field in (("board-3-points", _board(3), "board.points_mm"),
                               ("board-11-points", _board(11), "board.points_mm"),
                               ("board-13-points", _board([[0.0, 0.0, 0.0]] * 13), "board.points_mm"),
                               ("board-0-points", _board([]), "board.points_mm"),
                               ("board-sigma-3", _board(N, sigma=3), "board.sigma_points_mm"),
                               ("board-point-2d", _board([[0.0, 0.0]] * N), "board.points_mm[0]"),
                               ("board-point-nan", _board([[0.0, 0.0, 0.0]] * (N - 1) + [["NaN", 0, 0]]),
                                "board.points_mm[11]")):
        text = json.dumps(_calib(board=board)).replace('"NaN"', "NaN")
        out.append(_report(name, text, ("I.json", field)))
        out.append(_export(name, text, ("I.json", field)))
    return out


# --- messages: the photometric refusal up front, a parser's location, binary junk -------------------------
def _photometric_cases() -> list[dict]:
    def calibrate(name, files, inputs, fields):
        return {"name": f"photometric/{name}", "category": "photometric", "expect": "refuse", "fields": fields,
                "output": "C.json", "files": files,
                "argv": ["calibrate", *inputs, "--target", "{d}/T.json", "--pixel-pitch-mm", "0.02",
                         "--refine", "photometric", "-o", "{d}/C.json", "-q"]}

    junk = {f"p{i}.png": b"not read before the target is checked" for i in range(3)}
    return [calibrate("charuco-target", {"T.json": json.dumps(CHARUCO), **junk},
                      [f"{{d}}/p{i}.png" for i in range(3)], ("T.json", "--refine photometric", "ChArUco")),
            calibrate("det-files", {"T.json": json.dumps(TARGET), **_dets()}, [f"{{d}}/v{i}.json" for i in range(4)],
                      ("v0.json", "--refine photometric", "photographs"))]


JUNK = {"bytes-0-255": bytes(range(256)) * 4, "nul-led": b"\x00\x01\x02\x03abc",
        "random": bytes(np.random.default_rng(1).integers(1, 256, 2000, dtype=np.uint8)),
        "elf": b"\x7fELF\x02\x01\x01" + bytes(200)}


def _file_cases() -> list[dict]:
    out = []
    for name, blob in JUNK.items():
        out.append(_export(f"junk-{name}", blob, ("I.json", "binary data, not a text file")))
        out.append(_report(f"junk-{name}", blob, ("I.json", "binary data, not a text file")))
    text = json.dumps(_calib())
    for name, blob in (("utf16", text.encode("utf-16")), ("utf16-le-nobom", text.encode("utf-16-le")),
                       ("utf32-be-nobom", text.encode("utf-32-be"))):
        out.append(_export(f"wide-{name}", blob, ("I.json", "UTF-16 or UTF-32")))
    for name, bad in (("trailing-comma", '{"a": 1,}'), ("yaml", "foo: [1, 2\n"), ("truncated", text[:100])):
        out.append(_export(f"json-{name}", bad, ("I.json:1:", "not valid JSON")))
    return out


def cases() -> list[dict]:
    return fuzz_harness.unique(_init_cases() + _export_cases() + _report_cases() + _photometric_cases()
                               + _file_cases())


CASES = cases()


@pytest.mark.parametrize("case", CASES, ids=[c["name"] for c in CASES])
def test_fuzz_case(case):
    fuzz_harness.check(case, "tiltfit")


@pytest.mark.parametrize("command", ["export", "report", "compare", "detect"])
def test_a_parse_error_names_the_file_once(tmp_path, command):
    """issue 33 §4: `b.yml: b.yml:1:1: not valid JSON` named the file twice; the location follows it once."""
    from tiltfit.cli.main import main

    bad = tmp_path / "b.yml"
    bad.write_text("foo: [1, 2\n")
    (tmp_path / "I.json").write_text(json.dumps(_calib()))
    (tmp_path / "v0.json").write_text(_dets()["v0.json"])
    argv = {"export": ["export", bad, "-o", tmp_path / "o.yml"], "report": ["report", bad, "-o", tmp_path / "r"],
            "compare": ["compare", bad, tmp_path / "I.json"],
            "detect": ["detect", tmp_path / "v0.json", "--target", bad, "-o", tmp_path / "D.json"]}[command]
    rc, err = fuzz_harness.run_command(main, argv + ["-q"])
    line = err.strip()
    assert rc == 2 and line.count("b.yml") == 1 and f"{bad}:1:1: not valid JSON" in line, f"exit {rc}: {err!r}"


def test_export_of_a_lens_axis_calibration_with_theta_L_writes_tau(tmp_path):
    """The refusal is only for an undetermined θL: with θL known the OpenCV file holds τ ≠ 0 (14 coefficients)
    and a note that does not call the projection approximate."""
    import cv2

    from tiltfit.cli.main import main

    calib = _calib(distortion_centre="lens_axis", theta_F_deg=40.0, theta_L_deg=3.0)
    (tmp_path / "I.json").write_text(json.dumps(calib))
    rc, err = fuzz_harness.run_command(main, ["export", tmp_path / "I.json", "-o", tmp_path / "c.yml", "-q"])
    assert rc == 0, err
    fs = cv2.FileStorage(str(tmp_path / "c.yml"), cv2.FILE_STORAGE_READ)
    d = fs.getNode("distortion_coefficients").mat().ravel()
    note = fs.getNode("tiltfit_note").string()
    fs.release()
    assert d.size == 14 and abs(d[12]) + abs(d[13]) > 1e-3, f"no tau in {d}"
    assert "exactly" in note and "approximates" not in note, note
