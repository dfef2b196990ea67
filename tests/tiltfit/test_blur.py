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


# --- the band model's normal equations --------------------------------------------------------------------
def _synthetic_bands(rng, bands_per_point=(4, 3, 4), img_shape=(40, 60)):
    """Random bands (the dicts `_half_edges` returns) with far edges within a few pixels, and an image to read."""
    img = rng.uniform(0.0, 1.0, img_shape)
    groups = []
    for n_bands in bands_per_point:
        group = []
        for _ in range(n_bands):
            n = int(rng.integers(20, 60))
            alpha = rng.uniform(0, math.pi)
            group.append(dict(px=np.stack([rng.integers(0, img_shape[1], n), rng.integers(0, img_shape[0], n)], 1),
                              w=rng.uniform(0.2, 1.0, n), d0=rng.uniform(-5, 5, n), d_lo=rng.uniform(-6, 9, n),
                              d_hi=rng.uniform(-6, 9, n), dxy=rng.uniform(-12, 12, (n, 2)),
                              kappa=[float(k) for k in rng.integers(0, 2, 4)],
                              wa=max(abs(math.cos(alpha)), abs(math.sin(alpha))),
                              wb=min(abs(math.cos(alpha)), abs(math.sin(alpha)))))
        groups.append(group)
    return img, groups


def _dense_normal(img, groups, theta, prior):
    """Cost, JᵀJ and Jᵀr of `fit_corners`' model written pixel by pixel (every edge through `pixel_esf`, no
    selection of the pixels the blur reaches), for the points' parameters theta (C, P)."""
    B = max(len(g) for g in groups)
    P = 3 + 3 * B
    out = []
    for c, group in enumerate(groups):
        th = theta[c]
        J_rows, res = [], []
        for e, b in enumerate(group):
            t = {k: torch.as_tensor(np.asarray(b[k], dtype=np.float64)) for k in ("d0", "d_lo", "d_hi", "dxy", "w")}
            kap = b["kappa"]
            sb = th[0] + t["dxy"] @ th[1:3]
            r = (0.5 * sb.abs()).clamp_min(1e-3)
            wa, wb = torch.tensor(b["wa"], dtype=torch.float64), torch.tensor(b["wb"], dtype=torch.float64)
            o, ct, delta = th[3 + 3 * e], th[4 + 3 * e], th[5 + 3 * e]
            E0, E0d, E0r = pixel_esf(t["d0"] - delta, r, wa, wb, with_derivatives=True)
            El, _, Elr = pixel_esf(t["d_lo"], r, wa, wb, with_derivatives=True)
            Eh, _, Ehr = pixel_esf(t["d_hi"], r, wa, wb, with_derivatives=True)
            cl, c0, ch = kap[1] - kap[0], kap[2] - kap[1], kap[3] - kap[2]
            prof = kap[0] + cl * El + c0 * E0 + ch * Eh
            m = t["w"].sqrt()
            I = torch.as_tensor(img[b["px"][:, 1], b["px"][:, 0]])
            res.append((o + ct * prof - I) * m)
            J = torch.zeros(len(m), P, dtype=torch.float64)
            dr = ct * (cl * Elr + c0 * E0r + ch * Ehr) * 0.5 * torch.sign(sb) * m
            J[:, 0], J[:, 1], J[:, 2] = dr, dr * t["dxy"][:, 0], dr * t["dxy"][:, 1]
            J[:, 3 + 3 * e], J[:, 4 + 3 * e], J[:, 5 + 3 * e] = m, prof * m, -ct * c0 * E0d * m
            J_rows.append(J)
        J, r = torch.cat(J_rows), torch.cat(res)
        p2 = float(prior[c]) ** 2
        A = J.T @ J
        A[1, 1] += p2
        A[2, 2] += p2
        g = J.T @ r
        g[1:3] += p2 * th[1:3]
        out.append(((r * r).sum() + p2 * (th[1:3] ** 2).sum(), A, g))
    return [torch.stack(x) for x in zip(*out)]


