"""tiltfit.calibrate.fit: end-to-end calibrations on synthetic observations of the paper's camera.

Camera (paper, §4.2): 5472 × 3648 px, 6.54 µm pixels, w = 55.39 mm, U = 618.4 mm, d = 18.81 mm; a board of
9 × 6 cells of 25 mm (40 corners) at 520–720 mm in random poses; corner noise 0.05 px, blur noise 3 % of the
median blur. Tilted views are generated with the exact thin-lens physics: the lens (f = w U / (w + U)) tilted
by θL about its centre, so U moves (hinge rule) and θF follows the Scheimpflug relation; the blur is the
exact blur ellipse's equivalent-area diameter (renderer.cameras.optics).
"""
import math

import pytest
import torch

from renderer.cameras import optics
from tiltfit.calibrate.flow import calibrate
from tiltfit.calibrate.fit import FitError, FitOptions
from tiltfit.calibrate.model import (PAPER_LENS, PAPER_SENSOR, LensCamera, board_points_mm, random_poses,
                           synthesize_observations)
from tiltfit.calibrate.start import focal_from_homographies

W_MM, U_MM, D_MM = PAPER_LENS["w_mm"], PAPER_LENS["U_mm"], PAPER_LENS["d_mm"]
F_MM = W_MM * U_MM / (W_MM + U_MM)
BOARD = board_points_mm(8, 5, 25.0)
NOISE_PX = 0.05
BLUR_REL = 0.03
QUIET = FitOptions(model_selection=False)


def truth_camera(n_views, seed, theta_L_deg=0.0, principal_point_px=None):
    rvec, T = random_poses(n_views, seed)
    if theta_L_deg:
        return LensCamera.from_tilted_lens(n_views, **PAPER_SENSOR, w_mm=W_MM, f_mm=F_MM, d_mm=D_MM,
                                               theta_L=math.radians(theta_L_deg), rvec=rvec, T_mm=T,
                                               principal_point_px=principal_point_px)
    return LensCamera(n_views, **PAPER_SENSOR, **PAPER_LENS, rvec=rvec, T_mm=T,
                          principal_point_px=principal_point_px)


def observe(truth, seed, noise_px=NOISE_PX):
    clean = synthesize_observations(truth, BOARD, 0.0, 0.0)
    blur_sigma = BLUR_REL * float(clean.blur_px.nanmedian())
    return synthesize_observations(truth, BOARD, noise_px, blur_sigma, seed=seed), blur_sigma


@pytest.fixture(scope="module")
def stage1():
    """Stage 1 (unified) on 10 untilted views, with model selection."""
    truth = truth_camera(10, seed=1)
    obs, blur_sigma = observe(truth, seed=101)
    return truth, obs, blur_sigma, calibrate(obs, "unified")


@pytest.fixture(scope="module", params=[5.0, -5.0], ids=["tilt+5", "tilt-5"])
def tilted(request):
    """10 views with the lens tilted by ±5° about its centre (exact physics), and a joint fit."""
    truth = truth_camera(10, seed=2, theta_L_deg=request.param)
    obs, _ = observe(truth, seed=202)
    return request.param, truth, obs, calibrate(obs, "joint")


# --- stage 1 -------------------------------------------------------------------------------------------------

