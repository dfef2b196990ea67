"""`tiltfit report` on a calibration refined with `--refine photometric`: the residual images (issue 30 §5: when the
refinement is rejected the report shows why).

Photos from the independent generator (`tiltfit.experiments.exact_capture`: every ray traced through the thin lens,
shot and read noise, 8-bit sRGB), three small views, calibrated on the command line with `--refine photometric`:
- the report draws `photometric_residual_view_KK.png` for the views the real-against-rendered page compares and
  shows them in report.md under the bounds table, with the sentence on the trust bounds;
- the residual at the generator's truth is the capture's noise (measured from a second capture of the same view),
  through the camera the record refers to: the refined one where kept, the corner fit's where not (a wrong
  `refined` lens in a rejected record changes nothing); with the principal point 2 px off it is clearly larger.
"""
from __future__ import annotations

import copy
import json
import math
import os

import numpy as np
import pytest

from tiltfit.experiments import exact_capture as ec
from tiltfit.target.layout import Target

BOARD = Target(tuple(50.0 * i for i in range(7)), tuple(50.0 * j for j in range(5)), (0, 0), 25.0)
VIEWS = ((20.0, 5.0, 780.0), (-15.0, 15.0, 820.0), (-10.0, -10.0, 800.0))
W, H, PITCH = 240, 160, 0.13
# Focused at 650 mm with a 40 mm aperture: blur discs of about 5 px on the boards at 780-820 mm.
LENS = ec.ExactLens.focused_at(55.0, 650.0, 40.0, 0.0, W, H, PITCH)
STRATA = {"aperture_strata": 5, "pixel_strata": 2}


def _linear(img: np.ndarray) -> np.ndarray:
    from camio.files import srgb_to_linear

    return srgb_to_linear(img / 255.0)


@pytest.fixture(scope="module")
def refined(tmp_path_factory):
    """(folder, CALIB.json dict, its path, the true poses, a second capture of view 0 (linear), each photo (linear))."""
    import cv2

    from tiltfit.cli import main as cli

    folder = tmp_path_factory.mktemp("photometric_report")
    paths, poses, photos = [], [], []
    for k, (rx, ry, dist) in enumerate(VIEWS):
        R, T = ec.pose_facing(BOARD, rx, ry, dist)
        img = ec.capture(LENS, R, T, BOARD, seed=k, **STRATA)
        paths.append(str(folder / f"view{k}.png"))
        cv2.imwrite(paths[-1], img)
        poses.append((R, T))
        photos.append(_linear(img.astype(np.float64)))
    again = _linear(ec.capture(LENS, *poses[0], BOARD, seed=100, **STRATA).astype(np.float64))
    (folder / "board.json").write_text(json.dumps(BOARD.to_dict()))
    out = folder / "calib.json"
    rc = cli.main(["calibrate", *paths, "--target", str(folder / "board.json"), "--pixel-pitch-mm", str(PITCH),
                   "--fit", "unified", "--distortion", "none", "--held-out", "0", "--refine", "photometric", "-q",
                   "-o", str(out)])
    assert rc == 0, "calibrate --refine photometric succeeds"
    return folder, json.loads(out.read_text()), str(out), poses, again, photos


def _noise(photo: np.ndarray, again: np.ndarray, where: np.ndarray) -> float:
    """σ of one capture's pixel (linear) on `where`: two captures of the same view differ by √2 σ."""
    d = (photo - again)[where]
    return float(np.sqrt(np.mean(d * d) / 2))


def _at_truth(calib: dict, poses, kept: str = "photometric", **change) -> dict:
    """`calib` with the generator's true lens and poses, as the camera its photometric record refers to; the
    record's levels dropped (refitted), so that every camera below is shaded the same way."""
    truth = LENS.truth()
    lens = {"w_mm": truth["w_mm"], "U_mm": truth["U_mm"], "d_mm": truth["d_mm"], "theta_F_deg": 0.0,
            "theta_L_deg": 0.0}
    data = copy.deepcopy(calib)
    data.update(lens, principal_point_px=[(W - 1) / 2 + change.get("dx_px", 0.0), (H - 1) / 2])
    data["views"] = [dict(v, R=np.asarray(R).tolist(), T_mm=np.asarray(T).tolist()) for v, (R, T) in
                     zip(data["views"], poses)]
    ph = data["photometric"]
    ph.pop("levels", None)
    ph["kept"] = kept
    ph["refined" if kept == "photometric" else "corner_fit"] = dict(lens)
    return data


