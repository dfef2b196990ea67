"""Corner detection on synthetic images of known geometry (tiltfit.experiments.synth, exact disc-blur rendering)."""
import json
import math

import numpy as np
import pytest
import torch

from tiltfit.detect.chessboard import (Detection, detect, read_detection_json, refine_symmetric, to_gray,
                            write_detection_json)
from renderer import Lens, Sensor
from tiltfit.experiments.synth import (PAPER_CAMERA, look_at_pose, observe, projected_square_px, render_view,
                           with_blur_ratio)
from tiltfit.target.design import design_target
from tiltfit.target.layout import Target

torch.set_num_threads(1)

CAM = PAPER_CAMERA.binned(12)  # 456 × 304 px of 78.5 µm: the paper's camera, 12× coarser
TARGET = design_target(9, 6, 20.0, w_mm=55.39, distance_mm=650.0, inclination_deg=20.0)  # 9 + 6 odd


def view(ratio=0.15, position=(40.0, -30.0, -650.0), look_at=None, roll=0.0, noise=0.004, seed=0, target=TARGET,
         U_mm=400.0, camera=CAM):
    """A rendered view whose median blur is `ratio` × the median projected square (focus at U_mm)."""
    R, T = look_at_pose(target, position, look_at, roll)
    cam = with_blur_ratio(camera, target, R, T, ratio, U_mm=U_mm) if ratio else camera
    return render_view(target, cam, R, T, noise_sigma=noise, srgb8=True, seed=seed)


def errors(det: Detection, v) -> np.ndarray:
    return np.hypot(*(det.corners_px - v.truth.corners_px).T)


def rms(e):
    e = e[np.isfinite(e)]
    return float(np.sqrt(np.mean(e ** 2)))


@pytest.mark.parametrize("ratio", [0.05, 0.15, 0.3])
def test_corners_within_005_px_over_the_papers_blur_range(ratio):
    v = view(ratio, seed=1)
    det = detect(v.image, TARGET, measure_blur=False)
    assert det.grid_found, f"no grid at blur {ratio} of the square: {det.message}"
    assert det.found.all(), f"{(~det.found).sum()} of {TARGET.n_points} corners missing at blur ratio {ratio}"
    e = errors(det, v)
    assert rms(e) < 0.05, f"corner RMS {rms(e):.4f} px at blur ratio {ratio} (limit 0.05)"
    assert e.max() < 0.12, f"worst corner {e.max():.3f} px at blur ratio {ratio}"


def test_corners_across_the_plane_of_focus():
    """The paper's focus (U = 618.4 mm) inside the board: blur from 0 to several pixels in one image."""
    R, T = look_at_pose(TARGET, (60.0, -400.0, -450.0), roll_deg=8.0)
    cam = CAM.with_(d=50.0)  # a wider aperture than the paper's f/2.8
    v = render_view(TARGET, cam, R, T, noise_sigma=0.004, srgb8=True, seed=2)
    b = v.truth.blur_px
    assert b.min() < 0.5 < 2.0 < b.max(), f"the view should cross the plane of focus, blur {b.min():.2f}..{b.max():.2f}"
    det = detect(v.image, TARGET, measure_blur=False)
    e = errors(det, v)
    assert det.found.all() and rms(e) < 0.05, f"found {det.found.sum()}, RMS {rms(e):.4f} px across the focus"


@pytest.mark.slow
def test_works_at_blur_08_of_the_square():
    v = view(0.8, seed=3)
    sq = np.median(projected_square_px(TARGET, CAM, *look_at_pose(TARGET, (40.0, -30.0, -650.0))))
    assert np.median(v.truth.blur_px) > 0.75 * sq, "the view should have blur 0.8 of the square"
    det = detect(v.image, TARGET, measure_blur=False)
    assert det.grid_found, f"no grid at blur 0.8 of the square: {det.message}"
    e = errors(det, v)
    assert det.found.sum() >= 0.95 * TARGET.n_points, f"only {det.found.sum()} corners at blur 0.8"
    assert np.nanmax(e) < 0.3, f"a corner is {np.nanmax(e):.2f} px off: wrong index or lost refinement"
    assert rms(e) < 0.1, f"corner RMS {rms(e):.3f} px at blur 0.8 of the square"


@pytest.mark.parametrize("roll", [90.0, 180.0, 270.0])
def test_turned_board_gets_the_right_indices(roll):
    """A checkerboard is ambiguous under quarter turns; the colour of the cells fixes the indexing."""
    v = view(0.1, roll=roll, seed=4)
    det = detect(v.image, TARGET, measure_blur=False)
    e = errors(det, v)
    assert det.grid_found and det.found.all(), f"turned {roll}°: {det.message}"
    assert e.max() < 0.1, f"turned {roll}°: worst corner {e.max():.2f} px (a wrong index is ≥ one square)"