def test_unified_recovers_the_paper_camera(stage1):
    truth, obs, blur_sigma, res = stage1
    v, s = res.values, res.sigma
    print(f"\nstage 1: w {v['w_mm']:.4f} ± {s['w_mm']:.4f} (true {W_MM}), U {v['U_mm']:.3f} ± {s['U_mm']:.3f} "
          f"(true {U_MM}), d {v['d_mm']:.4f} ± {s['d_mm']:.4f} (true {D_MM}); {res.runtime_s:.2f} s")
    assert abs(v["w_mm"] / W_MM - 1) < 0.003, f"w within 0.3 %: {v['w_mm']} vs {W_MM}"
    assert abs(v["U_mm"] / U_MM - 1) < 0.005, f"U within 0.5 %: {v['U_mm']} vs {U_MM}"
    assert abs(v["d_mm"] / D_MM - 1) < 0.02, f"d within 2 %: {v['d_mm']} vs {D_MM}"
    assert v["theta_F_deg"] == 0.0 and s["theta_F_deg"] == 0.0, "stage 1 holds θF = 0"
    rot_err = torch.rad2deg((res.camera.R.detach().transpose(-1, -2) @ truth.R.detach()).diagonal(dim1=-2, dim2=-1)
                            .sum(-1).sub(1).div(2).clamp(-1, 1).acos())
    dT = (res.camera.T_mm - truth.T_mm).detach()
    sig_T = torch.tensor([view["sigma_T_mm"] for view in res.views])
    print(f"pose errors: rotation ≤ {float(rot_err.max()):.4f}°, lateral ≤ {float(dT[:, :2].abs().max()):.3f} mm, "
          f"depth ≤ {float(dT[:, 2].abs().max()):.3f} mm (σ depth ≤ {float(sig_T[:, 2].max()):.3f} mm)")
    assert float(rot_err.max()) < 0.05, f"rotations within 0.05°: {rot_err.tolist()}"
    assert float(dT[:, :2].abs().max()) < 0.2, f"lateral translation within 0.2 mm: {dT[:, :2].tolist()}"
    # Depth is tied to w (image scale ∝ w / z): its σ is w's relative σ times the distance, 0.1–0.2 mm here.
    assert bool((dT[:, 2].abs() < 3.5 * sig_T[:, 2]).all()) and float(dT[:, 2].abs().max()) < 0.5, \
        f"depth within 3.5σ and 0.5 mm: {dT[:, 2].tolist()} (σ {sig_T[:, 2].tolist()})"
    assert abs(res.noise["sigma_corner_px"] / NOISE_PX - 1) < 0.15, f"corner noise estimate {res.noise}"
    assert abs(res.noise["sigma_blur_px"] / blur_sigma - 1) < 0.15, f"blur noise estimate {res.noise}"
    rms = [view["rms_reprojection_px"] / math.sqrt(2) for view in res.views]  # per corner -> per coordinate
    assert all(0.6 * NOISE_PX < r < 1.4 * NOISE_PX for r in rms), f"per-view RMS near the noise: {rms}"


def test_model_selection_untilted(stage1):
    ms = stage1[3].model_selection
    th, pp = ms["theta_F"], ms["principal_point"]
    print(f"\nθF test: Λ = {th['lr_statistic']:.3g}, p = {th['p_value']:.3g}; "
          f"principal point: Λ = {pp['lr_statistic']:.3g}, p = {pp['p_value']:.3g}")
    assert ms["theta_F"]["justified"] is False, f"θF must not be justified on untilted data: {ms['theta_F']}"
    assert ms["principal_point"]["justified"] is False, f"centred principal point: {ms['principal_point']}"
    assert ms["theta_F"]["dof"] == 1 and ms["principal_point"]["dof"] == 2, "degrees of freedom"


# --- tilted lens ---------------------------------------------------------------------------------------------

def test_joint_recovers_the_lens_tilt(tilted):
    theta_L, truth, obs, res = tilted
    v, s = res.values, res.sigma
    true_U = float(truth.U_mm.detach())
    true_F = math.degrees(float(truth.theta_F.detach()))
    print(f"\njoint, θL = {theta_L:+}°: θL {v['theta_L_deg']:.4f} ± {s['theta_L_deg']:.4f}°, "
          f"θF {v['theta_F_deg']:.3f} ± {s['theta_F_deg']:.3f}° (true {true_F:.3f}), "
          f"U {v['U_mm']:.2f} ± {s['U_mm']:.2f} (true {true_U:.2f}), paper's (1): {v['theta_L_paper_deg']:.4f}°")
    assert abs(v["theta_L_deg"] - theta_L) < 0.05, f"θL within 0.05°: {v['theta_L_deg']} vs {theta_L}"
    assert abs(v["U_mm"] / true_U - 1) < 0.005, f"U (moved by the tilt) within 0.5 %: {v['U_mm']} vs {true_U}"
    assert abs(v["w_mm"] / W_MM - 1) < 0.003, f"w within 0.3 %: {v['w_mm']}"
    assert abs(v["d_mm"] / D_MM - 1) < 0.02, f"d within 2 %: {v['d_mm']}"
    assert abs(v["theta_L_deg"] - theta_L) < 4 * s["theta_L_deg"], f"error within 4σ: σ = {s['theta_L_deg']}"
    ms = res.model_selection["theta_F"]
    assert ms["justified"] is True and ms["p_value"] < 1e-6, f"θF justified on tilted data: {ms}"


