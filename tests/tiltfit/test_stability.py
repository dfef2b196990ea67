"""tiltfit.experiments.stability: the closed forms behind each sweep, checked against the cameras and fits they describe."""
import json
import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from renderer import load_scene
from renderer import render
from tiltfit.experiments import stability as st
from tiltfit.calibrate.fit import FitOptions
from tiltfit.calibrate.flow import calibrate
from tiltfit.experiments.stability import coverage, gamma_noise, singular, two_stage

torch.set_num_threads(1)

QUICK = st.StabilityConfig.quick()


def _quiet(_msg):
    pass


# ------------------------------------------------------------------------ (c) accumulation-buffer coverage

def test_first_row_is_lost_where_the_closed_form_says():
    scene = load_scene(coverage.coverage_scene(0.0, "thin_lens_accumulation", QUICK))
    h = scene.camera.screen.size[1]
    theta = st.first_row_lost_theta_F(st.W_MM, h)
    assert theta == pytest.approx(math.atan(2 * st.W_MM / h), abs=1e-15), "D = w − (h/2) tan θF = 0"
    assert math.degrees(theta) == pytest.approx(77.846, abs=1e-3), "EOS 6D sensor (23.86 mm) at w = 55.39 mm"
    assert coverage.bottom_edge_valid(scene, theta - 1e-9), "just below θF*: the bottom edge still has a focus point"
    assert not coverage.bottom_edge_valid(scene, theta + 1e-9), "just above θF*: the bottom edge has none"
    ours = load_scene(coverage.coverage_scene(0.0, "thin_lens", QUICK))
    assert coverage.bottom_edge_valid(ours, math.radians(89.0)), "distributed ray tracing has a ray for every pixel"


@pytest.mark.parametrize("theta_F_deg", [84.0, -84.0])
def test_rendered_coverage_follows_the_closed_form(theta_F_deg):
    cfg = replace(QUICK, coverage_spp=8)
    acc = render(load_scene(coverage.coverage_scene(theta_F_deg, "thin_lens_accumulation", cfg)), spp=8, seed=3)
    ours = render(load_scene(coverage.coverage_scene(theta_F_deg, "thin_lens", cfg)), spp=8, seed=3)
    h = load_scene(coverage.coverage_scene(0.0, "thin_lens", cfg)).camera.screen.size[1]
    expected = st.coverage_closed_form(math.radians(theta_F_deg), st.W_MM, h)
    assert expected == pytest.approx(0.5 + st.W_MM / (h * math.tan(math.radians(84.0))), abs=1e-12)
    assert float(acc.coverage.mean()) == pytest.approx(expected, abs=0.01), "coverage = 1/2 + w / (h |tan θF|)"
    lost_row = -1 if theta_F_deg > 0 else 0  # y down: θF > 0 loses the bottom rows, θF < 0 the top ones
    assert float(acc.coverage[lost_row].max()) == 0.0, f"row {lost_row} has no focus point at θF = {theta_F_deg}°"
    assert float(acc.coverage[-1 - lost_row].min()) == 1.0, "the opposite edge keeps every sample"
    assert float(ours.coverage.min()) == 1.0, "distributed ray tracing covers every pixel"
    assert bool(torch.isfinite(ours.image).all()), "and its image is finite"


def test_coverage_closed_form_limits():
    assert st.coverage_closed_form(0.0, 55.0, 24.0) == 1.0, "untilted: everything"
    assert st.coverage_closed_form(math.radians(60.0), 55.0, 24.0) == 1.0, "below θF*: everything"
    assert st.coverage_closed_form(math.radians(89.999), 55.0, 24.0) == pytest.approx(0.5, abs=1e-3), \
        "θF → 90°: the focus points of the lower half are all behind the lens"


# ------------------------------------------------------------------------------- (b) two-stage vs joint

@pytest.fixture(scope="module")
def stage1():
    obs, _ = two_stage.tilt_observations(0.0, QUICK, seed=11)
    return calibrate(obs, "unified", options=FitOptions(model_selection=False, nominal_focal_mm=55.0))


def test_exact_physics_of_a_5_degree_tilt():
    """The numbers of the papers' NOTES: U 618.4 → 648.4 mm, θF = 48.03°, eq. (1) maps it back to 4.62°."""
    _, truth = two_stage.tilt_observations(math.radians(5.0), QUICK, seed=0)
    s = truth.summary()
    assert s["U_mm"] == pytest.approx(648.4, abs=0.05), "hinge rule"
    assert s["theta_F_deg"] == pytest.approx(48.03, abs=0.01), "Scheimpflug rule"
    assert s["theta_L_paper_deg"] == pytest.approx(4.62, abs=0.01), "eq. (1) underestimates by 8 %"