@pytest.mark.slow
def test_report_draws_the_residual_images_of_the_compared_views(refined, tmp_path):
    """write_report: one `photometric_residual_view_KK.png` per compared view, shown in report.md after the bounds
    table and its sentence; the residual through the calibration is near the capture's noise."""
    from tiltfit.report.real_vs_rendered import RealVsRenderedOptions
    from tiltfit.report.photometric import photometric_residual
    from tiltfit.report.plots import write_report

    folder, calib, path, poses, again, photos = refined
    out = tmp_path / "report"
    files = write_report(calib, str(out), path, RealVsRenderedOptions(max_views=3, spp=1))
    names = sorted(os.path.basename(f) for f in files if "photometric_residual" in f)
    assert names == [f"photometric_residual_view_{k:02d}.png" for k in range(3)], f"residual images {names}"
    assert all((out / n).stat().st_size > 10_000 for n in names), "figures, not empty files"
    md = (out / "report.md").read_text()
    bounds, sentence, images = (md.index(s) for s in ("| parameter | start | trust bound", "**Trust bound:**",
                                                       "![photometric_residual_view_00.png]"))
    assert bounds < sentence < images < md.index("## Real against rendered"), "order: table, sentence, images"
    res = photometric_residual(calib, 0, photos[0], path)
    sigma = _noise(photos[0], again, np.isfinite(res.residual))
    assert res.levels == ("record" if calib["photometric"]["kept"] == "photometric" else "refitted"), res.levels
    assert 0.7 * sigma < res.rms < 2.0 * sigma, f"residual RMS {res.rms:.5f} through the calibration, noise {sigma:.5f}"
    # The same record, rejected: drawn through the corner fit's camera, levels refitted, and report.md says why.
    rejected = copy.deepcopy(calib)
    rejected["photometric"].update(kept="corner fit", rejected_because="held-out corners RMS 0.0300 px refined")
    write_report(rejected, str(tmp_path / "rejected"), path, RealVsRenderedOptions(views=(1,), spp=1))
    md = (tmp_path / "rejected" / "report.md").read_text()
    assert "not kept: held-out corners RMS 0.0300 px refined" in md.split("**Trust bound:**")[1], md
    assert "the corner fit's camera (the refinement was not kept)" in md and "| 1 | view1.png |" in md, md
    assert [r for r in md.splitlines() if r.startswith("| 1 | view1.png |")][0].endswith("| refitted |"), md
    assert (tmp_path / "rejected" / "photometric_residual_view_01.png").is_file(), "the rejected record's figure"


@pytest.mark.slow
@pytest.mark.parametrize("kept", ["photometric", "corner fit"])
def test_residual_at_the_truth_is_noise_and_a_wrong_camera_is_not(refined, kept):
    """At the generator's truth (as the refined camera, or as the corner fit's in a rejected record whose `refined`
    lens is 20 % off in d: it must not be used) the residual RMS is the capture's noise within ×1.5 both ways; with
    the principal point 2 px off it is at least twice that."""
    from tiltfit.report.photometric import photometric_residual

    _, calib, path, poses, again, photos = refined
    truth = _at_truth(calib, poses, kept)
    if kept != "photometric":
        truth["photometric"]["refined"] = dict(truth["photometric"]["corner_fit"],
                                               d_mm=1.2 * truth["photometric"]["corner_fit"]["d_mm"])
    res = photometric_residual(truth, 0, photos[0], path)
    finite = np.isfinite(res.residual)
    sigma = _noise(photos[0], again, finite)
    assert finite.sum() > 3000, f"{finite.sum()} pixels of the board drawn"
    assert res.camera == kept and res.levels == "refitted", (res.camera, res.levels)
    assert res.rms_levels_refitted == pytest.approx(res.rms, rel=1e-9), "levels refitted: the same RMS"
    assert sigma / 1.5 < res.rms < 1.5 * sigma, f"{kept}: RMS {res.rms:.5f} at the truth, capture noise {sigma:.5f}"
    off = photometric_residual(_at_truth(calib, poses, kept, dx_px=2.0), 0, photos[0], path)
    assert off.rms > 2.0 * sigma, f"{kept}: principal point 2 px off: RMS {off.rms:.5f}, noise {sigma:.5f}"