def _stage2_prediction(truth, stage1_lens):
    """What stage 2 converges to without noise: θF minimising the blur error with U held at stage 1's U.

    An independent 1-D scan over θF with the true poses and the stage-1 lens (w, U, d), against noise-free
    blur of the true (tilted) lens.
    """
    w, U, d = stage1_lens
    p_cam = truth.to_camera(BOARD).detach()
    b_true = truth.blur_camera(p_cam).detach()

    def best(grid_deg):
        th = torch.deg2rad(grid_deg)[:, None, None]
        b = optics.blur_diameter_exact(p_cam, w, U, d, th) / PAPER_SENSOR["pixel_pitch_mm"]
        return float(grid_deg[int(torch.argmin(((b - b_true) ** 2).sum((-1, -2))))])

    coarse = best(torch.arange(-85.0, 85.0, 0.25, dtype=torch.float64))
    th_F = torch.deg2rad(torch.tensor(best(torch.arange(coarse - 0.3, coarse + 0.3, 0.002, dtype=torch.float64)),
                                      dtype=torch.float64))
    f = optics.focal_length(w, U, 0.0)
    return (math.degrees(float(th_F)), math.degrees(float(optics.theta_L_from_theta_F(th_F, w, U))),
            math.degrees(float(optics.theta_L_paper(th_F, f, U))))


def test_two_stage_is_biased_as_the_physics_predicts(tilted, stage1):
    theta_L, truth, obs, joint = tilted
    s1 = stage1[3]
    res = calibrate(obs, "tilt", init=s1.camera, init_sigma=s1.sigma)
    v, s = res.values, res.sigma
    pred_F, pred_L, pred_paper = _stage2_prediction(truth, (W_MM, U_MM, D_MM))
    print(f"\nθL = {theta_L:+}°: joint {joint.values['theta_L_deg']:.3f}°; two-stage (U held at "
          f"{s1.values['U_mm']:.1f}, true {float(truth.U_mm.detach()):.1f}): θF {v['theta_F_deg']:.2f} ± "
          f"{s['theta_F_deg']:.2f}° (predicted {pred_F:.2f}), θL exact {v['theta_L_deg']:.3f} ± "
          f"{s['theta_L_deg']:.3f}° (predicted {pred_L:.3f}), paper's (1) {v['theta_L_paper_deg']:.3f}° "
          f"(predicted {pred_paper:.3f})")
    # Stage 2 lands where the physics (U held while the tilt moved it) predicts, not on the truth.
    tol = max(3 * s["theta_L_deg"], 0.05)
    assert abs(v["theta_L_deg"] - pred_L) < tol, f"stage-2 θL {v['theta_L_deg']} vs predicted {pred_L} (±{tol})"
    assert abs(v["theta_L_paper_deg"] - pred_paper) < tol, \
        f"stage-2 paper θL {v['theta_L_paper_deg']} vs predicted {pred_paper} (±{tol})"
    assert abs(v["theta_F_deg"] - pred_F) < max(3 * s["theta_F_deg"], 0.3), \
        f"stage-2 θF {v['theta_F_deg']} vs predicted {pred_F}"
    # The predicted bias is real and has the predicted sign; eq (1) (f < w) shrinks |θL| further.
    bias, pred_bias = v["theta_L_paper_deg"] - theta_L, pred_paper - theta_L
    assert abs(pred_bias) > 0.15 and bias * pred_bias > 0, f"bias {bias:+.3f}° vs predicted {pred_bias:+.3f}°"
    assert abs(v["theta_L_paper_deg"]) < abs(v["theta_L_deg"]), "eq (1) underestimates |θL| (f < w)"
    assert abs(joint.values["theta_L_deg"] - theta_L) < abs(bias), "the joint fit beats the two-stage fit"
    # σ in stage 2 includes the stage-1 uncertainty of the held w, U, d but not the bias of holding U.
    assert s["theta_L_deg"] > 0 and res.model_selection["theta_F"]["justified"] is True, "θF justified"


# --- uncertainties -------------------------------------------------------------------------------------------

