"""Fuzz corpus for the newer `tiltfit` commands (issue 24): `report` and `export` on bad CALIB.json files,
OpenCV camera files given to `calibrate --init`, `target design|print` options, detection contradictions
and a decompression-bomb image. Run in-process through tests/fuzz_harness.py: every case ends with exit 0 and
a finite output, or exit 2 and one line `tiltfit: <file>: <field>: ...`; no traceback, hang or file left.
"""
from __future__ import annotations

import copy
import functools
import gzip
import json
import os
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import fuzz_harness  # noqa: E402

N = 12  # feature points per view in the hand-made calibrations below
TARGET = {"type": "checkerboard", "units": "mm", "x_edges": [0, 25, 50, 75, 100, 125, 150, 175, 200],
          "y_edges": [0, 25, 50, 75, 100, 125, 150], "dark_cell": [0, 0], "margin": 25}


def _dets() -> dict:
    """Four DET.json files of TARGET seen by a synthetic thin-lens camera (w 35 mm, U 900 mm, d 8 mm)."""
    from renderer import Lens, Sensor
    from tiltfit.experiments.synth import look_at_pose, observe
    from tiltfit.target.layout import target_from_dict

    t = target_from_dict(TARGET)
    cam = Lens(35, 900, 8, sensor=Sensor(640, 480, 0.02))
    out = {}
    for i, pos in enumerate(((100, 75, -950), (-150, 20, -900), (330, 160, -880), (120, -200, -900))):
        o = observe(t, cam, *look_at_pose(t, pos))
        out[f"v{i}.json"] = json.dumps({
            "image_size_px": [640, 480], "grid_found": True,
            "corners_px": [[round(x, 4), round(y, 4)] if ok else None
                           for (x, y), ok in zip(o.corners_px.tolist(), o.in_image)],
            "blur_px": [round(b, 4) for b in o.blur_px.tolist()]})
    return out


def _calib(n_views: int = 3) -> dict:
    """A CALIB.json as `tiltfit calibrate` writes it (the keys `report` and `export` read), made by hand."""
    rng = np.random.default_rng(0)
    views = []
    for v in range(n_views):
        corners = (rng.uniform(50, 590, (N, 2))).round(3).tolist()
        views.append({"image": f"img{v:05d}.png", "R": np.eye(3).tolist(), "T_mm": [-100.0 + v, -75.0, 950.0],
                      "rms_reprojection_px": 0.1, "rms_blur_px": 0.05, "n_points": N, "outlier": False,
                      "corners_px": corners, "residuals_px": rng.normal(0, 0.1, (N, 2)).round(4).tolist(),
                      "blur_px": [2.0] * N, "blur_residuals_px": rng.normal(0, 0.05, N).round(4).tolist(),
                      "depth_mm": [950.0] * N})
    return {"pixel_pitch_mm": 0.02, "image_size_px": [640, 480], "principal_point_px": [319.5, 239.5],
            "w_mm": 35.0, "U_mm": 900.0, "d_mm": 8.0, "f_mm": 33.7, "theta_F_deg": 0.0, "theta_L_deg": 0.0,
            "theta_L_paper_deg": 0.0, "views": views, "sigma": {"w_mm": 0.01, "U_mm": 1.0, "d_mm": 0.01},
            "runtime_s": 1.0, "rms_reprojection_px": 0.1, "held_out": {"folds": 3, "rms_px": 0.12},
            "skipped": [], "undetermined": [], "notes": [], "distortion_model": "k1",
            "distortion": {"model": "brown_conrady", "coefficients": [0.01, 0, 0, 0, 0]}}


CALIB = _calib()


def _with(obj, path: str, raw: str) -> str:
    """JSON text of `obj` with the value at the dotted `path` replaced by the raw JSON token `raw`."""
    obj = copy.deepcopy(obj)
    node, keys = obj, path.split(".")
    for k in keys[:-1]:
        node = node[int(k)] if isinstance(node, list) else node[k]
    node[int(keys[-1]) if isinstance(node, list) else keys[-1]] = "__FUZZ__"
    return json.dumps(obj).replace('"__FUZZ__"', raw)


