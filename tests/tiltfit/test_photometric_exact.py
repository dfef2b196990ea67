"""The photometric fit against captures of an independent generator (`tiltfit.experiments.exact_capture`: every ray
traced through the tilted thin lens, stratified aperture and pixel-area samples, no closed form of the blur).

- the forward model, at the generator's true lens and pose, agrees with its capture pixel by pixel within the
  capture's own noise, and the mismatch it leaves would move d by less than the noise does;
- the refinement, started from the corner fit of such captures, is kept and lands within its σ of the truth.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tiltfit.experiments import exact_capture as ec
from tiltfit.target.layout import Target

BOARD = Target(tuple(20.0 * i for i in range(5)), tuple(20.0 * j for j in range(4)), (0, 0), 12.0)
LOOK = ec.Board()


def _model_camera(truth: dict, R, T, W: int, H: int, pitch: float, **change):
    from renderer.cameras import ThinLensCamera
    from renderer.cameras.lens import Lens, Sensor

    p = {"w": truth["w_mm"], "U": truth["U_mm"], "d": truth["d_mm"], "theta_F": math.radians(truth["theta_F_deg"])}
    p.update(change)
    lens = Lens(p["w"], p["U"], p["d"], p["theta_F"], sensor=Sensor(W, H, pitch))
    return ThinLensCamera.from_calibration(lens, torch.tensor(R), torch.tensor(T))


def test_exact_capture_truth_matches_the_calibrations_lens_relations():
    """The generator's truth (from conjugate points of a physical lens) obeys the project's thin-lens relations:
    f = U w cos θL / (U + w) and tan θF = (U + w) tan θL / w; an untilted lens has θF 0 and U from 1/f = 1/w + 1/U."""
    for tilt in (-5.0, 0.0, 3.0):
        t = ec.ExactLens.focused_at(50.0, 700.0, 20.0, tilt, 64, 48, 0.2).truth()
        a, w, U = math.radians(tilt), t["w_mm"], t["U_mm"]
        assert t["f_mm"] == pytest.approx(U * w * math.cos(a) / (U + w), rel=1e-12), f"f at tilt {tilt}: {t}"
        assert math.tan(math.radians(t["theta_F_deg"])) == pytest.approx((U + w) * math.tan(a) / w, abs=1e-12), \
            f"θF at tilt {tilt}: {t}"
        if tilt == 0.0:
            assert U == pytest.approx(700.0, rel=1e-12) and t["theta_F_deg"] == 0.0, t


def _forward_case(blur_px: float, tilt_deg: float, rx_deg: float):
    W, H, pitch, w, dist, d = 64, 48, 0.2, 50.0, 720.0, 20.0
    U0 = 1.0 / (1.0 / dist + blur_px * pitch / (w * d))
    lens = ec.ExactLens.focused_at(w, U0, d, tilt_deg, W, H, pitch)
    R, T = ec.pose_facing(BOARD, rx_deg, 10.0, dist)
    rad = [ec.radiance(lens, R, T, BOARD, LOOK, aperture_strata=8, pixel_strata=4, seed=s) for s in (0, 1)]
    D = [((LOOK.paper - r) / (LOOK.paper - LOOK.ink)).reshape(-1) for r in rad]
    return lens.truth(), R, T, (W, H, pitch), D


def _implied_d(cam_fn, truth, uv, r, near, rel=1e-3) -> float:
    """Relative change of d (%) that best explains r = model − capture, by the model's own derivative."""
    from tiltfit.photometric import dark_fraction_disc

    with torch.no_grad():
        J = (dark_fraction_disc(BOARD, cam_fn(d=truth["d_mm"] * (1 + rel)), uv, near)
             - dark_fraction_disc(BOARD, cam_fn(d=truth["d_mm"] * (1 - rel)), uv, near)).numpy() / (2 * rel)
    return float(-100.0 * (J @ r) / (J @ J))


