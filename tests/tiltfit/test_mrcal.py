"""mrcal camera models: `tiltfit export --to mrcal` writes a `.cameramodel` that mrcal itself projects as we do, and
`--init` reads one back.

The cross-check runs mrcal (Debian's python3-mrcal, for the system Python; `make test` installs it as root) in a
subprocess; without it that test is skipped.
"""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest

from renderer import Lens, Sensor
from tiltfit.files.calib import camera_from_calib, validate_calib
from tiltfit.files.export import ExportError
from tiltfit.files.mrcal_file import mrcal_text, read_mrcal

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
import fuzz_harness  # noqa: E402  (tests/fuzz_harness.py: run a command's main in-process)

SYSTEM_PYTHON = "/usr/bin/python3"
COEFFS = [-0.21, 0.05, 0.0008, -0.0005, -0.004, 0.02, -0.01, 0.003]


def _calib(theta_F_deg: float = 0.0) -> dict:
    """A CALIB.json dict as `tiltfit calibrate` writes it (the keys `tiltfit export` reads)."""
    return {"pixel_pitch_mm": 0.0048, "image_size_px": [1280, 1024], "principal_point_px": [652.3, 498.7],
            "w_mm": 14.61, "U_mm": 900.0, "d_mm": 3.1, "f_mm": 14.37, "theta_F_deg": theta_F_deg,
            "theta_L_deg": theta_F_deg / 10, "theta_L_paper_deg": theta_F_deg / 10,
            "distortion": {"model": "brown_conrady", "coefficients": COEFFS}, "views": [],
            "sigma": {"w_mm": 0.01, "U_mm": 5.0, "d_mm": 0.1, "theta_F_deg": 0.1, "theta_L_deg": 0.01}}


def _points(n=60, seed=4) -> np.ndarray:
    g = np.random.default_rng(seed)
    return np.c_[g.uniform(-300, 300, n), g.uniform(-240, 240, n), g.uniform(500, 1500, n)]


def _our_projection(calib: dict, p_cam: np.ndarray) -> np.ndarray:
    lens = Lens(calib["w_mm"], calib["U_mm"], calib["d_mm"], math.radians(calib["theta_F_deg"]),
                Sensor(*calib["image_size_px"], calib["pixel_pitch_mm"]), tuple(calib["principal_point_px"]),
                tuple(calib["distortion"]["coefficients"]))
    return lens.project(p_cam)


def test_round_trip_keeps_the_projection(tmp_path):
    calib = _calib()
    path = tmp_path / "cam.cameramodel"
    path.write_text(mrcal_text(calib))
    back = validate_calib(str(path), read_mrcal(str(path)))
    assert back["pixel_pitch_mm"] == calib["pixel_pitch_mm"] and back["image_size_px"] == [1280, 1024]
    p = _points()
    again = {**back, "U_mm": 900.0, "d_mm": 3.1}
    assert np.abs(_our_projection(again, p) - _our_projection(calib, p)).max() < 1e-9, "same projection"
    cam = camera_from_calib(back)
    assert float(cam.w_mm.detach()) == pytest.approx(14.61, rel=1e-12), "--init starts from the file's lens"


def test_tilted_lens_says_what_is_lost():
    text = mrcal_text(_calib(theta_F_deg=12.0))
    note = next(line for line in text.splitlines() if line.startswith("# what this file does not hold"))
    assert "tilted" in note and "blur model" in note, f"the comment names the tilt and the blur: {note}"


@pytest.mark.parametrize("edit, match", [
    (lambda t: t.replace("LENSMODEL_OPENCV8", "LENSMODEL_SPLINED_STEREOGRAPHIC_order=3_Nx=16_Ny=12_fov_x_deg=100"),
     "lensmodel"),
    (lambda t: t.replace("'intrinsics': [", "'intrinsics': [1.0, "), "intrinsics"),
    (lambda t: t.replace("[1280, 1024]", "[1280.5, 1024]"), "imagersize"),
    (lambda t: "{'lensmodel': ", "not an mrcal camera model"),
])
def test_bad_files_are_refused_naming_the_key(tmp_path, edit, match):
    path = tmp_path / "bad.cameramodel"
    path.write_text(edit(mrcal_text(_calib())))
    with pytest.raises(ExportError, match=match):
        read_mrcal(str(path))


def test_cli_export_and_init(tmp_path):
    calib_path = tmp_path / "calib.json"
    calib_path.write_text(json.dumps(_calib()))
    out = tmp_path / "cam.cameramodel"
    from tiltfit.cli.main import main

    rc, err = fuzz_harness.run_command(main, ["export", calib_path, "--to", "mrcal", "-o", out, "-q"])
    assert rc == 0 and out.is_file(), f"export: {err}"
    rc, err = fuzz_harness.run_command(main, ["export", calib_path, "--to", "mrcal", "-o", tmp_path / "cam.yml", "-q"])
    assert rc == 2 and "cameramodel" in err and not (tmp_path / "cam.yml").exists(), err


def _mrcal_available() -> bool:
    if not os.path.exists(SYSTEM_PYTHON):
        return False
    return subprocess.run([SYSTEM_PYTHON, "-c", "import mrcal"], capture_output=True, timeout=120).returncode == 0


@pytest.mark.skipif(not _mrcal_available(), reason="mrcal (Debian's python3-mrcal) is not installed")
@pytest.mark.parametrize("theta_F_deg", [0.0, 12.0])
def test_mrcal_projects_as_we_do(tmp_path, theta_F_deg):
    """mrcal.project of the exported model equals our projection (a tilted lens's too: its chief rays meet a
    sensor perpendicular to the axis) to 1e-6 px."""
    calib = _calib(theta_F_deg)
    path = tmp_path / "cam.cameramodel"
    path.write_text(mrcal_text(calib))
    p = _points()
    np.save(tmp_path / "p.npy", p)
    script = ("import sys, numpy as np, mrcal\n"
              "m = mrcal.cameramodel(sys.argv[1])\n"
              "q = mrcal.project(np.load(sys.argv[2]), *m.intrinsics())\n"
              "np.save(sys.argv[3], q)\n")
    run = subprocess.run([SYSTEM_PYTHON, "-c", script, str(path), str(tmp_path / "p.npy"), str(tmp_path / "q.npy")],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, f"mrcal failed: {run.stderr.strip()[-400:]}"
    q = np.load(tmp_path / "q.npy")
    ours = _our_projection(calib, p)
    err = np.abs(q - ours).max()
    assert err < 1e-6, f"mrcal and tiltfit differ by {err:.3g} px"
    assert np.abs(ours - np.array(calib["principal_point_px"])).max() > 100, "points spread over the image"