@pytest.mark.slow
def _coverage_ok(z) -> tuple[bool, str]:
    """Two-sided check that z = (estimate − truth) / σ behaves like N(0, 1): mean z² in [0.6, 1.6], the
    fraction within ±1σ in [0.55, 0.80] and within ±2σ in [0.88, 0.99]. σ twice too large gives mean z² ≈ 0.25
    and ~100 % within ±2σ; σ half too small gives mean z² ≈ 4 and ~38 % within ±1σ: both fail."""
    z = torch.as_tensor(z, dtype=torch.float64)
    m2 = float((z * z).mean())
    f1 = float((z.abs() < 1).double().mean())
    f2 = float((z.abs() < 2).double().mean())
    ok = 0.6 <= m2 <= 1.6 and 0.55 <= f1 <= 0.80 and 0.88 <= f2 <= 0.99
    return ok, f"mean z² {m2:.2f}, within 1σ {f1:.0%}, within 2σ {f2:.0%} (n = {len(z)})"


def test_uncertainties_are_honest():
    """Across 20 + 20 seeded fits with independent corner noise the errors in units of the classical σ behave like
    N(0, 1) — a two-sided test: the same check fails when σ is scaled by 2 or by 0.5. The default σ (the per-view
    error model, `tiltfit.uncertainty.covariance`, with the classical σ as its floor) may only be conservative here: never
    too small, at most about 1.3× the classical (mean z² ≥ 0.5); correlated errors: test_sigma_against_spread.py."""
    zs, lines, zv = [], [], []
    for seed in range(20):
        truth = truth_camera(6, seed=1000 + seed)
        obs, _ = observe(truth, seed=2000 + seed, noise_px=0.1)
        res = calibrate(obs, "unified", options=QUIET)
        for key, true in (("w_mm", W_MM), ("U_mm", U_MM), ("d_mm", D_MM)):
            zs.append((res.values[key] - true) / res.sigma_classical[key])
            zv.append((res.values[key] - true) / res.sigma[key])
    for seed in range(20):
        theta_L = 5.0 if seed % 2 == 0 else -5.0
        truth = truth_camera(6, seed=3000 + seed, theta_L_deg=theta_L)
        obs, _ = observe(truth, seed=4000 + seed, noise_px=0.1)
        res = calibrate(obs, "joint", options=QUIET)
        for key, true in (("theta_L_deg", theta_L), ("U_mm", float(truth.U_mm.detach())),
                          ("theta_F_deg", math.degrees(float(truth.theta_F.detach())))):
            zs.append((res.values[key] - true) / res.sigma_classical[key])
            zv.append((res.values[key] - true) / res.sigma[key])
            lines.append(f"{key} z = {zs[-1]:+.2f}")
    ok, why = _coverage_ok(zs)
    print(f"\n{why}")
    assert ok, f"errors in units of σ should be N(0, 1): {why}; {lines}"
    for factor in (2.0, 0.5):
        bad, why_bad = _coverage_ok([z / factor for z in zs])
        assert not bad, f"σ × {factor} must fail the same check: {why_bad}"
    m2 = sum(z * z for z in zv) / len(zv)
    within2 = sum(abs(z) < 2 for z in zv) / len(zv)
    assert 0.5 <= m2 <= 1.6 and within2 >= 0.9, f"the default (views) σ: mean z² {m2:.2f}, within 2σ {within2:.0%}"


# --- options and edge cases ----------------------------------------------------------------------------------

def test_principal_point_freed_when_it_is_off_centre():
    pp = (2735.5 + 15.0, 1823.5 - 10.0)
    truth = truth_camera(8, seed=5, principal_point_px=pp)
    obs, _ = observe(truth, seed=505)
    res = calibrate(obs, "unified")  # the default: fitted where the test justifies it
    got, sig = res.values["principal_point_px"], res.sigma["principal_point_px"]
    print(f"\nprincipal point {got} ± {sig} (true {pp}); test {res.model_selection['principal_point']}")
    assert all(abs(g - t) < 4 * s for g, t, s in zip(got, pp, sig)), f"pp {got} vs {pp} (σ {sig})"
    assert res.model_selection["principal_point"]["justified"] is True, "an off-centre pp must be justified"
    assert res.model_selection["principal_point"]["fitted"] is True and res.free_principal_point, \
        "and then fitted"
    assert abs(res.values["w_mm"] / W_MM - 1) < 0.003, "w still recovered"