def _report(text, expect="refuse", fields=("I.json",), name="", extra_files=None):
    return {"name": f"report/{name}", "category": "report", "files": {"I.json": text, **(extra_files or {})},
            "expect": expect, "fields": fields, "output": "rep",
            "argv": ["report", "{d}/I.json", "-o", "{d}/rep", "-q"]}


def _export(text, expect="refuse", fields=("I.json",), name="", output="cam.yml"):
    return {"name": f"export/{name}", "category": "export", "files": {"I.json": text}, "expect": expect,
            "fields": fields, "output": output, "argv": ["export", "{d}/I.json", "--to", "opencv", "-o",
                                                         "{d}/" + output, "-q"]}


# Fields of CALIB.json that report and export read, with values that must be refused.
BAD_EXTRAS = [
    ("held_out", "[]"), ("held_out", '"x"'), ("held_out.rms_px", "NaN"), ("held_out.rms_px", '"abc"'),
    ("held_out.folds", "1.5"), ("skipped", "[1, 2]"), ("skipped", '"a"'), ("undetermined", "[1]"),
    ("notes", "{}"), ("rms_reprojection_px", '"abc"'), ("rms_reprojection_px", "NaN"),
    ("rms_reprojection_px", "-1"), ("rms_reprojection_px", "Infinity"), ("distortion_model", "5"),
    ("views.0.residuals_px", "5"), ("views.0.residuals_px", "[[1, 2, 3]]"),
    ("views.0.residuals_px.0", "[NaN, 0]"), ("views.0.residuals_px.0", '["a", 0]'),
    ("views.0.corners_px", "[[1, 2]]"), ("views.0.corners_px.3", "[Infinity, 1]"),
    ("views.0.blur_residuals_px", "[1, 2, 3]"), ("views.0.depth_mm.0", "NaN"), ("views.0.image", "[]"),
    ("views.0.rms_reprojection_px", '"x"'), ("views.0.n_points", "1.5"), ("views.0.outlier", '"yes"'),
    ("views.1", "[]"),
]


def _report_cases() -> list[dict]:
    good = json.dumps(CALIB)
    out = [_report(good, expect="ok", fields=(), name="ok"),
           _report(good, expect="ok", fields=(), name="ok-existing-folder", extra_files={"rep/keep.txt": "mine"})]
    for field, raw in BAD_EXTRAS:
        key = field.split(".")[-1] if not field.split(".")[-1].isdigit() else field.split(".")[-2]
        out.append(_report(_with(CALIB, field, raw), fields=("I.json", key), name=f"{field}={raw[:10]}"))
    # Residuals of the wrong length (the plots used to be half written) and none at all.
    c = copy.deepcopy(CALIB)
    c["views"][1]["residuals_px"] = c["views"][1]["residuals_px"][:3]
    out.append(_report(json.dumps(c), fields=("I.json", "views[1].residuals_px"), name="residuals-short"))
    c = copy.deepcopy(CALIB)
    for v in c["views"]:
        v["residuals_px"] = [None] * N
    out.append(_report(json.dumps(c), fields=("I.json", "residuals_px"), name="residuals-all-null"))
    out.append(_report(_with(CALIB, "w_mm", "NaN"), fields=("I.json", "w_mm"), name="w_mm-nan",
                       extra_files={"rep/keep.txt": "mine"}))
    out.append(_report(good, fields=("rep",), name="output-is-file", extra_files={"rep": "a file"}))
    return out


def _export_cases() -> list[dict]:
    out = [_export(json.dumps(CALIB), expect="ok", fields=(), name="ok"),
           _export(json.dumps(CALIB), expect="ok", fields=(), name="ok-json", output="cam.json"),
           _export(json.dumps(CALIB), expect="ok", fields=(), name="ok-gz", output="cam.yml.gz"),
           _export(json.dumps(CALIB), expect="ok", fields=(), name="ok-xml", output="cam.xml")]
    for field, raw in BAD_EXTRAS[:14]:
        key = field.split(".")[-1]
        out.append(_export(_with(CALIB, field, raw), fields=("I.json", key), name=f"{field}={raw[:10]}"))
    big = copy.deepcopy(CALIB)
    big["views"] = [{"image": f"view_{i:05d}.png", "R": np.eye(3).tolist(), "T_mm": [0.0, 0.0, 900.0 + i]}
                    for i in range(6000)]
    out.append(_export(json.dumps(big), expect="ok", fields=(), name="6000-views"))
    return out