@pytest.mark.parametrize("blur_px, tilt_deg, rx_deg", [(1.5, 0.0, 0.0), (6.0, 5.0, 20.0)])
def test_forward_model_agrees_with_exact_tracing_within_noise(blur_px, tilt_deg, rx_deg):
    """Closed-form aperture, 4 x 4 points per pixel: mean and RMS of model − capture on the usable edge pixels
    within the capture's noise, and the d that would explain the difference within ±0.6 % (the midpoint rule's
    pixels, narrower than the box, made it +1.5 % at 1.5 px; the capture's own noise moves it by about 0.15 %)."""
    from tiltfit.photometric import dark_fraction_disc
    from tiltfit.photometric.render import usable_pixels

    truth, R, T, (W, H, pitch), D = _forward_case(blur_px, tilt_deg, rx_deg)
    cam_fn = lambda **c: _model_camera(truth, R, T, W, H, pitch, **c)  # noqa: E731
    cam = cam_fn()
    flat = torch.arange(W * H)
    uv = torch.stack([(flat % W).to(torch.float64), (flat // W).to(torch.float64)], -1)
    capture = 0.5 * (D[0] + D[1])
    edge = usable_pixels(BOARD, cam, uv) & (capture > 0.03) & (capture < 0.97)
    assert edge.sum() > 150, f"only {edge.sum()} usable edge pixels"
    near = max(len(BOARD.x_edges), len(BOARD.y_edges))
    with torch.no_grad():
        model = dark_fraction_disc(BOARD, cam, uv[torch.from_numpy(edge)], near).numpy()
    r = model - capture[edge]
    noise = float(np.sqrt(((D[0] - D[1])[edge] ** 2).mean() / 2)) / math.sqrt(2)   # of the two seeds' mean
    rms = float(np.sqrt((r ** 2).mean()))
    assert rms < 1.3 * noise, f"RMS {rms:.5f} against the capture's noise {noise:.5f}"
    assert abs(r.mean()) < 4 * noise / math.sqrt(edge.sum()) + 5e-4, f"mean {r.mean():+.5f} (noise {noise:.5f})"
    shift = _implied_d(cam_fn, truth, uv[torch.from_numpy(edge)], r, near)
    assert abs(shift) < 0.6, f"the mismatch would move d by {shift:+.3f} %"


def test_closed_form_pixel_quadrature_below_3px():
    """The closed form's pixel box is a grid of points; at a 1.5 px blur disc 4 x 4 points make the edges wider
    than the box does (a fit would take d −0.40 % on a facing board, −0.34 % inclined 30° x 30°: the mismatch exact
    tracing showed). The fit's choice (`closed_form_subpixels`: 8 x 8 below 3 px) stays within 0.12 % of a 32 x 32
    grid on both. No generator noise: the reference is the same closed form, exact over the aperture."""
    blur_px = 1.5
    from tiltfit.photometric.render import closed_form_subpixels, dark_fraction_disc, usable_pixels

    W, H, pitch, w, dist, d = 64, 48, 0.2, 50.0, 720.0, 20.0
    lens = ec.ExactLens.focused_at(w, 1.0 / (1.0 / dist + blur_px * pitch / (w * d)), d, 0.0, W, H, pitch)
    n = closed_form_subpixels(blur_px)
    assert n == 8, f"{n} points a side at {blur_px} px"
    for rx, ry in ((0.0, 10.0), (30.0, 30.0)):
        R, T = ec.pose_facing(BOARD, rx, ry, dist)
        truth = lens.truth()
        cam_fn = lambda **c: _model_camera(truth, R, T, W, H, pitch, **c)  # noqa: E731
        cam = cam_fn()
        flat = torch.arange(W * H)
        uv = torch.stack([(flat % W).to(torch.float64), (flat // W).to(torch.float64)], -1)
        uv = uv[torch.from_numpy(usable_pixels(BOARD, cam, uv))]
        with torch.no_grad():
            ref = dark_fraction_disc(BOARD, cam, uv, 5, 32).numpy()
            edge = torch.from_numpy((ref > 0.03) & (ref < 0.97))
            uv, ref = uv[edge], ref[edge.numpy()]
            J = (dark_fraction_disc(BOARD, cam_fn(d=d * 1.001), uv, 5, 32)
                 - dark_fraction_disc(BOARD, cam_fn(d=d * 0.999), uv, 5, 32)).numpy() / 0.002
            shifts = {}
            for sub in (4, n):
                r = dark_fraction_disc(BOARD, cam, uv, 5, sub).numpy() - ref
                shifts[sub] = float(-100.0 * (J @ r) / (J @ J))
        assert abs(shifts[n]) < 0.12, f"{blur_px} px, board ({rx}, {ry}): {n}x{n} points would move d {shifts}"
        assert shifts[4] < -0.2, f"negative control: 4 x 4 points no longer biased at {blur_px} px: {shifts}"


# ------------------------------------------------------------------------------------------ the refinement

FIT_BOARD = Target(tuple(50.0 * i for i in range(7)), tuple(50.0 * j for j in range(5)), (0, 0), 25.0)
FIT_VIEWS = ((20.0, 5.0, 780.0), (-15.0, 15.0, 820.0), (-10.0, -10.0, 800.0))


@pytest.fixture(scope="module")
def tilted_fit():
    """Three exact captures (240 x 160, lens tilted +5°, 8-bit sRGB with shot and read noise), the corner fit
    (tiltfit's detector and joint fit) and the refinement started from it."""
    from camio.files import srgb_to_linear
    from tiltfit.calibrate.flow import calibrate
    from tiltfit.detect.chessboard import detect
    from tiltfit.calibrate.fit import FitOptions
    from tiltfit.calibrate.model import Observations
    from tiltfit.photometric import PhotometricOptions, refine_photometric

    W, H, pitch = 240, 160, 0.13
    lens = ec.ExactLens.focused_at(55.0, 760.0, 40.0, 5.0, W, H, pitch)
    linear = []
    for k, (rx, ry, dist) in enumerate(FIT_VIEWS):
        R, T = ec.pose_facing(FIT_BOARD, rx, ry, dist)
        img = ec.capture(lens, R, T, FIT_BOARD, seed=k, aperture_strata=6, pixel_strata=3)
        linear.append(srgb_to_linear(img / 255.0))
    dets = [detect(im, FIT_BOARD) for im in linear]
    assert min(int(d.found.sum()) for d in dets) == FIT_BOARD.n_points, "corners not found: no corner fit to start"
    obs = Observations(FIT_BOARD.feature_points(), np.stack([d.corners_px for d in dets]),
                       np.stack([d.blur_px for d in dets]), (W, H), pitch)
    corner = calibrate(obs, "joint", options=FitOptions(model_selection=False, nominal_focal_mm=55.0))
    res = refine_photometric(linear, FIT_BOARD, corner.camera, PhotometricOptions(max_pixels=800),
                             start_sigma=corner.sigma, corners=obs)
    return lens.truth(), corner, res


@pytest.mark.slow
def test_refinement_of_exact_captures_is_kept_and_within_sigma(tilted_fit):
    truth, corner, res = tilted_fit
    report = "; ".join(f"{k}: truth {truth[k]:.4f}, corners {corner.values[k] - truth[k]:+.4f} "
                       f"(σ {corner.sigma[k]:.4f}), photometric {res.values[k] - truth[k]:+.4f} (σ {res.sigma[k]:.4f})"
                       for k in ("theta_L_deg", "theta_F_deg", "d_mm", "U_mm"))
    assert res.kept == "photometric", f"not kept ({res.rejected_because}): {report}"
    for k in ("theta_L_deg", "theta_F_deg", "d_mm"):
        err, s = res.values[k] - truth[k], res.sigma[k]
        assert 0 < s < corner.sigma[k], f"{k}: σ {s} against the corner fit's {corner.sigma[k]}: {report}"
        assert abs(err) <= 2.5 * s, f"{k} off by {err:+.4f} ({err / s:+.1f}σ): {report}"


@pytest.mark.slow
def test_bound_record_says_which_parameter_is_where(tilted_fit):
    """Each bounded lens parameter's record holds its start inside its bound, the refined value inside it too,
    and `at_bound` exactly where the refined value reached 95 % of the way to an end."""
    truth, corner, res = tilted_fit
    names = {b["parameter"] for b in res.bounds}
    assert {"w_mm", "d_mm", "theta_F_deg"} <= names, f"bounds for {names}"
    for b in res.bounds:
        assert b["low"] < b["start"] < b["high"], b
        assert b["low"] <= b["refined"] <= b["high"], b
        assert b["at_bound"] == (b["parameter"] in {e for e in res.at_bound} or
                                 {"w_mm": "log_w_mm", "U_mm": "inv_U_per_m", "d_mm": "d_scaled",
                                  "theta_F_deg": "theta_F"}[b["parameter"]] in res.at_bound), b
    from tiltfit.report.photometric import photometric_lines

    lines = "\n".join(photometric_lines({"photometric": {"kept": res.kept, "bounds": res.bounds,
                                                         "rejected_because": res.rejected_because}}))
    assert all(b["parameter"] in lines for b in res.bounds), lines


def test_residual_image_of_the_truth_is_noise(tmp_path):
    """At the generator's truth the residual image (photo − rendered board) is the capture's noise on the usable
    pixels and NaN elsewhere; with d 10 % off it shows the edges (a negative control); it plots to a PNG."""
    from tiltfit.photometric import residual_image
    from tiltfit.report.photometric import plot_residual_image

    truth, R, T, (W, H, pitch), D = _forward_case(6.0, 5.0, 20.0)
    photo = (LOOK.paper - (LOOK.paper - LOOK.ink) * D[0]).reshape(H, W)
    res = residual_image(photo, BOARD, _model_camera(truth, R, T, W, H, pitch), LOOK.paper, LOOK.ink)
    finite = np.isfinite(res)
    noise = float(np.sqrt(np.mean((D[0] - D[1]).reshape(H, W)[finite] ** 2) / 2)) * (LOOK.paper - LOOK.ink)
    assert 300 < finite.sum() < W * H, f"{finite.sum()} usable pixels of {W * H}"
    rms = float(np.sqrt(np.mean(res[finite] ** 2)))
    assert rms < 1.5 * noise, f"residual RMS {rms:.5f} at the truth, noise {noise:.5f}"
    off = residual_image(photo, BOARD, _model_camera(truth, R, T, W, H, pitch, d=1.1 * truth["d_mm"]),
                         LOOK.paper, LOOK.ink)
    rms_off = float(np.sqrt(np.nanmean(off ** 2)))
    assert rms_off > 1.5 * rms, f"d 10 % off: RMS {rms_off:.5f}, at the truth {rms:.5f}"
    path = plot_residual_image(res, str(tmp_path / "residual.png"))
    assert (tmp_path / "residual.png").stat().st_size > 1000, path


def test_chi2_quantile_of_the_corner_check():
    """The corner check's χ² quantiles against the tables (0.99: 6.635 for 1, 13.277 for 4 degrees of freedom)."""
    from tiltfit.photometric.checks import _chi2_quantile

    assert _chi2_quantile(0.99, 1) == pytest.approx(6.6349, abs=1e-3), _chi2_quantile(0.99, 1)
    assert _chi2_quantile(0.99, 4) == pytest.approx(13.2767, abs=1e-3), _chi2_quantile(0.99, 4)
    assert _chi2_quantile(0.5, 2) == pytest.approx(2 * math.log(2), abs=1e-6), _chi2_quantile(0.5, 2)


@pytest.mark.slow
def test_heavy_blur_two_views_refinement_is_kept():
    """Two exact captures under heavy blur (d 36 mm, blur discs about 10 px, untilted): the corners are few (2 x 15)
    and the corner fit's own RMS on them is in sample, so the refinement one corner-fit σ away costs a few % more
    there. It was rejected for it (0.0210 px against a limit of 1.02 x 0.0203 px) though nearer the truth; the
    corner check now allows the χ² rise of its free lens parameters. Kept, and w, U, d within 2.5 of its σ."""
    from camio.files import srgb_to_linear
    from tiltfit.calibrate.flow import calibrate
    from tiltfit.detect.chessboard import detect
    from tiltfit.calibrate.fit import FitOptions
    from tiltfit.calibrate.model import Observations
    from tiltfit.photometric import PhotometricOptions, refine_photometric

    W, H, pitch = 240, 160, 0.13
    lens = ec.ExactLens.focused_at(55.0, 620.0, 36.0, 0.0, W, H, pitch)
    linear = []
    for k, (rx, ry, dist) in enumerate(((25.0, 10.0, 760.0), (-20.0, -15.0, 860.0))):
        R, T = ec.pose_facing(FIT_BOARD, rx, ry, dist)
        linear.append(srgb_to_linear(ec.capture(lens, R, T, FIT_BOARD, seed=k, aperture_strata=6,
                                                pixel_strata=2) / 255.0))
    dets = [detect(im, FIT_BOARD) for im in linear]
    assert min(int(d.found.sum()) for d in dets) == FIT_BOARD.n_points, "corners not found"
    obs = Observations(FIT_BOARD.feature_points(), np.stack([d.corners_px for d in dets]),
                       np.stack([d.blur_px for d in dets]), (W, H), pitch)
    corner = calibrate(obs, "joint", options=FitOptions(distortion="none", nominal_focal_mm=55.0))
    res = refine_photometric(linear, FIT_BOARD, corner.camera, PhotometricOptions(lens_samples=0, max_pixels=2000),
                             start_sigma=corner.sigma, corners=obs, start_covariance=corner.intrinsics_covariance)
    truth = lens.truth()
    report = "; ".join(f"{k}: corners {corner.values[k] - truth[k]:+.4f} (σ {corner.sigma[k]:.4f}), photometric "
                       f"{res.values[k] - truth[k]:+.4f} (σ {res.sigma[k]:.4f})" for k in ("w_mm", "U_mm", "d_mm"))
    cc = res.corner_check
    assert res.kept == "photometric", f"not kept ({res.rejected_because}): {report}"
    assert not cc["start_is_held_out"] and cc["start_px"] < cc["refined_px"] <= cc["limit_px"], \
        f"the in-sample corner check: {cc}"
    for k in ("w_mm", "U_mm", "d_mm"):
        err, s = res.values[k] - truth[k], res.sigma[k]
        assert abs(err) <= 2.5 * s, f"{k} off by {err:+.4f} ({err / s:+.1f}σ): {report}"