def test_robust_loss_resists_outliers():
    truth = truth_camera(8, seed=6)
    obs, _ = observe(truth, seed=606)
    gen = torch.Generator().manual_seed(7)
    bad = torch.rand(obs.corners_px.shape[:2], generator=gen) < 0.05
    obs.corners_px[bad] += 15.0
    plain = calibrate(obs, "unified", options=QUIET)
    robust = calibrate(obs, "unified", options=FitOptions(robust="huber", model_selection=False))
    err_plain = abs(plain.values["w_mm"] / W_MM - 1)
    err_robust = abs(robust.values["w_mm"] / W_MM - 1)
    print(f"\n5 % outliers of 15 px: w error {err_plain:.3%} (least squares), {err_robust:.3%} (Huber)")
    assert err_robust < 0.003 and err_robust < err_plain, f"Huber {err_robust:.3%} vs LS {err_plain:.3%}"
    assert robust.noise["sigma_corner_px"] < 2 * NOISE_PX, f"robust noise scale {robust.noise}"


def test_missing_observations_are_ignored():
    truth = truth_camera(8, seed=8)
    obs, _ = observe(truth, seed=808)
    gen = torch.Generator().manual_seed(9)
    obs.corners_px[torch.rand(obs.corners_px.shape[:2], generator=gen) < 0.3] = float("nan")
    obs.blur_px[torch.rand(obs.blur_px.shape, generator=gen) < 0.3] = float("nan")
    res = calibrate(obs, "unified", options=QUIET)
    assert abs(res.values["w_mm"] / W_MM - 1) < 0.003 and abs(res.values["U_mm"] / U_MM - 1) < 0.005, \
        f"recovery with 30 % missing: {res.values}"
    assert sum(v["n_points"] for v in res.views) == int(obs.corner_mask.sum()), "n_points counts detections"


def test_non_convergence_is_an_error():
    truth = truth_camera(4, seed=9)
    obs, _ = observe(truth, seed=909)
    with pytest.raises(FitError, match="did not converge in 1 iterations"):
        calibrate(obs, "joint", options=FitOptions(max_iterations=1, model_selection=False))


def test_tilt_mode_needs_init():
    truth = truth_camera(3, seed=10)
    obs, _ = observe(truth, seed=1010)
    with pytest.raises(FitError, match="init"):
        calibrate(obs, "tilt")


def test_a_view_with_too_few_corners_is_skipped_and_none_left_is_an_error():
    truth = truth_camera(4, seed=11)
    obs, _ = observe(truth, seed=1111)
    obs.corners_px[1, 3:] = float("nan")
    res = calibrate(obs, "unified", options=QUIET)
    assert [s["image"] for s in res.skipped] == ["view1"], f"the 3-corner view is skipped: {res.skipped}"
    assert len(res.views) == 3, "the other three views are calibrated"
    obs.corners_px[:, 3:] = float("nan")
    with pytest.raises(FitError, match="none of the 4 views"):
        calibrate(obs, "unified", options=QUIET)


def test_focal_length_from_homographies():
    truth = truth_camera(6, seed=12)
    obs, _ = observe(truth, seed=1212)
    F = focal_from_homographies(obs)
    F_true = W_MM / PAPER_SENSOR["pixel_pitch_mm"]
    assert F is not None and abs(F / F_true - 1) < 0.01, f"focal length {F} px vs {F_true} px"
    flat = LensCamera(2, **PAPER_SENSOR, **PAPER_LENS, T_mm=[[0, 0, 600.0], [10, 0, 650.0]])
    fronto = synthesize_observations(flat, BOARD, 0.0, 0.0)
    assert focal_from_homographies(fronto) is None, "fronto-parallel views cannot give a focal length"
    with pytest.raises(FitError, match="nominal focal length"):
        calibrate(fronto, "unified", options=QUIET)


def test_mismatched_target_is_an_error():
    truth = truth_camera(4, seed=13)
    obs, _ = observe(truth, seed=1313)
    obs.points_mm[:, 1] *= 1.25  # the wrong target file: rows 25 % further apart than on the board seen
    with pytest.raises(FitError, match="no consistent solution"):
        calibrate(obs, "unified", options=FitOptions(nominal_focal_mm=50.0, model_selection=False))


def test_blur_scan_on_non_finite_geometry_raises_fit_error_not_type_error():
    """A NaN starting pose (seen from solvePnP on degenerate views) must end in a clear FitError."""
    import pytest as _pytest

    from tiltfit.calibrate.start import blur_from_scan

    p_cam = torch.full((1, 6, 3), float("nan"), dtype=torch.float64)
    blur = torch.ones(1, 6, dtype=torch.float64)
    mask = torch.ones(1, 6, dtype=torch.bool)
    with _pytest.raises(FitError, match="blur"):
        blur_from_scan(p_cam, blur, mask, 55.39, 0.00654, fit_tilt=False)