YML = """%YAML:1.0
---
image_width: __W__
image_height: 480
pixel_pitch_mm: 0.02
__EXTRA__
camera_matrix: __K__
"""
K_OK = "!!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ 1750., 0., 319.5, 0., 1750., 239.5, 0., 0., 1. ]"


def _yml(K=K_OK, W="640", extra=""):
    return YML.replace("__K__", K).replace("__W__", W).replace("__EXTRA__", extra)


def _init(files: dict, name: str, expect="refuse", fields=("cam.yml",), init="cam.yml"):
    return {"name": f"init-opencv/{name}", "category": "init-opencv", "expect": expect, "fields": fields,
            "files": {"T.json": json.dumps(TARGET), **_dets(), **files}, "output": "C.json",
            "argv": ["calibrate", *[f"{{d}}/v{i}.json" for i in range(4)], "--target", "{d}/T.json",
                     "--pixel-pitch-mm", "0.02", "-o", "{d}/C.json", "-q", "--fit", "joint", "--init",
                     "{d}/" + init, "--max-iterations", "1"]}


def _init_cases() -> list[dict]:
    out = []
    for name, K, field in (
            ("K-2x2", "!!opencv-matrix\n   rows: 2\n   cols: 2\n   dt: d\n   data: [ 1., 0., 0., 1. ]", "camera_matrix"),
            ("K-scalar", "5", "camera_matrix"), ("K-text", "abc", "camera_matrix"),
            ("K-dt-q", K_OK.replace("dt: d", "dt: q"), "camera_matrix"),
            ("K-short-data", K_OK.replace("0., 0., 1. ]", "0. ]"), "camera_matrix"),
            ("K-strings", K_OK.replace("1750., 0.,", '"a", "b",'), "camera_matrix"),
            ("K-nan", K_OK.replace("1750., 0.,", ".nan, 0.,"), "camera_matrix"),
            ("K-list", "[1, 2, 3]", "camera_matrix")):
        out.append(_init({"cam.yml": _yml(K=K)}, name, fields=("cam.yml", field)))
    for W in (".Inf", "5472.5", "-640", "0", "1e12", "abc", ".nan"):
        out.append(_init({"cam.yml": _yml(W=W)}, f"width={W}", fields=("cam.yml", "image_width")))
    for name, extra, field in (
            ("fisheye", "fisheye_model: 1", "fisheye"),
            ("fisheye-name", "distortion_model: fisheye", "distortion_model"),
            ("dist-3x3", "distortion_coefficients: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
                         "   data: [ 0., 0., 0., 0., 0., 0., 0., 0., 0. ]", "distortion_coefficients"),
            ("dist-nan", "distortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n"
                         "   data: [ .nan, 0., 0., 0., 0. ]", "distortion_coefficients"),
            ("rvecs-2", "rvecs: !!opencv-matrix\n   rows: 1\n   cols: 2\n   dt: d\n   data: [ 0., 0. ]", "rvecs"),
            ("pitch-text", "pixel_pitch_mm2: 1", None)):
        if field is None:
            continue
        out.append(_init({"cam.yml": _yml(extra=extra)}, name, fields=("cam.yml", field)))
    out.append(_init({"cam.yml": _yml(extra="fisheye_model: 0")}, "fisheye-0", expect="either", fields=()))
    return out