def test_partly_visible_board_returns_the_corners_it_sees():
    R, T = look_at_pose(TARGET, (170.0, 40.0, -380.0), look_at_mm=(175.0, 30.0, 0.0), roll_deg=12.0)
    cam = with_blur_ratio(CAM, TARGET, R, T, 0.1, U_mm=400.0)
    v = render_view(TARGET, cam, R, T, noise_sigma=0.004, srgb8=True, seed=5)
    inner = observe(TARGET, cam, R, T, border_px=8.0).in_image
    assert 8 <= inner.sum() < TARGET.n_points - 8, f"the view should cut the board, {inner.sum()} inside"
    det = detect(v.image, TARGET, measure_blur=False)
    assert det.grid_found, f"partial board not found: {det.message}"
    e = errors(det, v)
    assert np.all(v.truth.in_image[det.found]), "a corner outside the image was reported"
    assert det.found[inner].mean() > 0.9, f"found {det.found[inner].sum()} of {inner.sum()} corners well inside"
    assert np.nanmax(e) < 0.1, f"worst corner {np.nanmax(e):.2f} px: the partial board is mis-indexed"


SYMMETRIC = Target(tuple(np.arange(0, 161, 20.0)), tuple(np.arange(0, 121, 20.0)), (0, 0), 25.0)  # 8 × 6 cells


@pytest.mark.parametrize("roll", [0.0, 180.0])
def test_target_symmetric_under_180_is_labelled_by_image_geometry(roll):
    """Even n_cols + n_rows and uniform rows: a 180° turn gives the same image. The board turned by 0° and by
    180° must get the same labelling in the image (corner 0 nearer the top-left), i.e. the labels follow the
    image, not the board; the note says so."""
    R, T = look_at_pose(SYMMETRIC, (40.0, -30.0, -650.0), roll_deg=roll + 10.0)
    v = render_view(SYMMETRIC, with_blur_ratio(CAM, SYMMETRIC, R, T, 0.1, U_mm=400.0), R, T, noise_sigma=0.004,
                    seed=6)
    det = detect(v.image, SYMMETRIC, measure_blur=False)
    assert det.grid_found and det.found.all(), f"turned {roll}°: {det.message}"
    assert "180" in det.message, f"the labelling choice must be noted, got {det.message!r}"
    truth = v.truth.corners_px if roll == 0 else v.truth.corners_px[::-1]  # the half turn reverses the order
    e = np.hypot(*(det.corners_px - truth).T)
    assert e.max() < 0.1, f"turned {roll}°: worst corner {e.max():.2f} px from the image-geometry labelling"
    first, last = det.corners_px[0], det.corners_px[-1]
    assert (last - first).sum() > 0, f"corner 0 {first} should be nearer the top-left than corner N-1 {last}"


def test_no_board_in_noise():
    rng = np.random.default_rng(0)
    det = detect(rng.uniform(0.2, 0.3, (200, 300)).astype(np.float32), TARGET)
    assert not det.grid_found and np.isnan(det.corners_px).all() and np.isnan(det.blur_px).all(), det.message


def test_pixel_convention_on_odd_non_square_image():
    """(0, 0) is the centre of the top-left pixel on a 301 × 203 image with its principal point off-centre."""
    cam = Lens(50.0, 400.0, 2.0, sensor=Sensor(301, 203, 0.09),
                      principal_point_px=(140.3, 108.6))
    R, T = look_at_pose(TARGET, (90.0, 60.0, -900.0), roll_deg=5.0)
    v = render_view(TARGET, cam, R, T, noise_sigma=0.002, srgb8=True, seed=7)
    det = detect(v.image, TARGET, measure_blur=False)
    e = det.corners_px - v.truth.corners_px
    assert det.found.all(), det.message
    assert np.abs(e.mean(0)).max() < 0.01, f"mean offset {e.mean(0)} px: a pixel-convention error"