def test_bound_sentence_names_the_parameter_and_the_end():
    """The sentence under the bounds table: which parameter hit which end; without a hit, why it was not kept."""
    from tiltfit.report.photometric import bound_sentence, photometric_lines

    d = {"parameter": "d_mm", "start": 36.01, "low": 35.5, "high": 36.12, "refined": 36.12, "at_bound": True}
    w = {"parameter": "w_mm", "start": 55.0, "low": 54.0, "high": 56.0, "refined": 54.9, "at_bound": False}
    hit = bound_sentence({"kept": "corner fit", "bounds": [w, d], "rejected_because": "d_mm at the trust bound"})
    assert "d_mm hit the upper end" in hit and "w_mm" not in hit and "corner fit is kept" in hit, hit
    low = bound_sentence({"kept": "corner fit", "bounds": [dict(d, refined=35.5)]})
    assert "d_mm hit the lower end" in low, low
    why = bound_sentence({"kept": "corner fit", "bounds": [w], "rejected_because": "held-out corners RMS 0.015 px"})
    assert "No lens parameter reached" in why and "held-out corners RMS 0.015 px" in why, why
    ok = bound_sentence({"kept": "photometric", "bounds": [w]})
    assert "No lens parameter reached" in ok and "not kept" not in ok, ok
    lines = photometric_lines({"photometric": {"kept": "corner fit", "bounds": [w, d]}})
    assert lines[-1].startswith("**Trust bound:**") and "| d_mm |" in "\n".join(lines), lines
    # U's bound reaches infinity (1/U = 0): null in CALIB.json, ∞ in the table and the sentence
    u = {"parameter": "U_mm", "start": 1583.1, "low": 693.9, "high": None, "refined": None, "at_bound": True}
    text = "\n".join(photometric_lines({"photometric": {"kept": "corner fit", "bounds": [u]}}))
    assert "[693.9, ∞]" in text and "U_mm hit the upper end" in text, text


@pytest.mark.parametrize("field, value, named", [
    ("levels", {"white": 1}, "photometric.levels"),
    ("levels", [{"white": "x", "black": 0.0}], "photometric.levels[0].white"),
    ("bounds", [{"parameter": "d_mm", "start": 1.0, "low": 0.5, "high": "2", "refined": 1.0}],
     "photometric.bounds[0].high"),
    ("refined", {"w_mm": "55", "d_mm": 1.0}, "photometric.refined.w_mm"),
    ("vignetting", [0.1], "photometric.vignetting"),
])
def test_a_bad_photometric_record_is_one_line_naming_the_field(tmp_path, capsys, field, value, named):
    """`tiltfit report` on a CALIB.json whose photometric record is malformed: exit status 2, one line naming the
    file and the field, no report folder."""
    import warnings

    from tiltfit.cli.main import main

    calib = {"pixel_pitch_mm": PITCH, "image_size_px": [W, H], "w_mm": 55.0, "U_mm": None, "d_mm": None,
             "theta_F_deg": 0.0, "views": [{"image": "a.png", "R": np.eye(3).tolist(), "T_mm": [0, 0, 800.0],
                                            "corners_px": [[10.0, 10.0]], "residuals_px": [[0.1, 0.0]]}],
             "target": BOARD.to_dict(), "photometric": {"kept": "corner fit", field: value}}
    path = tmp_path / "calib.json"
    path.write_text(json.dumps(calib))
    out = tmp_path / "report"
    # The command's main in this process (no interpreter start-up: `python -m tiltfit` itself is
    # tests/tiltfit/test_cli.py::test_python_m_tiltfit's); a warning would have been a second line on stderr.
    capsys.readouterr()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rc = main(["report", str(path), "-o", str(out)])
    err = capsys.readouterr().err + "".join(f"{w.category.__name__}: {w.message}\n" for w in caught)
    lines = err.strip().splitlines()
    assert rc == 2 and len(lines) == 1, f"exit {rc}, stderr {err!r}"
    assert str(path) in lines[0] and named in lines[0] and "Traceback" not in err, lines[0]
    assert not out.exists(), "no partial report"