def test_two_stage_bias_at_5_degrees_has_the_predicted_sign_and_size(stage1):
    theta_L = math.radians(5.0)
    obs, truth = two_stage.tilt_observations(theta_L, QUICK, seed=12)
    with torch.no_grad():
        p_cam = truth.to_camera(obs.points_mm)[obs.blur_mask].numpy()
    v = stage1.values
    pred = st.two_stage_prediction(p_cam, theta_L, v["w_mm"], v["U_mm"], v["d_mm"])
    assert -0.45 < pred["error"] < -0.3, f"predicted two-stage bias {pred['error']:+.3f}° (U held, eq. (1))"
    opts = FitOptions(model_selection=False, nominal_focal_mm=55.0)
    st2 = calibrate(obs, "tilt", init=stage1.camera, init_sigma=stage1.sigma, options=replace(opts, blur_model="paper"))
    err = st2.values["theta_L_paper_deg"] - 5.0
    assert err < -0.3, f"the paper's two stages underestimate the tilt: error {err:+.3f}°"
    assert err == pytest.approx(pred["error"], abs=0.05), \
        f"measured {err:+.3f}° vs predicted {pred['error']:+.3f}° from the exact physics"
    joint = calibrate(obs, "joint", init=stage1.camera, options=opts)
    jerr = joint.values["theta_L_deg"] - 5.0
    assert abs(jerr) < 0.05, f"the joint fit frees U and recovers θL: error {jerr:+.4f}°"
    assert joint.values["U_mm"] == pytest.approx(truth.summary()["U_mm"], abs=2.0), "joint U follows the hinge rule"


def test_two_stage_prediction_vanishes_without_tilt():
    pts = np.array([[x, y, z] for x in (-40.0, 40.0) for y in (-60.0, 0.0, 60.0) for z in (500.0, 650.0, 800.0)])
    pred = st.two_stage_prediction(pts, math.radians(0.01))
    assert abs(pred["error"]) < 1e-3, f"a vanishing tilt has a vanishing bias, got {pred['error']:.2e}°"
    assert pred["U_true"] == pytest.approx(st.U0_MM, abs=1e-3), "U barely moves"


# ----------------------------------------------------------------------- (d) inverted perspective, singular

def test_inverted_perspective_stays_finite_near_its_singular_depth():
    a_star = st.singular_depth(singular.IP_ALPHA, singular.IP_P3)
    assert a_star == pytest.approx(8.0), "α p3 / (α − 1) for α = 2, p3 = 4"
    cam = load_scene(singular.singular_scene(a_star)).camera
    c = torch.tensor(cam.screen.center_px, dtype=torch.float64)
    screen_w = 2 * singular.IP_Q3 * math.tan(math.radians(singular.IP_FOV_DEG) / 2)
    px_per_unit = cam.width / screen_w
    for eps in (1.0, 1e-3, 1e-6, 1e-10, -1e-6):
        a = torch.tensor([[0.1, 0.05, a_star - eps]], dtype=torch.float64)
        uv = cam.project(a)[0]
        assert bool(torch.isfinite(uv).all()), f"ε = {eps:g}: projected position {uv.tolist()}"
        m = float(torch.linalg.norm(uv - c)) / (math.hypot(0.1, 0.05) * px_per_unit)
        m_closed = abs(singular.IP_Q3 / ((singular.IP_ALPHA - 1) * eps))
        assert m == pytest.approx(m_closed, rel=1e-6), f"ε = {eps:g}: magnification q3 / ((α − 1) ε)"
    at = cam.project(torch.tensor([[0.1, 0.05, a_star]], dtype=torch.float64))
    assert not bool(torch.isnan(at).any()), "no NaN at the singular depth"
    assert bool(torch.isinf(at).all()), "the point at the singular depth has no image (+inf)"
    for eps in (1e-9, 0.0):
        res = render(load_scene(singular.singular_scene(a_star - eps)), seed=1)
        assert bool(torch.isfinite(res.image).all()), f"ε = {eps:g}: rendered image finite"
        assert float(res.coverage.min()) == 1.0, f"ε = {eps:g}: every ray valid"
        assert float(res.image.std()) < 1e-6, f"ε = {eps:g}: all rays meet at the apex: one colour"