def test_band_model_normal_equations_are_the_pixel_by_pixel_ones():
    """The model evaluates the closed form only where the blur reaches (own edge and the far edges' listed
    candidates) and forms the normal equations from 7 rows a band: the same as every pixel through `pixel_esf`."""
    from tiltfit.detect.blur import _BandModel

    rng = np.random.default_rng(5)
    img, groups = _synthetic_bands(rng)
    C, B = len(groups), 4
    theta = torch.zeros(C, 3 + 3 * B, dtype=torch.float64)
    theta[:, 0] = torch.tensor([4.0, -2.5, 0.6], dtype=torch.float64)  # β: large, negative and small blur
    theta[:, 1:3] = torch.tensor([[0.05, -0.03], [0.2, 0.1], [-0.02, 0.04]], dtype=torch.float64)
    theta[:, 3::3], theta[:, 4::3], theta[:, 5::3] = 0.1, 0.8, 0.3
    prior = torch.tensor([0.5, 1.0, 2.0], dtype=torch.float64)
    model = _BandModel(img, groups, torch.full((C,), 3.0, dtype=torch.float64), B)
    idx = torch.tensor([1, 2])  # a subset, as the solver asks once points have converged; point 1 has 3 bands
    got = model.normal(theta[idx], idx, prior[idx])
    cost, A, g = _dense_normal(img, [groups[i] for i in idx], theta[idx], prior[idx])
    for name, x, ref in (("cost", got.cost, cost), ("JᵀJ", got.A, A), ("Jᵀr", got.g, g)):
        err = float((x - ref).abs().max() / ref.abs().max())
        assert err < 1e-10, f"{name} differs from the pixel-by-pixel model by {err:.2e} of its largest entry"


def test_band_model_evaluates_a_large_subset_with_its_kept_points():
    """The solver drops converged points a few at a time: a subset of most of the points gathered last is evaluated
    with them (nothing gathered anew) and gives the normal equations a model asked for that subset alone gives."""
    from tiltfit.detect.blur import _BandModel

    rng = np.random.default_rng(7)
    img, groups = _synthetic_bands(rng, bands_per_point=(4, 3, 4, 4, 2, 4))
    C, B = len(groups), 4
    theta = torch.zeros(C, 3 + 3 * B, dtype=torch.float64)
    theta[:, 0] = torch.linspace(-3.0, 4.0, C, dtype=torch.float64)
    theta[:, 1:3] = 0.05
    theta[:, 3::3], theta[:, 4::3], theta[:, 5::3] = 0.1, 0.8, 0.3
    prior = torch.linspace(0.5, 2.0, C, dtype=torch.float64)
    r_cap = torch.full((C,), 3.0, dtype=torch.float64)
    model = _BandModel(img, groups, r_cap, B)
    every = torch.arange(C)
    model.normal(theta, every, prior)
    idx = torch.tensor([0, 2, 3, 4, 5])  # point 1 converged
    step = 0.01 * torch.arange(idx.numel(), dtype=torch.float64)[:, None]  # the others moved on
    got = model.normal(theta[idx] + step, idx, prior[idx])
    assert torch.equal(model._idx, every), "a subset of 5 of the 6 points kept should not gather its tensors anew"
    ref = _BandModel(img, groups, r_cap, B).normal(theta[idx] + step, idx, prior[idx])
    for name in ("cost", "A", "g"):
        assert torch.equal(getattr(got, name), getattr(ref, name)), f"{name} differs from the subset's own model"


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


def test_a_point_the_first_pass_finds_too_sharp_is_measured_by_the_next(monkeypatch):
    """The first pass only plans the next: a point whose coarse fit leaves β undetermined (σ infinite, as a sharp
    corner's tiny β on the coarse level can, by rounding) is refitted on the level chosen for its blur and measured
    there, not dropped; nor is the coarse fit's width reported for it."""
    import tiltfit.detect.blur as blur

    v = _view(0.07, 0.002, seed=5)
    fit = blur.fit_corners
    sharp = {}

    def first_pass_undetermined(img, groups, r0, iterations=30):
        b, sb, grad, ok = fit(img, groups, r0, iterations)
        if iterations == 8 and not sharp:  # the first pass: its first point's β left undetermined
            sharp["done"] = True
            sb, ok = sb.copy(), ok.copy()
            sb[0], ok[0] = math.inf, False
        return b, sb, grad, ok

    monkeypatch.setattr(blur, "fit_corners", first_pass_undetermined)
    b, sb = measure_blur(v.image[..., 0], TARGET, v.truth.corners_px)
    monkeypatch.setattr(blur, "fit_corners", fit)
    ref, ref_sb = measure_blur(v.image[..., 0], TARGET, v.truth.corners_px)
    assert sharp, "the first pass should have run"
    assert np.isfinite(b).all() and np.isfinite(sb).all(), f"{np.isnan(b).sum()} points without a width"
    assert np.array_equal(b, ref) and np.array_equal(sb, ref_sb), "the later passes should measure the point as usual"


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
