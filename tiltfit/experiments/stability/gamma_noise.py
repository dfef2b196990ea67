"""(e) Blur measured on sRGB-encoded values instead of linear ones (bias against blur size, predicted by
`closed_forms.srgb_blur_bias`), and the stage-1 calibration error against image noise, from rendered target
photographs, detected and calibrated."""
from __future__ import annotations

import time

import numpy as np

from .closed_forms import srgb_blur_bias
from .common import D_MM, U0_MM, W_MM, StabilityConfig, Study, subplots_row
from .detectors import DETECTOR_POSES, detector_target

def srgb_bias_rows(cfg: StabilityConfig, log) -> list[dict]:
    """Blur measured on decoded (linear) and on encoded (sRGB) values, true corners, against the truth."""
    from camio.files import srgb_to_linear

    from tiltfit.detect.blur import measure_blur
    from tiltfit.experiments.synth import PAPER_CAMERA, look_at_pose, render_view, with_blur_ratio

    target = detector_target()
    base = PAPER_CAMERA.binned(12)
    pos, roll = DETECTOR_POSES[0]
    R, T = look_at_pose(target, pos, roll_deg=roll)
    rows = []
    for k, ratio in enumerate(cfg.srgb_ratios):
        cam = with_blur_ratio(base, target, R, T, ratio, U_mm=400.0)
        v = render_view(target, cam, R, T, noise_sigma=0.002, srgb8=True, seed=cfg.seed + k)
        enc = v.image_srgb8[..., 0] / 255.0
        truth = v.truth.blur_px
        b_lin, _ = measure_blur(srgb_to_linear(enc), target, v.truth.corners_px)
        b_enc, _ = measure_blur(enc, target, v.truth.corners_px)
        b = float(np.median(truth))
        row = {"blur_over_square": ratio, "blur_px": b,
               "bias_decoded": float(np.nanmedian(b_lin / truth) - 1),
               "bias_encoded": float(np.nanmedian(b_enc / truth) - 1),
               "bias_encoded_vs_decoded": float(np.nanmedian(b_enc / b_lin) - 1),
               "predicted_bias": srgb_blur_bias(b)}
        rows.append(row)
        log(f"(e) sRGB: blur {b:.2f} px: bias decoded {100 * row['bias_decoded']:+.2f} %, on sRGB values "
            f"{100 * row['bias_encoded']:+.2f} % (predicted {100 * row['predicted_bias']:+.2f} %)")
    return rows