def _target_cases() -> list[dict]:
    def design(*opts, name, expect="refuse", fields=()):
        argv = {"--cols": "9", "--rows": "6", "--square-mm": "25", "--w-mm": "35", "--distance-mm": "900"}
        extra = list(opts)
        for k in list(argv):
            if k in extra:
                i = extra.index(k)
                argv[k] = extra.pop(i + 1)
                extra.pop(i)
        args = [x for kv in argv.items() for x in kv if kv[1] is not None]
        return {"name": f"target/design/{name}", "category": "target", "files": {}, "expect": expect,
                "fields": fields, "output": "T.json",
                "argv": ["target", "design", *args, *extra, "-o", "{d}/T.json", "-q"]}

    def print_(*opts, name, expect="refuse", fields=(), output="p.png"):
        return {"name": f"target/print/{name}", "category": "target", "files": {"T.json": json.dumps(TARGET)},
                "expect": expect, "fields": fields, "output": output,
                "argv": ["target", "print", "{d}/T.json", *opts, "-q"]}

    out = [design(name="ok", expect="ok"),
           design("--cols", "201", "--rows", "200", name="cols-201", fields=("--cols",)),
           design("--margin-mm", "1e7", name="margin-1e7", fields=("--margin-mm",)),
           design("--cols", "nine", name="cols-nine", fields=("--cols",)),
           design("--w-mm", None, name="missing-w", fields=("--w-mm",)),
           design("--square-mm", "1e7", name="square-1e7", fields=("T.json",)),
           design("--inclination-deg", "nan", name="inclination-nan", fields=("inclination",)),
           print_("--png", "{d}/p.png", "--dpi", "30", name="ok", expect="ok"),
           print_("--pdf", "{d}/p.pdf", name="ok-pdf", expect="ok", output="p.pdf"),
           print_("--png", "{d}/p.png", "--dpi", "1e-300", name="dpi-tiny", fields=("--dpi",)),
           print_("--png", "{d}/p.png", "--dpi", "nan", name="dpi-nan", fields=("--dpi",)),
           print_("--png", "{d}/p.png", "--dpi", "x", name="dpi-text", fields=("--dpi",)),
           print_("--png", "{d}/p.png", "--dpi", "30", "--scale-bar-mm", "1e9", name="bar-1e9",
                  fields=("--scale-bar-mm",)),
           print_("--pdf", "{d}/p.pdf", "--scale-bar-mm", "1e9", name="bar-1e9-pdf", fields=("--scale-bar-mm",),
                  output="p.pdf")]
    wide = {**TARGET, "margin": 1e6}
    c = print_("--pdf", "{d}/p.pdf", name="margin-1km-pdf", fields=("T.json", "margin"), output="p.pdf")
    c["files"]["T.json"] = json.dumps(wide)
    out.append(c)
    return out


# 8 columns, 7 non-uniform rows (cols + rows odd): the colours and the geometry each fix the labelling.
BOARD = {**TARGET, "y_edges": [0, 18, 38, 60, 84, 110, 138, 168]}
_PNG: dict = {}


def _png(pixels) -> bytes:
    import tempfile

    import OpenImageIO as oiio

    with tempfile.TemporaryDirectory() as d:
        p = os.path.join(d, "b.png")
        out = oiio.ImageOutput.create(p)
        out.open(p, oiio.ImageSpec(pixels.shape[1], pixels.shape[0], pixels.shape[2], oiio.UINT8))
        out.write_image(np.ascontiguousarray(pixels))
        out.close()
        return open(p, "rb").read()


def _board_png(kind: str) -> bytes:
    """An 8-bit photo of BOARD (tiltfit.experiments.synth's renderer): as printed, with dark and light swapped, or
    mirrored; cached."""
    if not _PNG:
        from renderer import Lens, Sensor
        from tiltfit.experiments.synth import look_at_pose, render_view
        from tiltfit.target.layout import target_from_dict

        t = target_from_dict(BOARD)
        cam = Lens(35, 900, 8, sensor=Sensor(640, 480, 0.02))
        px = render_view(t, cam, *look_at_pose(t, (100, 75, -950)), noise_sigma=0.002, srgb8=True,
                         seed=0).image_srgb8
        _PNG.update(board=_png(px), swapped=_png(255 - px), mirrored=_png(px[:, ::-1]))
    return _PNG[kind]


def _detection_cases() -> list[dict]:
    def detect(image, target, name, expect="refuse", fields=("img.png", "contradicts")):
        return {"name": f"detect/{name}", "category": "detection", "expect": expect, "fields": fields,
                # The photo is made when the case runs, not at collection (seconds of rendering in each worker).
                "files": {"img.png": functools.partial(_board_png, image), "T.json": json.dumps(target)},
                "output": "D.json",
                "argv": ["detect", "{d}/img.png", "--target", "{d}/T.json", "-o", "{d}/D.json", "-q"]}

    transposed = {**BOARD, "x_edges": BOARD["y_edges"], "y_edges": BOARD["x_edges"]}
    return [detect("board", BOARD, "ok", expect="ok", fields=()),
            detect("board", {**BOARD, "dark_cell": [1, 0]}, "dark-cell-parity"),
            detect("swapped", BOARD, "dark-light-swapped"),
            detect("mirrored", BOARD, "mirrored", fields=("img.png",)),
            detect("board", transposed, "transposed-target")]