@pytest.mark.parametrize("blur_px", [0.0, 1.0, 4.0])
def test_symmetric_refinement_is_unbiased_across_subpixel_phase(blur_px):
    cam0 = Lens(50.0, 500.0, 1.0, sensor=Sensor(96, 72, 0.05))
    cam = cam0 if blur_px == 0 else with_blur_ratio(cam0, TARGET, np.eye(3), np.array([-90.0, -60.0, 600.0]),
                                                    blur_px / 33.3)
    worst = 0.0
    for phase in (0.1, 0.3, 0.5, 0.7, 0.9):
        T = np.array([-90.0 + phase * 0.6, -60.0 + phase * 0.35, 600.0])
        v = render_view(TARGET, cam, np.eye(3), T)
        truth = v.truth.corners_px
        k = np.nonzero(v.truth.in_image & (np.abs(truth - [48, 36]).max(1) < 20))[0]
        xy, asym, ok = refine_symmetric(to_gray(v.image), truth[k] + 0.3, np.full(len(k), 8.0))
        assert ok.all(), "refinement failed on a clean corner"
        worst = max(worst, float(np.hypot(*(xy - truth[k]).T).max()))
    assert worst < 0.04, f"refinement bias {worst:.3f} px at blur {blur_px} px"


def test_detection_json_contract(tmp_path):
    v = view(0.15, seed=8)
    det = detect(v.image, TARGET)
    det.corners_px[3] = np.nan  # pretend one is missing
    det.blur_px[3] = np.nan
    path = tmp_path / "det.json"
    write_detection_json(det, str(path))
    d = json.loads(path.read_text())
    assert d["image_size_px"] == list(CAM.sensor.size_px), f"image_size_px is [W, H], got {d['image_size_px']}"
    assert len(d["corners_px"]) == TARGET.n_points and len(d["blur_px"]) == TARGET.n_points, "one entry per point"
    assert d["corners_px"][3] is None and d["blur_px"][3] is None, "missing points are null"
    assert d["grid_found"] is True and all(len(c) == 2 for c in d["corners_px"] if c is not None)
    back = read_detection_json(str(path), TARGET.n_points)
    np.testing.assert_allclose(back.corners_px, det.corners_px, atol=1e-4, err_msg="JSON round trip")
    assert math.isfinite(d["blur_px"][0]), "blur must be written for found points"


# --- the synthetic images the tests rely on ----------------------------------------------------------------
def test_analytic_rendering_equals_brute_force_disc_convolution():
    """Fronto-parallel board, uniform blur: render_analytic against a 16× supersampled image convolved with
    an anti-aliased disc (FFT) and box-averaged back, away from the image border."""
    from tiltfit.experiments.synth import render_analytic
    from tiltfit.target.raster import rasterise

    t = Target(tuple(np.arange(0, 81, 10.0)), tuple(np.arange(0, 61, 10.0)), (0, 0), 10.0)
    cam = Lens(50.0, 500.0, 10.0, sensor=Sensor(64, 48, 0.05))
    z, T = 600.0, np.array([-40.3, -30.2, 600.0])
    img = render_analytic(t, cam, np.eye(3), T, 0.05, 0.8, 0.3)
    f = cam.w / cam.sensor.pixel_pitch / z  # px per mm
    (cx, cy), s, (W, H) = cam.center_px, 16, (cam.sensor.width_px, cam.sensor.height_px)
    xr = ((-0.5 - cx) / f - T[0], (W - 0.5 - cx) / f - T[0])
    yr = ((-0.5 - cy) / f - T[1], (H - 0.5 - cy) / f - T[1])
    hi = rasterise(t, xr, yr, W * s, H * s, 0.05, 0.8).astype(np.float64)
    xc = np.linspace(*xr, W * s + 1)[:-1] + 0.5 * (xr[1] - xr[0]) / (W * s)
    yc = np.linspace(*yr, H * s + 1)[:-1] + 0.5 * (yr[1] - yr[0]) / (H * s)
    x0, y0, x1, y1 = t.extent_mm
    hi[~(((yc > y0) & (yc < y1))[:, None] & ((xc > x0) & (xc < x1))[None, :])] = 0.3
    b = float(cam.blur_px(np.array([0.0, 0.0, z])))
    rad = 0.5 * b * s
    k = int(math.ceil(rad)) + 1
    yy, xx = np.mgrid[-k:k + 1, -k:k + 1]
    o = (np.arange(8) + 0.5) / 8 - 0.5
    ker = sum(((xx + a) ** 2 + (yy + c) ** 2 <= rad * rad).astype(float) for a in o for c in o)
    pad = np.pad(hi, k, mode="edge")
    kf = np.zeros_like(pad)
    kf[:2 * k + 1, :2 * k + 1] = ker / ker.sum()
    conv = np.real(np.fft.ifft2(np.fft.fft2(pad) * np.fft.fft2(kf)))[2 * k:, 2 * k:][:H * s, :W * s]
    ref = conv.reshape(H, s, W, s).mean((1, 3))
    m = int(b) + 2
    diff = np.abs(img - ref)[m:-m, m:-m]
    assert diff.max() < 3e-3, f"analytic rendering differs from brute force by up to {diff.max():.4f} (blur {b:.2f} px)"


