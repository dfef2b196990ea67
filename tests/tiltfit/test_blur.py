"""Blur-disc diameters from edge profiles: the model, accuracy on synthetic images, and why sRGB must be decoded."""
import math

import numpy as np
import pytest
import torch

from camio.files import srgb_to_linear
from tiltfit.detect.blur import measure_blur, pixel_esf

from tiltfit.experiments.synth import PAPER_CAMERA, look_at_pose, projected_square_px, render_view, with_blur_ratio
from tiltfit.target.design import design_target

torch.set_num_threads(1)

CAM = PAPER_CAMERA.binned(12)  # 456 × 304 px
TARGET = design_target(9, 6, 20.0, w_mm=55.39, distance_mm=650.0, inclination_deg=20.0)
POSE = look_at_pose(TARGET, (40.0, -30.0, -650.0), roll_deg=10.0)  # edges slanted: sub-pixel phases vary


def tolerance(b):
    return np.maximum(0.05 * b, 0.3)


# --- the edge model ----------------------------------------------------------------------------------------
def _esf_brute(d, r, alpha, n=400):
    """Disc-segment area fraction averaged over a unit pixel whose centre is d from an edge at angle alpha."""
    o = (np.arange(n) + 0.5) / n - 0.5
    ox, oy = np.meshgrid(o, o)
    s = d + ox * math.cos(alpha) + oy * math.sin(alpha)
    u = np.clip(s / r, -1, 1)
    return float(np.mean(0.5 + (u * np.sqrt(1 - u * u) + np.arcsin(u)) / math.pi))


@pytest.mark.parametrize("r, alpha", [(0.05, 0.0), (0.7, 0.3), (2.5, 0.785), (6.0, 1.2)])
def test_pixel_esf_matches_brute_force_integration(r, alpha):
    d = torch.linspace(-r - 1.5, r + 1.5, 13, dtype=torch.float64)
    wa, wb = max(abs(math.cos(alpha)), abs(math.sin(alpha))), min(abs(math.cos(alpha)), abs(math.sin(alpha)))
    E = pixel_esf(d, torch.tensor(r, dtype=torch.float64), torch.tensor(wa, dtype=torch.float64),
                  torch.tensor(wb, dtype=torch.float64))
    ref = np.array([_esf_brute(float(x), r, alpha) for x in d])
    assert np.abs(E.numpy() - ref).max() < 2e-3, f"pixel ESF off by {np.abs(E.numpy() - ref).max():.4f}"


def test_pixel_esf_symmetry_and_derivatives():
    d = torch.linspace(-4, 4, 41, dtype=torch.float64)
    r, wa, wb = (torch.tensor(v, dtype=torch.float64) for v in (2.0, 0.9, 0.4))
    E, dEd, dEr = pixel_esf(d, r, wa, wb, with_derivatives=True)
    Em = pixel_esf(-d, r, wa, wb)
    assert torch.allclose(E + Em, torch.ones_like(E), atol=1e-12), "E(d) + E(−d) must be 1"
    h = 1e-6
    num_d = (pixel_esf(d + h, r, wa, wb) - pixel_esf(d - h, r, wa, wb)) / (2 * h)
    num_r = (pixel_esf(d, r + h, wa, wb) - pixel_esf(d, r - h, wa, wb)) / (2 * h)
    assert torch.allclose(dEd, num_d, atol=1e-6) and torch.allclose(dEr, num_r, atol=1e-6), "analytic derivatives"


# --- accuracy on images ------------------------------------------------------------------------------------
def _view(ratio, noise, seed=0, pose=POSE, U_mm=400.0):
    cam = with_blur_ratio(CAM, TARGET, *pose, ratio, U_mm=U_mm)
    return render_view(TARGET, cam, *pose, noise_sigma=noise, srgb8=True, seed=seed)


@pytest.mark.parametrize("ratio, noise", [(0.05, 0.002), (0.15, 0.002), (0.4, 0.002), (0.15, 0.01), (0.4, 0.01)])
def test_blur_within_5_percent_or_03_px(ratio, noise):
    v = _view(ratio, noise, seed=1)
    truth = v.truth.blur_px
    b, sb = measure_blur(v.image[..., 0], TARGET, v.truth.corners_px)
    err = b - truth
    assert np.isfinite(b).all(), f"{np.isnan(b).sum()} points without blur"
    bad = np.abs(err) > tolerance(truth)
    assert not bad.any(), (f"blur ~{np.median(truth):.2f} px, noise {noise}: {bad.sum()} points outside "
                           f"max(5 %, 0.3 px), worst error {np.abs(err).max():.3f} px")
    z = err / sb
    zr = float(np.sqrt(np.mean(z ** 2)))
    assert 0.3 < zr < 3.0, f"uncertainties do not describe the errors: RMS of error / sigma = {zr:.2f}"


def test_blur_across_the_plane_of_focus():
    R, T = look_at_pose(TARGET, (60.0, -400.0, -450.0), roll_deg=8.0)
    cam = CAM.with_(d=50.0)
    v = render_view(TARGET, cam, R, T, noise_sigma=0.004, srgb8=True, seed=2)
    b, _ = measure_blur(v.image[..., 0], TARGET, v.truth.corners_px)
    err = np.abs(b - v.truth.blur_px)
    assert (err <= tolerance(v.truth.blur_px)).all(), f"worst blur error {err.max():.3f} px across the focus"


@pytest.mark.slow
def test_blur_08_of_the_square():
    v = _view(0.8, 0.004, seed=3)
    sq = np.median(projected_square_px(TARGET, CAM, *POSE))
    b, _ = measure_blur(v.image[..., 0], TARGET, v.truth.corners_px)
    rel = np.abs(b / v.truth.blur_px - 1)
    assert np.median(v.truth.blur_px) > 0.75 * sq, "the view should have blur 0.8 of the square"
    assert np.isfinite(b).mean() > 0.9 and np.nanmax(rel) < 0.05, f"worst relative blur error {np.nanmax(rel):.3f}"


def test_measuring_on_srgb_values_biases_the_blur():
    """The disc model holds for linear intensities; on sRGB-encoded values the profile is bent and b grows."""
    v = _view(0.07, 0.002, seed=4)  # blur about 1.5 px
    truth = v.truth.blur_px
    b_lin, _ = measure_blur(srgb_to_linear(v.image_srgb8[..., 0] / 255.0), TARGET, v.truth.corners_px)
    b_enc, _ = measure_blur(v.image_srgb8[..., 0] / 255.0, TARGET, v.truth.corners_px)
    bias_lin = np.median(b_lin / truth) - 1
    bias_enc = np.median(b_enc / truth) - 1
    assert abs(bias_lin) < 0.02, f"decoded: median bias {bias_lin:+.3f}"
    assert bias_enc > 0.04, f"encoded values should overestimate b by several %, got {bias_enc:+.3f}"