def _bomb_cases() -> list[dict]:
    """A valid 20,000 × 20,000 PNG of a few hundred kB (a decompression bomb): refused naming the file."""
    import zlib

    def chunk(kind, data):
        return len(data).to_bytes(4, "big") + kind + data + zlib.crc32(kind + data).to_bytes(4, "big")

    side = 20000
    # Two rows of data suffice: the image must be refused from its header, before any row is decoded (the
    # message names the megapixels, which a read of the short data would not).
    raw = zlib.compress(b"\0" * (2 * (side + 1)), 9)
    png = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", side.to_bytes(4, "big") * 2 + bytes([8, 0, 0, 0, 0]))
           + chunk(b"IDAT", raw) + chunk(b"IEND", b""))
    return [{"name": "detect/decompression-bomb", "category": "limits", "expect": "refuse",
             "fields": ("img.png", "megapixels"), "files": {"img.png": png, "T.json": json.dumps(TARGET)},
             "output": "D.json",
             "argv": ["detect", "{d}/img.png", "--target", "{d}/T.json", "-o", "{d}/D.json", "-q"]}]


def cases() -> list[dict]:
    return fuzz_harness.unique(_report_cases() + _export_cases() + _init_cases() + _target_cases()
                               + _detection_cases() + _bomb_cases())


CASES = cases()


@pytest.mark.parametrize("case", CASES, ids=[c["name"] for c in CASES])
def test_fuzz_case(case):
    fuzz_harness.check(case, "tiltfit")


@pytest.mark.parametrize("ext", [".yml", ".json", ".yml.gz", ".xml"])
def test_export_files_are_accepted_by_init(tmp_path, ext):
    """What `tiltfit export` writes, in every format it writes, reads back through --init's reader and checks
    with the lens and poses unchanged."""
    from tiltfit.files.calib import validate_calib
    from tiltfit.cli.main import main
    from tiltfit.files.opencv_file import is_opencv_file, read_opencv

    (tmp_path / "I.json").write_text(json.dumps(CALIB))
    out = tmp_path / f"cam{ext}"
    rc, err = fuzz_harness.run_command(main, ["export", tmp_path / "I.json", "-o", out, "-q"])
    assert rc == 0, f"export to {ext}: {err}"
    if ext.endswith(".gz"):
        assert gzip.decompress(out.read_bytes()).startswith(b"%YAML"), "a .gz export is gzip-compressed YAML"
    assert is_opencv_file(str(out)), f"--init does not take {out.name} for an OpenCV file"
    data = validate_calib(str(out), read_opencv(str(out)))
    assert abs(data["w_mm"] - CALIB["w_mm"]) < 1e-9, f"w_mm {data['w_mm']} after the {ext} round trip"
    assert data["image_size_px"] == CALIB["image_size_px"], f"image size {data['image_size_px']}"
    assert len(data["views"]) == len(CALIB["views"]), f"{len(data['views'])} views read back"
    T = np.array([v["T_mm"] for v in data["views"]])
    assert np.allclose(T, [v["T_mm"] for v in CALIB["views"]]), "poses changed in the round trip"
    assert sorted(os.listdir(tmp_path)) == sorted(["I.json", out.name]), f"left: {os.listdir(tmp_path)}"


def _interrupt_on_call(monkeypatch, owner, name, n):
    """Make `owner.name` raise KeyboardInterrupt on its n-th call (as Ctrl-C arriving mid-write would)."""
    real, calls = getattr(owner, name), []

    def wrapped(*a, **k):
        calls.append(1)
        if len(calls) == n:
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(owner, name, wrapped)