@pytest.mark.slow
def test_ray_tracer_agrees_with_the_analytic_rendering():
    """The renderer's thin-lens camera and textured rectangle show the same image (within Monte Carlo noise)."""
    cam = PAPER_CAMERA.binned(16)
    R, T = look_at_pose(TARGET, (40.0, -30.0, -650.0), roll_deg=10.0)
    cam = with_blur_ratio(cam, TARGET, R, T, 0.2, U_mm=400.0)
    va = render_view(TARGET, cam, R, T)
    vr = render_view(TARGET, cam, R, T, method="renderer", spp=16)
    d = vr.clean - va.clean
    assert abs(d.mean()) < 2e-3 and np.abs(d).mean() < 8e-3, f"mean {d.mean():.4f}, mean |diff| {np.abs(d).mean():.4f}"
    det = detect(vr.image, TARGET)
    e = errors(det, va)
    assert det.found.all() and rms(e) < 0.1, f"on the ray-traced image: {det.found.sum()} corners, RMS {rms(e):.3f}"
    ratio = np.median(det.blur_px / va.truth.blur_px)
    assert abs(ratio - 1) < 0.03, f"blur on the ray-traced image is {ratio:.3f} of the closed form"


def test_shifted_patches_are_the_separable_cubic_filter():
    """`_shift_patches` (numpy, both axes' weights at once, the filters that share a pass together, each pass along
    the flattened patch) gives the same bits as torch filtering one output at a time: Keys' kernel, the x pass, then
    the y pass, each a sum of four weighted shifted slices in float32."""
    import torch

    from tiltfit.detect.refine import _shift_patches

    def keys(x):  # Keys' cubic kernel (a = -1/2) and its derivative, in torch
        ax = x.abs()
        return torch.where(ax <= 1, (1.5 * ax - 2.5) * ax * ax + 1,
                           torch.where(ax < 2, ((-0.5 * ax + 2.5) * ax - 4) * ax + 2, torch.zeros_like(ax)))

    def dkeys(x):
        ax = x.abs()
        return torch.sign(x) * torch.where(ax <= 1, (4.5 * ax - 5) * ax,
                                           torch.where(ax < 2, (-1.5 * ax + 5) * ax - 4, torch.zeros_like(ax)))

    rng = np.random.default_rng(9)
    for n, size in ((1, 11), (7, 23), (12, 59), (3, 81)):
        patches = rng.random((n, size, size)).astype(np.float32) - np.float32(0.25)
        frac = rng.random((n, 2)).astype(np.float32)
        frac[0] = 0.0  # a tap of weight exactly 0
        pt, ft = torch.from_numpy(patches), torch.from_numpy(frac)
        ks = torch.arange(-1, 3, dtype=torch.float32)

        def one(img, w, axis):
            cut = size - 3
            return sum(w[:, k, None, None] * (img[:, :, k:k + cut] if axis == 1 else img[:, k:k + cut, :])
                       for k in range(4))

        wx, wy = keys(ft[:, 0:1] - ks), keys(ft[:, 1:2] - ks)
        dwx, dwy = dkeys(ft[:, 0:1] - ks), dkeys(ft[:, 1:2] - ks)
        tx, tdx = one(pt, wx, 1), one(pt, dwx, 1)
        want = (one(tx, wy, 0), one(tdx, wy, 0), one(tx, dwy, 0))
        got = _shift_patches(patches, frac)
        for name, g, e in zip(("value", "x slope", "y slope"), got, want):
            assert g.shape == (n, size - 3, size - 3) and np.array_equal(g, e.numpy()), \
                f"{n} patches of {size}: {name} differs"
    # and the interpolant reproduces a quadratic (Keys' kernel with a = -1/2 is third-order accurate)
    yy, xx = np.mgrid[0:15, 0:15].astype(np.float64)
    quad = (0.01 * xx * xx + 0.02 * xx * yy - 0.03 * yy + 0.5)[None].astype(np.float32)
    v, gx, gy = _shift_patches(quad, np.array([[0.25, 0.75]], np.float32))
    x, y = xx[:12, :12] + 1.25, yy[:12, :12] + 1.75
    assert np.abs(v[0] - (0.01 * x * x + 0.02 * x * y - 0.03 * y + 0.5)).max() < 1e-5, "value of a quadratic"
    assert np.abs(gx[0] - (0.02 * x + 0.02 * y)).max() < 1e-5, "x slope of a quadratic"
    assert np.abs(gy[0] - (0.02 * x - 0.03)).max() < 1e-5, "y slope of a quadratic"