def _expose(clean: np.ndarray, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """(H, W) clean linear image -> (H, W) uint8 sRGB photograph with Gaussian noise σ (linear units): the one
    sensor model, `renderer.cameras.sensor`."""
    from renderer.cameras.sensor import SensorResponse

    return SensorResponse(read_noise=sigma, encoding="srgb8").expose(clean, rng)


def _calibrate_photos(photos8, decode: bool, target, size, pitch):
    """Detect the target in 8-bit photographs (decoded to linear, or mistakenly not) and run stage 1.

    Returns (FitResult or None, views used, message)."""
    from camio.files import srgb_to_linear

    from tiltfit.detect.chessboard import detect
    from tiltfit.calibrate.fit import FitError, FitOptions
    from tiltfit.calibrate.flow import calibrate
    from tiltfit.calibrate.model import Observations
    from ..reproduce import MIN_CORNER_FRACTION

    corners, blur = [], []
    for p in photos8:
        img = p / 255.0
        det = detect(srgb_to_linear(img) if decode else img, target)
        if det.grid_found and det.found.sum() >= MIN_CORNER_FRACTION * target.n_points:
            corners.append(det.corners_px)
            blur.append(det.blur_px)
    if len(corners) < 2:
        return None, len(corners), "fewer than two views with the board found"
    obs = Observations(target.feature_points(), np.stack(corners), np.stack(blur), size, pitch)
    try:
        return calibrate(obs, "unified", options=FitOptions(model_selection=False, nominal_focal_mm=55.0)), \
            len(corners), ""
    except FitError as e:
        return None, len(corners), str(e)
    except (ValueError, TypeError, RuntimeError) as e:  # a crash inside the fit is a finding too: record it
        return None, len(corners), f"the fit crashed: {type(e).__name__}: {e}"


def _noise_rows(cfg: StabilityConfig, log) -> list[dict]:
    """Stage-1 calibration error against image noise (and with blur read off sRGB values, at one level)."""
    from tiltfit.experiments import reproduce
    from renderer import Lens

    from tiltfit.experiments.synth import render_view

    target = reproduce.calibration_target(reproduce.SetValues())
    cam = Lens.paper().binned(cfg.noise_downscale)
    clean = []
    for v in reproduce.TARGET_VIEWS[:cfg.noise_views]:
        R, T = reproduce.target_pose(target, *v)
        clean.append(render_view(target, cam, R, T).clean.astype(np.float64))
    mistake_level = cfg.noise_levels[0]
    runs = [(s, True) for s in cfg.noise_levels] + [(mistake_level, False)]
    rows = []
    for k, (sigma, decode) in enumerate(runs):
        rng = np.random.default_rng(cfg.seed + 1000 + cfg.noise_levels.index(sigma))
        photos = [_expose(c, sigma, rng) for c in clean]
        t = time.perf_counter()
        res, n_views, msg = _calibrate_photos(photos, decode, target, cam.sensor.size_px, cam.sensor.pixel_pitch)
        row = {"noise_sigma": sigma, "blur_read_on": "linear" if decode else "sRGB values (mistake)",
               "contrast_to_noise": (0.8 - 0.05) / sigma if sigma > 0 else None, "views_used": n_views}
        if res is None:
            row.update(w_error_mm=None, U_error_mm=None, d_error_mm=None, w_sigma_mm=None, U_sigma_mm=None,
                       d_sigma_mm=None, rms_reprojection_px=None, rms_blur_px=None, failure=msg)
        else:
            v, s = res.values, res.sigma
            row.update(w_error_mm=v["w_mm"] - W_MM, U_error_mm=v["U_mm"] - U0_MM, d_error_mm=v["d_mm"] - D_MM,
                       w_sigma_mm=s["w_mm"], U_sigma_mm=s["U_mm"], d_sigma_mm=s["d_mm"],
                       rms_reprojection_px=float(np.mean([x["rms_reprojection_px"] for x in res.views])),
                       rms_blur_px=float(np.mean([x["rms_blur_px"] for x in res.views])), failure="")
        rows.append(row)
        log(f"(e) noise σ {sigma:g}, blur on {row['blur_read_on']}: {n_views} views, "
            + (f"failed: {msg}" if res is None else
               f"w {row['w_error_mm']:+.3f} ± {row['w_sigma_mm']:.3f}, U {row['U_error_mm']:+.2f} ± "
               f"{row['U_sigma_mm']:.2f}, d {row['d_error_mm']:+.3f} ± {row['d_sigma_mm']:.3f} mm")
            + f" ({time.perf_counter() - t:.1f} s)")
    return rows


def study_gamma_noise(cfg: StabilityConfig, log) -> Study:
    """(e) The sRGB mistake in blur measurement, and calibration error against image noise."""
    t0 = time.perf_counter()
    srgb = srgb_bias_rows(cfg, log)
    noise = _noise_rows(cfg, log)
    findings = _srgb_findings(srgb) + _noise_findings(cfg, noise)
    fig = _gamma_noise_figure(srgb, noise)
    return Study("gamma_noise", "(e) Gamma mistakes and image noise", srgb, findings,
                 {"srgb": srgb, "noise": noise, "truth": {"w_mm": W_MM, "U_mm": U0_MM, "d_mm": D_MM}}, fig,
                 time.perf_counter() - t0)


def _srgb_findings(srgb: list) -> list:
    """What the sRGB sweep shows: the bias of blur read off sRGB values against the disc model's prediction and
    against the truth."""
    findings = []
    small = min(srgb, key=lambda r: r["blur_px"])
    large = max(srgb, key=lambda r: r["blur_px"])
    worst = max(srgb, key=lambda r: abs(r["bias_decoded"]))
    small = min((r for r in srgb if r["blur_px"] >= 1.0), key=lambda r: r["blur_px"], default=small)
    gap = max(abs(r["bias_encoded_vs_decoded"] - r["predicted_bias"]) for r in srgb if r["blur_px"] >= 1.0) \
        if any(r["blur_px"] >= 1.0 for r in srgb) else float("nan")
    findings.append(
        f"Blur read off sRGB-encoded values instead of linear ones is biased upwards at pixel-sized blur and "
        f"slightly downwards at large blur, as the disc edge model predicts: relative to the decoded measurement "
        f"{100 * small['bias_encoded_vs_decoded']:+.1f} % at {small['blur_px']:.2f} px (predicted "
        f"{100 * small['predicted_bias']:+.1f} %) and {100 * large['bias_encoded_vs_decoded']:+.2f} % at "
        f"{large['blur_px']:.1f} px (predicted {100 * large['predicted_bias']:+.2f} %); the largest gap from the "
        f"prediction for blur ≥ 1 px is {100 * gap:.2f} percentage points.")
    findings.append(
        f"Against the truth: on sRGB values {100 * small['bias_encoded']:+.1f} % at {small['blur_px']:.2f} px and "
        f"{100 * large['bias_encoded']:+.2f} % at {large['blur_px']:.1f} px; decoded, the largest bias is "
        f"{100 * worst['bias_decoded']:+.1f} % ({worst['bias_decoded'] * worst['blur_px']:+.3f} px) at "
        f"{worst['blur_px']:.2f} px.")
    return findings


def _noise_findings(cfg: StabilityConfig, noise: list) -> list:
    """What the noise sweep shows: stage-1 errors against image noise, failures, and the sRGB mistake's effect."""
    findings = []
    good = [r for r in noise if r["blur_read_on"] == "linear" and r["w_error_mm"] is not None]
    failed = [r for r in noise if r["blur_read_on"] == "linear" and r["w_error_mm"] is None]
    if good:
        lo_r, hi_r = good[0], good[-1]
        findings.append(
            f"Stage-1 calibration against image noise ({cfg.noise_views} views, "
            f"{_sensor_px(cfg.noise_downscale)}): at σ = {lo_r['noise_sigma']:g} the errors are w "
            f"{lo_r['w_error_mm']:+.3f}, U {lo_r['U_error_mm']:+.2f}, d {lo_r['d_error_mm']:+.3f} mm; at σ = "
            f"{hi_r['noise_sigma']:g} (contrast/noise {hi_r['contrast_to_noise']:.0f}) w {hi_r['w_error_mm']:+.3f} "
            f"± {hi_r['w_sigma_mm']:.3f}, U {hi_r['U_error_mm']:+.2f} ± {hi_r['U_sigma_mm']:.2f}, d "
            f"{hi_r['d_error_mm']:+.3f} ± {hi_r['d_sigma_mm']:.3f} mm (errors of "
            f"{abs(hi_r['w_error_mm']) / hi_r['w_sigma_mm']:.1f}, {abs(hi_r['U_error_mm']) / hi_r['U_sigma_mm']:.1f} "
            f"and {abs(hi_r['d_error_mm']) / hi_r['d_sigma_mm']:.1f} of the fit's one-σ).")
    if failed:
        findings.append("The calibration fails at σ = " + ", ".join(f"{r['noise_sigma']:g} ({r['failure']})"
                                                                     for r in failed) + ".")
    mistake = next((r for r in noise if r["blur_read_on"] != "linear"), None)
    ref = next((r for r in good if r["noise_sigma"] == (mistake or {}).get("noise_sigma")), None)
    if mistake is not None and mistake["w_error_mm"] is not None and ref is not None:
        findings.append(
            f"With the blur read off sRGB values (σ = {mistake['noise_sigma']:g}) stage 1 returns d "
            f"{mistake['d_error_mm']:+.3f} mm and U {mistake['U_error_mm']:+.2f} mm from the truth, against "
            f"{ref['d_error_mm']:+.3f} and {ref['U_error_mm']:+.2f} mm when decoded.")
    elif mistake is not None:
        findings.append(f"With the blur read off sRGB values stage 1 fails: {mistake['failure']}.")
    return findings


def _gamma_noise_figure(srgb: list, noise: list):
    """Blur bias against blur diameter, and the stage-1 relative errors against noise."""
    good = [r for r in noise if r["blur_read_on"] == "linear" and r["w_error_mm"] is not None]
    fig, (ax1, ax2) = subplots_row(2)
    b = [r["blur_px"] for r in srgb]
    fine = np.geomspace(min(min(b), 0.7), max(max(b), 12.0), 24)
    ax1.plot(fine, [100 * srgb_blur_bias(x) for x in fine], "-", color="tab:red", lw=1, label="predicted (disc model)")
    ax1.plot(b, [100 * r["bias_encoded_vs_decoded"] for r in srgb], "o", color="tab:red", mfc="none",
             label="on sRGB values, vs decoded")
    ax1.plot(b, [100 * r["bias_encoded"] for r in srgb], "x", color="tab:red", label="on sRGB values, vs truth")
    ax1.plot(b, [100 * r["bias_decoded"] for r in srgb], "s", color="tab:blue", ms=4, label="decoded, vs truth")
    ax1.axhline(0, color="k", lw=0.6)
    ax1.set_xscale("log")
    ax1.set_xlabel("blur diameter [px]")
    ax1.set_ylabel("median blur bias [%]")
    ax1.legend(fontsize="x-small")
    if good:
        s = [r["noise_sigma"] for r in good]
        for key, true, lab in (("w", W_MM, "w"), ("U", U0_MM, "U"), ("d", D_MM, "d")):
            ax2.errorbar(s, [100 * abs(r[f"{key}_error_mm"]) / true for r in good],
                         yerr=[100 * r[f"{key}_sigma_mm"] / true for r in good], fmt="o-", ms=4, capsize=2,
                         label=f"|{lab} error| (bars: fit's one-σ)")
        ax2.set_xscale("log")
        ax2.set_yscale("log")
    ax2.set_xlabel("noise σ (linear units; white − dark = 0.75)")
    from matplotlib.ticker import NullFormatter

    ax2.xaxis.set_minor_formatter(NullFormatter())
    ax2.set_ylabel("relative error [%]")
    ax2.legend(fontsize="x-small")
    for ax in (ax1, ax2):
        ax.grid(alpha=0.3, which="both")
    fig.suptitle("(e) gamma mistake in the blur, and calibration against noise", fontsize="medium")
    return fig


def _sensor_px(downscale: int) -> str:
    """'W×H px' of the EOS 6D sensor binned by `downscale`."""
    from ..scenes import EOS_6D

    w, h = EOS_6D.binned(downscale).size_px
    return f"{w}×{h} px"