@pytest.mark.parametrize("command", ["report", "report-existing", "print-png", "print-pdf"])
def test_interrupt_mid_write_one_line_exit_130_nothing_partial(tmp_path, monkeypatch, command):
    """Ctrl-C while the report's third plot or the printable is written: `tiltfit: interrupted`, exit 130,
    and the output folder / file as before the run (no partial plot set, no temporary file)."""
    from matplotlib.figure import Figure

    from tiltfit.cli.main import main

    (tmp_path / "I.json").write_text(json.dumps(CALIB))
    (tmp_path / "T.json").write_text(json.dumps(TARGET))
    if command == "report-existing":
        (tmp_path / "rep").mkdir()
        (tmp_path / "rep" / "keep.txt").write_text("mine")
    before = {p.relative_to(tmp_path) for p in tmp_path.rglob("*")}
    if command == "print-png":  # the PNG is written in strips of rows: Ctrl-C after the first strip
        import tiltfit.target.printable

        monkeypatch.setattr(tiltfit.target.printable, "PNG_STRIP_PIXELS", 1 << 12)
        _interrupt_on_call(monkeypatch, tiltfit.target.printable, "_write_rows", 2)
    else:
        _interrupt_on_call(monkeypatch, Figure, "savefig", 3 if command.startswith("report") else 1)
    argv = {"report": ["report", tmp_path / "I.json", "-o", tmp_path / "rep"],
            "print-png": ["target", "print", tmp_path / "T.json", "--png", tmp_path / "p.png", "--dpi", "30"],
            "print-pdf": ["target", "print", tmp_path / "T.json", "--pdf", tmp_path / "p.pdf"]}
    argv["report-existing"] = argv["report"]
    rc, err = fuzz_harness.run_command(main, argv[command] + ["-q"])
    assert rc == 130 and err.strip() == "tiltfit: interrupted", f"exit {rc}: {err!r}"
    after = {p.relative_to(tmp_path) for p in tmp_path.rglob("*")}
    assert after == before, f"left behind: {sorted(map(str, after - before))}"


def test_leftover_of_a_killed_writer_is_removed_by_the_next_run(tmp_path):
    """A SIGKILL between link and rename leaves `.NAME.PID.N.tmp`; the next write to NAME removes it once PID
    is gone (and leaves a live process's temporary file alone)."""
    import subprocess

    from tiltfit.cli.main import main

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    pid = int(dead.stdout)
    (tmp_path / "T.json").write_text(json.dumps(TARGET))
    stale, live = tmp_path / f".p.png.{pid}.0.tmp", tmp_path / f".p.png.{os.getppid()}.0.tmp"
    stale_dir = tmp_path / f".rep.{pid}.tmp"
    for p in (stale, live):
        p.write_bytes(b"partial")
    stale_dir.mkdir()
    (stale_dir / "coverage.png").write_bytes(b"partial")
    (tmp_path / "I.json").write_text(json.dumps(CALIB))
    rc, err = fuzz_harness.run_command(main, ["target", "print", tmp_path / "T.json", "--png", tmp_path / "p.png",
                                              "--dpi", "30", "-q"])
    assert rc == 0, err
    rc, err = fuzz_harness.run_command(main, ["report", tmp_path / "I.json", "-o", tmp_path / "rep", "-q"])
    assert rc == 0, err
    assert not stale.exists() and not stale_dir.exists(), "a dead writer's temporary files were not removed"
    assert live.exists(), "a live process's temporary file was removed"
    assert len(os.listdir(tmp_path / "rep")) == 6, f"report files: {os.listdir(tmp_path / 'rep')}"


@pytest.mark.parametrize("argv, where", [
    (["design", "--cols", "nine", "--rows", "6"], "--cols"),
    (["design", "--cols", "9", "--rows", "6", "--square-mm", "25", "--distance-mm", "900"], "--w-mm"),
    (["print", "T.json", "--dpi", "abc"], "--dpi"),
    (["frobnicate"], "frobnicate"),
])
def test_target_usage_errors_are_one_line(tmp_path, argv, where):
    """argparse's usage errors of `tiltfit target` (a word for a number, a missing option) as one line, exit 2."""
    from tiltfit.cli.main import main

    rc, err = fuzz_harness.run_command(main, ["target", *argv, "-o", tmp_path / "x.json"])
    lines = err.strip().splitlines()
    assert rc == 2 and len(lines) == 1 and lines[0].startswith("tiltfit: ") and where in lines[0], \
        f"exit {rc}: {err!r}"


def _interrupting_atomic_output(monkeypatch):
    """camio.files.atomic_output that lets the writer start, then raises KeyboardInterrupt (Ctrl-C mid-write)."""
    import contextlib

    from camio import files as io

    real = io.atomic_output

    @contextlib.contextmanager
    def interrupted(path):
        with real(path) as tmp:
            yield tmp
            with open(tmp, "ab") as f:
                f.write(b"partial")
            raise KeyboardInterrupt

    monkeypatch.setattr(io, "atomic_output", interrupted)