def test_singular_depth_needs_alpha_not_one():
    with pytest.raises(ValueError, match="alpha"):
        st.singular_depth(1.0, 4.0)
    m = st.inverted_magnification(2.0, 4.0, 1.0, np.array([4.0, 8.0]))
    assert m[0] == pytest.approx(0.25) and np.isinf(m[1]), "q3/p3 on the pseudo-screen; inf at a3*"


# -------------------------------------------------------------------------------------- (e) gamma mistake

def test_srgb_bias_prediction_changes_sign_with_blur_size():
    small, large = st.srgb_blur_bias(1.0), st.srgb_blur_bias(15.0)
    assert 0.05 < small < 0.12, f"pixel-sized blur read off sRGB values is overestimated: {small:+.3f}"
    assert -0.02 < large < 0.0, f"large blur is slightly underestimated: {large:+.4f}"
    assert st.srgb_blur_bias(1.0, dark=0.3, white=0.31) == pytest.approx(0.0, abs=0.01), \
        "a low-contrast edge sees a nearly linear encoding: no bias"
    with pytest.raises(ValueError, match="b_px"):
        st.srgb_blur_bias(0.0)


@pytest.mark.parametrize("ratio, expect", [(0.05, "up"), (0.5, "down")])
def test_measured_srgb_bias_is_the_predicted_one(ratio, expect):
    (row,) = gamma_noise.srgb_bias_rows(replace(QUICK, srgb_ratios=(ratio,)), _quiet)
    assert abs(row["bias_decoded"]) < 0.02, f"decoded to linear: bias {row['bias_decoded']:+.3f}"
    bias = row["bias_encoded_vs_decoded"]  # the encoding's own effect, what `srgb_blur_bias` predicts
    if expect == "up":
        assert bias > 0.05, f"{row['blur_px']:.2f} px read on sRGB values: {bias:+.3f} against decoded"
        assert bias == pytest.approx(row["predicted_bias"], abs=0.015), f"predicted {row['predicted_bias']:+.3f}"
    else:
        assert bias < 0.0, f"{row['blur_px']:.2f} px read on sRGB values: {bias:+.4f} against decoded"
        assert bias == pytest.approx(row["predicted_bias"], abs=0.003), f"predicted {row['predicted_bias']:+.4f}"


# ------------------------------------------------------------------------------------------ command line

def test_cli_runs_one_sweep(tmp_path, capsys):
    from tiltfit.cli.main import main

    assert main(["stability", "--quick", "--only", "singular", "-o", str(tmp_path)]) == 0
    for name in ("singular.json", "singular.csv", "singular.png", "stability.md", "run.json"):
        assert (tmp_path / name).is_file(), f"{name} written"
    data = json.loads((tmp_path / "singular.json").read_text(), parse_constant=_no_nan)
    assert data["findings"] and data["rows"], "findings and rows in the JSON"
    assert "Singular depth a3* = α p3/(α − 1) = 8" in capsys.readouterr().out, "findings on stdout"
    with pytest.raises(SystemExit):
        main(["stability", "--only", "nonsense"])


def _no_nan(token):
    raise AssertionError(f"non-standard JSON constant {token}")


@pytest.mark.slow
@pytest.mark.xdist_group("stability_quick")  # the run is test_stability_cluster.py's serial reference too
def test_quick_run_end_to_end(stability_quick_run):
    res, tmp_path, _ = stability_quick_run
    assert set(res.studies) == set(st.STUDIES), "every sweep ran"
    for name in st.STUDIES:
        for ext in ("json", "csv", "png"):
            assert (tmp_path / f"{name}.{ext}").is_file(), f"{name}.{ext} written"
        json.loads((tmp_path / f"{name}.json").read_text(), parse_constant=_no_nan)
        assert res.studies[name].findings, f"{name}: at least one finding"
    md = (tmp_path / "stability.md").read_text()
    for needle in ("77.846", "a3* = α p3/(α − 1) = 8", "+5°", "sRGB"):
        assert needle in md, f"stability.md states {needle!r}"
    two = {r["theta_L_true_deg"]: r for r in res.studies["two_stage"].rows}
    assert two[10.0]["two_stage_error_deg"] < two[5.0]["two_stage_error_deg"] < 0, "two-stage bias grows"
    assert abs(two[10.0]["joint_error_deg"]) < 0.1, "joint fit holds at 10°"
