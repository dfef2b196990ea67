"""`tiltfit compare A.json B.json [-o DIR]` and `tiltfit calibrate --cross-validate K`: the projection difference
of two calibrations against what their σ predict, and the error contract."""
import json
import math
import os
from dataclasses import replace

import pytest

from tiltfit.files.calib import calib_dict
from tiltfit.calibrate.flow import calibrate
from tiltfit.cli.main import main
from tiltfit.calibrate.fit import FitOptions
from tiltfit.calibrate.model import PAPER_LENS, PAPER_SENSOR, LensCamera, board_points_mm, random_poses, \
    synthesize_observations
from tiltfit.uncertainty.covariance import projection_difference

OPTS = FitOptions(model_selection=False, free_principal_point=True, distortion="k1", max_rms_px=None)


def fit(seed, k1=-0.05, noise=0.1):
    rvec, T = random_poses(8, seed)
    cam = LensCamera(8, **PAPER_SENSOR, **PAPER_LENS, rvec=rvec, T_mm=T, distortion=[k1])
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
    cam = LensCamera(n_views, **PAPER_SENSOR, **PAPER_LENS, rvec=rvec, T_mm=T)
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
    cam = LensCamera(6, **PAPER_SENSOR, **PAPER_LENS, rvec=rvec, T_mm=T, distortion=[-0.05])
    obs = synthesize_observations(cam, board_points_mm(7, 5, 25.0), 0.1, 0.05, seed=4)
    path = tmp_path / "c.json"
    json.dump(calib_dict(calibrate(obs, "unified", options=OPTS), obs=obs), open(path, "w"))
    assert main(["report", str(path), "-o", str(tmp_path / "rep"), "-q"]) == 0
    assert os.path.getsize(tmp_path / "rep" / "projection_uncertainty.png") > 1000, "no map drawn"
    text = open(tmp_path / "rep" / "report.md").read()
    assert "projection uncertainty: median" in text and "σ error model: views" in text, text


# --- the review of `tiltfit compare`: order and sign, the rotation said, views shared ---------------------------

def _shifted(path, tmp_path, name, d_cx=0.0, d_cy=0.0, d_focal_px=0.0):
    """A copy of the CALIB.json at `path` with its principal point and focal length moved (px)."""
    data = json.load(open(path))
    data["principal_point_px"] = [data["principal_point_px"][0] + d_cx, data["principal_point_px"][1] + d_cy]
    data["w_mm"] += d_focal_px * data["pixel_pitch_mm"]
    out = str(tmp_path / name)
    json.dump(data, open(out, "w"))
    return out


def test_compare_prints_a_before_b_and_signs_b_minus_a(calibs, tmp_path, capsys):
    from tiltfit.uncertainty.compare import plot_titles

    a = calibs["a"]
    c = _shifted(a, tmp_path, "c.json", d_cx=4.0, d_cy=-2.0, d_focal_px=10.0)
    for first, second, sign in ((a, c, +1), (c, a, -1)):
        out = tmp_path / f"out{sign}"
        assert main(["compare", first, second, "-o", str(out), "-q"]) == 0
        printed = capsys.readouterr().out
        head = printed.splitlines()[0]
        assert f"{first} vs {second}" in head, f"the first file named first: {head!r}"
        assert f"from {first}'s camera frame to {second}'s" in head, head
        exp = (f"{second} − {first}: principal point ({4 * sign:+.3g}, {-2 * sign:+.3g}) px, "
               f"focal length {10 * sign:+.3g} px")
        assert exp in printed, f"expected {exp!r} in {printed!r}"
        saved = json.load(open(out / "compare.json"))
        assert (saved["a"], saved["b"]) == (first, second), (saved["a"], saved["b"])
        assert saved["principal_point_difference_px"] == pytest.approx([4 * sign, -2 * sign], abs=1e-9), \
            f"B − A: {saved['principal_point_difference_px']}"
        assert saved["focal_difference_px"] == pytest.approx(10 * sign, abs=1e-6), saved["focal_difference_px"]
        title, diff_title = plot_titles(saved, first, second)
        f, s = os.path.basename(first), os.path.basename(second)
        assert title.startswith(f"{f} vs {s}:") and f"rotation {f} → {s}" in title, title
        assert diff_title.startswith(f"difference {f} vs {s}"), diff_title


def test_compare_says_the_rotation_absorbs_a_principal_point_shift(calibs, tmp_path, capsys):
    a = calibs["a"]
    c = _shifted(a, tmp_path, "c.json", d_cx=6.0)
    data = json.load(open(a))
    focal_px = data["w_mm"] / data["pixel_pitch_mm"]
    assert main(["compare", a, c]) == 0
    printed = capsys.readouterr().out
    assert "the rotation absorbs a common shift of the principal point" in printed, printed
    turned = projection_difference(data, json.load(open(c)))
    expected_deg = math.degrees(math.atan(6.0 / focal_px))
    assert 0.8 * expected_deg < turned["rotation_deg"] < 1.25 * expected_deg, \
        f"rotation {turned['rotation_deg']:.4f}° for a 6 px shift at f = {focal_px:.0f} px ({expected_deg:.4f}°)"
    assert f"({turned['rotation_deg']:.3g}°)" in printed.splitlines()[0], printed
    assert turned["median_px"] < 0.1 * 6.0, f"the rotation should absorb most of the shift: {turned['median_px']}"
    assert main(["compare", a, c, "--no-rotation"]) == 0
    printed = capsys.readouterr().out
    assert "no rotation fitted" in printed, printed
    plain = projection_difference(data, json.load(open(c)), rotation=False)
    assert 0.9 * 6.0 < plain["median_px"] < 1.1 * 6.0, f"without a rotation the shift counts: {plain['median_px']}"
    assert plain["rotation_deg"] == 0.0, plain["rotation_deg"]


