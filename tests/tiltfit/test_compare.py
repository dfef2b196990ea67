"""`tiltfit compare A.json B.json [-o DIR]` and `tiltfit calibrate --cross-validate K`: the projection difference
of two calibrations against what their σ predict, and the error contract."""
import json
import os

import pytest

from tiltfit.calibfile import calib_dict
from tiltfit.calibration import calibrate
from tiltfit.cli import main
from tiltfit.fit import FitOptions
from tiltfit.model import PAPER_LENS, PAPER_SENSOR, TiltLensCamera, board_points_mm, random_poses, \
    synthesize_observations
from tiltfit.uncertainty import projection_difference

OPTS = FitOptions(model_selection=False, free_principal_point=True, distortion="k1", max_rms_px=None)


def fit(seed, k1=-0.05, noise=0.1):
    rvec, T = random_poses(8, seed)
    cam = TiltLensCamera(8, **PAPER_SENSOR, **PAPER_LENS, rvec=rvec, T_mm=T, distortion=[k1])
    obs = synthesize_observations(cam, board_points_mm(7, 5, 25.0), noise, 0.05, seed=seed)
    return calib_dict(calibrate(obs, "unified", options=OPTS))


@pytest.fixture(scope="module")
def calibs(tmp_path_factory):
    d = tmp_path_factory.mktemp("cmp")
    out = {}
    for name, kw in (("a", {"seed": 1}), ("b", {"seed": 2}), ("far", {"seed": 3, "k1": 0.0})):
        out[name] = str(d / f"{name}.json")
        with open(out[name], "w") as f:
            json.dump(fit(**kw), f)
    return out


def test_compare_agrees_and_disagrees(calibs, tmp_path, capsys):
    same = projection_difference(json.load(open(calibs["a"])), json.load(open(calibs["b"])))
    assert same["consistent"], f"two fits of one camera: {same['verdict']} (ratio {same['rms_ratio']:.2f})"
    assert 0.05 < same["rms_ratio"] < 2.0, f"difference / predicted {same['rms_ratio']:.3f}"
    differ = projection_difference(json.load(open(calibs["a"])), json.load(open(calibs["far"])))
    assert not differ["consistent"] and differ["rms_ratio"] > 5, \
        f"a different distortion should be found inconsistent: ratio {differ['rms_ratio']:.2f}"
    assert main(["compare", calibs["a"], calibs["b"], "-o", str(tmp_path / "out"), "-q"]) == 0
    printed = capsys.readouterr().out
    assert "median" in printed and "verdict" in printed and len(printed.splitlines()) <= 6, printed
    assert sorted(os.listdir(tmp_path / "out")) == ["compare.json", "compare.png"]


def test_calib_has_projection_uncertainty(calibs):
    data = json.load(open(calibs["a"]))
    pu = data["projection_uncertainty"]
    assert 0 < pu["median_px"] <= pu["worst_px"] < 10, f"projection σ: {pu['median_px']}, {pu['worst_px']}"
    assert data["sigma_model"]["name"] == "views", data["sigma_model"]
    assert data["sigma_classical"]["w_mm"] <= data["sigma"]["w_mm"] * (1 + 1e-9), "the classical σ is the floor"


@pytest.mark.parametrize("case", ["missing", "not_calib", "size"])
def test_compare_bad_input(calibs, tmp_path, capsys, case):
    a = calibs["a"]
    if case == "missing":
        b, field = str(tmp_path / "nope.json"), "nope.json"
    elif case == "not_calib":
        b = str(tmp_path / "det.json")
        json.dump({"image_size_px": [10, 10], "corners_px": []}, open(b, "w"))
        field = "det.json"
    else:
        data = json.load(open(a))
        data["image_size_px"] = [data["image_size_px"][0] // 2, data["image_size_px"][1] // 2]
        data["principal_point_px"] = [p / 2 for p in data["principal_point_px"]]
        b = str(tmp_path / "half.json")
        json.dump(data, open(b, "w"))
        field = "image_size_px"
    assert main(["compare", a, b]) == 2, f"{case}: expected exit status 2"
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and field in err, f"{case}: one line naming {field}: {err!r}"


def _calibrate_command(tmp_path, n_views: int, seed: int):
    """(`tiltfit calibrate` arguments for `n_views` synthetic DET files, the CALIB.json path it writes)."""
    from tests.tiltfit.test_cli import TARGET, write_detections  # noqa: F401

    rvec, T = random_poses(n_views, seed)
    cam = TiltLensCamera(n_views, **PAPER_SENSOR, **PAPER_LENS, rvec=rvec, T_mm=T)
    dets = write_detections(str(tmp_path), cam, "v", seed)
    target = tmp_path / "t.json"
    json.dump(TARGET.to_dict(), open(target, "w"))
    out = tmp_path / "c.json"
    return ["calibrate", *dets, "--target", str(target), "--pixel-pitch-mm", str(PAPER_SENSOR["pixel_pitch_mm"]),
            "--distortion", "none", "--no-model-selection", "--held-out", "0", "-o", str(out), "-q"], out


def test_calibrate_cross_validate(tmp_path, capsys):
    base, out = _calibrate_command(tmp_path, 9, 5)
    rc = main(base + ["--free-principal-point", "--cross-validate", "3"])
    assert rc == 0, capsys.readouterr().err
    cv = json.load(open(out))["cross_validation"]
    assert cv["k"] == 3 and len(cv["pairs"]) == 3 and sum(len(g) for g in cv["groups"]) == 9, cv
    assert all(p["consistent"] for p in cv["pairs"]), [p["verdict"] for p in cv["pairs"]]
    assert "cross-validation" in capsys.readouterr().err


def test_cross_validate_more_groups_than_views_is_refused_before_calibrating(tmp_path, capsys):
    base, out = _calibrate_command(tmp_path, 4, 6)
    assert main(base + ["--cross-validate", "3"]) == 2, "3 groups of 4 views should be refused"
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--cross-validate" in err[0] and "4" in err[0], err
    assert not out.exists(), "nothing written"
    assert main(base + ["--cross-validate", "2"]) == 0, capsys.readouterr().err
    assert out.exists(), "2 groups of 2 views calibrate"


def test_report_draws_projection_uncertainty(tmp_path):
    rvec, T = random_poses(6, 4)
    cam = TiltLensCamera(6, **PAPER_SENSOR, **PAPER_LENS, rvec=rvec, T_mm=T, distortion=[-0.05])
    obs = synthesize_observations(cam, board_points_mm(7, 5, 25.0), 0.1, 0.05, seed=4)
    path = tmp_path / "c.json"
    json.dump(calib_dict(calibrate(obs, "unified", options=OPTS), obs=obs), open(path, "w"))
    assert main(["report", str(path), "-o", str(tmp_path / "rep"), "-q"]) == 0
    assert os.path.getsize(tmp_path / "rep" / "projection_uncertainty.png") > 1000, "no map drawn"
    text = open(tmp_path / "rep" / "report.md").read()
    assert "projection uncertainty: median" in text and "σ error model: views" in text, text