@pytest.mark.parametrize("command", ["export", "render", "design"])
def test_interrupt_in_the_atomic_writer_leaves_the_old_output(tmp_path, monkeypatch, command):
    """Ctrl-C while `tiltfit export`, `renderer render` or `tiltfit target design` writes: one line, exit 130,
    the previous output unchanged and no temporary file."""
    (tmp_path / "I.json").write_text(json.dumps(CALIB))
    scene = {"image": {"width": 4, "height": 3}, "camera": {"type": "pinhole", "position": [0, 0, -5],
                                                           "fov_deg": 40},
             "lights": [{"type": "point", "position": [0, 0, -5], "intensity": [5, 5, 5]}],
             "objects": [{"name": "b", "shape": {"type": "sphere", "center": [0, 0, 0], "radius": 1}}]}
    (tmp_path / "s.json").write_text(json.dumps(scene))
    out = tmp_path / {"export": "cam.yml", "render": "out.exr", "design": "T.json"}[command]
    out.write_bytes(b"previous")
    _interrupting_atomic_output(monkeypatch)
    if command == "render":
        from renderer.cli.main import main

        argv, prefix = ["render", tmp_path / "s.json", "-o", out, "--quiet"], "renderer"
    else:
        from tiltfit.cli.main import main

        prefix = "tiltfit"
        argv = (["export", tmp_path / "I.json", "-o", out, "-q"] if command == "export" else
                ["target", "design", "--cols", "9", "--rows", "6", "--square-mm", "25", "--w-mm", "35",
                 "--distance-mm", "900", "-o", out, "-q"])
    rc, err = fuzz_harness.run_command(main, argv)
    assert rc == 130 and err.strip() == f"{prefix}: interrupted", f"exit {rc}: {err!r}"
    assert out.read_bytes() == b"previous", "the previous output was changed"
    assert sorted(os.listdir(tmp_path)) == sorted(["I.json", "s.json", out.name]), f"left: {os.listdir(tmp_path)}"


def test_transposed_target_on_a_uniform_board_is_refused_by_its_colours(tmp_path):
    """A uniform board whose target file has its rows and columns swapped: the grid fits the photo turned by 90°,
    but on this board (an even number of cells each way) that turn swaps the squares' colours, so no placement
    of the file's board matches the photo: detection refuses in one line naming the contradiction (it labelled
    all corners before, wrongly); the matching file is labelled with no note."""
    from tiltfit.cli.main import main
    from renderer import Lens, Sensor
    from tiltfit.experiments.synth import look_at_pose, render_view
    from tiltfit.target.layout import target_from_dict

    t = target_from_dict(TARGET)
    assert t.n_cols % 2 == 0 and t.n_rows % 2 == 0, "the premise: an even number of cells each way"
    cam = Lens(35, 900, 8, sensor=Sensor(640, 480, 0.02))
    px = render_view(t, cam, *look_at_pose(t, (100, 75, -950)), noise_sigma=0.002, srgb8=True, seed=0).image_srgb8
    (tmp_path / "img.png").write_bytes(_png(px))
    notes = {}
    for name, target in (("same", TARGET), ("swapped", {**TARGET, "x_edges": TARGET["y_edges"],
                                                        "y_edges": TARGET["x_edges"]})):
        (tmp_path / f"{name}.json").write_text(json.dumps(target))
        rc, err = fuzz_harness.run_command(main, ["detect", tmp_path / "img.png", "--target", tmp_path / f"{name}.json",
                                                  "-o", tmp_path / f"{name}-D.json"])
        assert rc == (0 if name == "same" else 2), f"{name}: exit {rc}: {err}"
        notes[name] = err
    assert "contradicts the target file" in notes["swapped"] and len(notes["swapped"].strip().splitlines()) == 1, \
        f"one line naming the contradiction: {notes['swapped']!r}"
    assert not (tmp_path / "swapped-D.json").exists(), "no detection file written for the refused labelling"
    assert "x_edges and y_edges" not in notes["same"], f"a note where the target matches: {notes['same']!r}"