@pytest.fixture(scope="module")
def named_calibs():
    """Calibrations of one camera from named views 0…11: A = 0–7, B = 4–11 (4 shared), C = 8–11 (none in A),
    and A2 = A's views with another distortion model (all shared); with their detected corners."""
    rvec, T = random_poses(12, 11)
    cam = LensCamera(12, **PAPER_SENSOR, **PAPER_LENS, rvec=rvec, T_mm=T, distortion=[-0.05])
    obs = synthesize_observations(cam, board_points_mm(7, 5, 25.0), 0.1, 0.05, seed=11)
    obs.names = [f"photos/img{v:02d}.png" for v in range(12)]
    out = {}
    for name, views, opts in (("A", range(8), OPTS), ("B", range(4, 12), OPTS), ("C", range(6, 12), OPTS),
                              ("A2", range(8), replace(OPTS, distortion="k1k2"))):
        sub = obs.subset(list(views))
        out[name] = json.loads(json.dumps(calib_dict(calibrate(sub, "unified", options=opts), obs=sub)))
    return out


def test_compare_warns_about_shared_views(named_calibs, tmp_path, capsys):
    from tiltfit.uncertainty.compare import compare

    paths = {}
    for name, data in named_calibs.items():
        paths[name] = str(tmp_path / f"{name}.json")
        json.dump(data, open(paths[name], "w"))
    assert main(["compare", paths["A"], paths["B"], "-q"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "warning" in err[0] and "4 views" in err[0] and "not the right yardstick" in err[0], err
    res = compare(named_calibs["A"], named_calibs["B"])
    assert res["shared_views"]["n"] == 4 and res["consistent"] is not None, res["shared_views"]
    assert main(["compare", paths["C"], paths["A"], "-q"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "2 views are in both calibrations (of 6 and 8)" in err[0], err


def test_compare_no_warning_for_disjoint_views(named_calibs, calibs, tmp_path, capsys):
    from tiltfit.uncertainty.compare import shared_views

    a = dict(named_calibs["A"], views=[v for v in named_calibs["A"]["views"][:6]])
    assert shared_views(a, named_calibs["C"]) == [], "views 0–5 and 6–11 share none"
    pa, pc = str(tmp_path / "a.json"), str(tmp_path / "c.json")
    json.dump(a, open(pa, "w"))
    json.dump(named_calibs["C"], open(pc, "w"))
    assert main(["compare", pa, pc, "-q"]) == 0
    assert "warning" not in capsys.readouterr().err, "disjoint views: no warning"
    # Calibrations made without file names ("view0" …) say nothing about shared photos.
    assert shared_views(json.load(open(calibs["a"])), json.load(open(calibs["b"]))) == []


def test_shared_views_by_name_or_corners(named_calibs):
    from tiltfit.uncertainty.compare import shared_views

    a, b = named_calibs["A"], named_calibs["B"]
    assert shared_views(a, b) == [(4, 0), (5, 1), (6, 2), (7, 3)], shared_views(a, b)
    no_corners = [{k: x for k, x in v.items() if k != "corners_px"} for v in b["views"]]
    assert len(shared_views(a, dict(b, views=no_corners))) == 4, "without corners, the image names decide"
    # Another session numbered its photos alike: C's views 6–11 renamed img00…img05; where both files hold
    # corners, only the two truly shared views (6 and 7) count; without corners, the names decide.
    c = named_calibs["C"]
    renamed = [dict(v, image=f"elsewhere/img{i:02d}.png") for i, v in enumerate(c["views"])]
    assert shared_views(a, dict(c, views=renamed)) == [(6, 0), (7, 1)], shared_views(a, dict(c, views=renamed))
    bare = [{k: x for k, x in v.items() if k != "corners_px"} for v in renamed]
    assert shared_views(a, dict(c, views=bare)) == [(i, i) for i in range(6)], shared_views(a, dict(c, views=bare))


def test_compare_all_views_shared_gives_no_verdict(named_calibs, tmp_path, capsys):
    pa, pb = str(tmp_path / "a.json"), str(tmp_path / "a2.json")
    json.dump(named_calibs["A"], open(pa, "w"))
    json.dump(named_calibs["A2"], open(pb, "w"))
    assert main(["compare", pa, pb, "-q"]) == 0
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and "all 8 views" in err[0], err
    assert "verdict: no verdict" in captured.out and "consistent:" not in captured.out, captured.out
