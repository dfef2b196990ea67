"""ChArUco targets: the file format, the printable (OpenCV's own board), detection of partial and blurred views
with the right ids, and calibration from partial views (issue 23)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from tiltfit.detect.charuco import detect_board, detect_charuco, opencv_corners, refine_model
from tiltfit.detect.chessboard import DetectionError, detect
from tiltfit.experiments.charuco_views import (BOARD, CAMERA, FULL, PARTIAL, TARGET, blurred_renders, pose,
                                               square_px)
from tiltfit.calibrate.fit import FitOptions
from tiltfit.calibrate.model import Observations
from tiltfit.calibrate.photos import fit_with_held_out
from tiltfit.experiments.synth import render_view
from tiltfit.target.layout import CharucoTarget, Target, TargetError, target_from_dict
from tiltfit.target.raster import rasterise


# --- the file format and the printable ----------------------------------------------------------------------
def test_charuco_target_file_round_trip_and_one_line_errors():
    assert isinstance(TARGET, CharucoTarget) and TARGET.squares == (12, 9), "charuco file builds a CharucoTarget"
    assert target_from_dict(TARGET.to_dict()) == TARGET, "to_dict / target_from_dict round trip"
    assert TARGET.n_points == 11 * 8, "feature points are the 11 × 8 inner corners"
    board = TARGET.opencv_board()
    assert np.allclose(board.getChessboardCorners()[:, :2], TARGET.feature_points()[:, :2]), \
        "feature point k is OpenCV's ChArUco corner id k"
    for change, field in [({"marker_mm": 15.0}, "marker_mm"), ({"squares": [12]}, "squares"),
                          ({"dictionary": "DICT_5X5_1000000"}, "dictionary"), ({"squares": [20, 20]}, "squares"),
                          ({"dark_cell": [1, 0]}, "dark_cell"), ({"x_edges": [0, 1, 2]}, "x_edges"),
                          ({"square_mm": -1}, "square_mm")]:
        with pytest.raises(TargetError) as e:
            target_from_dict({**BOARD, **change}, "t.json")
        msg = str(e.value)
        assert msg.startswith(f"t.json: {field}:") and "\n" not in msg, f"{change}: message {msg!r}"
    checker = target_from_dict({"type": "checkerboard", "x_edges": [0, 10, 20, 30], "y_edges": [0, 10, 20]})
    assert type(checker) is Target, "the checkerboard stays the plain Target"


@pytest.mark.parametrize("dictionary, squares, dark_cell", [("DICT_5X5_100", (5, 7), (0, 0)),
                                                            ("DICT_4X4_50", (6, 4), (1, 0))])
def test_picture_is_opencvs_board(dictionary, squares, dark_cell):
    """Our rasterised board (the printable's and the renderer's texture) equals `CharucoBoard.generateImage`
    pixel for pixel where the bits fall on whole pixels, the legacy pattern (dark_cell odd) included."""
    bits = 7 if dictionary.startswith("DICT_5X5") else 6
    t = CharucoTarget.board(squares, 10.0, 0.1 * bits * 10, dictionary, margin=0.0, dark_cell=dark_cell)
    W, H = squares[0] * 100, squares[1] * 100
    theirs = t.opencv_board().generateImage((W, H), marginSize=0, borderBits=1)
    ours = rasterise(t, (0.0, squares[0] * 10.0), (0.0, squares[1] * 10.0), W, H)
    differ = np.mean(np.abs(ours * 255 - theirs) > 1)
    assert differ == 0, f"{100 * differ:.3f} % of pixels differ from OpenCV's board"


def test_printable_png_and_pdf(tmp_path):
    from tiltfit.cli import target as target_cli

    TARGET.save(str(tmp_path / "t.json"))
    rc = target_cli.main(["print", tmp_path / "t.json", "--png", tmp_path / "t.png", "--pdf", tmp_path / "t.pdf",
                          "--dpi", "100", "-q"])
    assert rc == 0 and (tmp_path / "t.png").stat().st_size > 0 and (tmp_path / "t.pdf").stat().st_size > 0, \
        "target print writes the ChArUco board"


# --- detection: ids and accuracy against blur --------------------------------------------------------------
BLURS = (0.0, 0.1, 0.25, 0.4, 0.5)  # blur-disc diameter, squares


@pytest.fixture(scope="module")
def blurred_partial_views():
    """Two partial views (a third of the board) at each blur, noise-free constant-blur renders + 0.3 % noise."""
    rng = np.random.default_rng(3)
    out = {}
    for v in PARTIAL[:2]:
        for truth, sq, b, img in blurred_renders(v, BLURS, 0.003, rng):
            out[(v, b)] = (img, truth, sq, detect_charuco(img, TARGET))
    return out


def _errors(det, truth):
    f = det.found
    return f, np.hypot(*(det.corners_px[f] - truth.corners_px[f]).T)


@pytest.mark.slow
@pytest.mark.parametrize("blur", BLURS)
def test_partial_views_get_the_right_ids(blurred_partial_views, blur):
    """Every corner found lies at its own id's true position (a wrong id is off by a square), and nearly
    all corners in the view are found, up to blur of half a square (where OpenCV reads no marker)."""
    for (v, b), (img, truth, sq, det) in blurred_partial_views.items():
        if b != blur:
            continue
        f, e = _errors(det, truth)
        n_in = int(truth.in_image.sum())
        assert n_in < 0.45 * TARGET.n_points, f"view shows {n_in} of {TARGET.n_points} corners: not partial"
        assert f.sum() >= 0.7 * n_in, f"blur {b}: {f.sum()} of {n_in} corners found ({det.message})"
        assert e.max() < 0.25 * sq, f"blur {b}: a corner is {e.max():.2f} px from its id's position (wrong id)"


@pytest.mark.slow
@pytest.mark.parametrize("blur", BLURS)
def test_corners_within_005_px(blurred_partial_views, blur):
    """Sub-pixel accuracy: every corner within 0.05 px of the truth up to blur of half a square (beyond 0.15 of a
    square fitted by the board's own blurred picture, markers' bits included)."""
    for (v, b), (img, truth, sq, det) in blurred_partial_views.items():
        if b == blur:
            f, e = _errors(det, truth)
            assert e.max() <= 0.05, f"blur {b}: max error {e.max():.3f} px, RMS {np.sqrt(np.mean(e ** 2)):.3f} px"


@pytest.mark.slow
def test_heavy_blur_error_at_the_noise_floor(blurred_partial_views):
    """At half a square of blur the corners' RMS error is the noise's floor (the model fit's Cramér–Rao bound at
    the true corners and blur), two-sided: within 0.5–2× of it. Above it: a model error left (painting the bits
    out left 4-10× the floor); below it: the floor is not what limits the corners (or the truth leaked in). The
    floor (0.005-0.01 px) puts the largest error over a view's ~25 corners near 0.015 px: 0.05 px is reachable."""
    for (v, b), (img, truth, sq, det) in blurred_partial_views.items():
        if b != 0.5:
            continue
        f, e = _errors(det, truth)
        _, floor = refine_model(img, TARGET, np.where(f[:, None], truth.corners_px, np.nan),
                                np.where(f, b * sq, np.nan))
        assert np.isfinite(floor[f]).all(), "the floor is computed at every found corner"
        rms, rms_floor = float(np.sqrt(np.mean(e ** 2))), float(np.sqrt(np.mean(floor[f] ** 2)))
        assert 0.5 * rms_floor <= rms <= 2.0 * rms_floor, \
            f"blur {b}: RMS error {rms:.4f} px, noise floor {rms_floor:.4f} px ({f.sum()} corners)"
        assert rms_floor < 0.02, f"floor {rms_floor:.4f} px: not a floor that allows 0.05 px corners"


@pytest.mark.parametrize("radius_px, d_radius", [(3.7, 0.2), (0.1, None)])
def test_model_picture_is_the_direct_convolution(radius_px, d_radius):
    """The model's picture (`_render_patch`: the disc blur as products of Fourier transforms, pixels read from
    folded transforms) is the supersampled picture convolved with the disc's kernel directly, its central
    differences and each pixel's box average, within 2e-6 of the dark fraction (float32 transforms), for a blur
    of some pixels (and the picture under a larger disc) and one under half a tap (not blurred)."""
    import cv2

    from tiltfit.detect.charuco_model import SUPERSAMPLE as S, _disc_kernel, _render_patch, board_texture
    from tiltfit.experiments.synth import plane_homography

    tex, origin, ppm = board_texture(TARGET)
    Hm = plane_homography(CAMERA, *pose(PARTIAL[0]))
    c = Hm @ np.r_[TARGET.feature_points()[40, :2], 1.0]
    r0, c0, h, w = int(c[1] / c[2]) - 20, int(c[0] / c[2]) - 23, 40, 47
    pad = math.ceil(radius_px + (d_radius or 0.0)) + 2
    v = (np.arange(r0 - pad, r0 + h + pad)[:, None] + (np.arange(S) + 0.5) / S - 0.5).ravel()
    u = (np.arange(c0 - pad, c0 + w + pad)[:, None] + (np.arange(S) + 0.5) / S - 0.5).ravel()
    V, U = np.meshgrid(v, u, indexing="ij")
    p = np.stack([U, V, np.ones_like(U)], -1) @ np.linalg.inv(Hm).T
    sharp = cv2.remap(tex, ((p[..., 0] / p[..., 2] - origin[0]) * ppm - 0.5).astype(np.float32),
                      ((p[..., 1] / p[..., 2] - origin[1]) * ppm - 0.5).astype(np.float32), cv2.INTER_LINEAR,
                      borderMode=cv2.BORDER_REPLICATE).astype(np.float64)

    def blurred(r):
        return cv2.filter2D(sharp, -1, _disc_kernel(r).astype(np.float64), borderType=cv2.BORDER_REPLICATE) \
            if r > 0.5 else sharp

    fine = blurred(radius_px * S)
    gy, gx = np.gradient(fine, 1.0 / S)
    want = [fine, gx, gy] + ([] if d_radius is None else [blurred((radius_px + d_radius) * S)])
    want = [a[pad * S:(pad + h) * S, pad * S:(pad + w) * S].reshape(h, S, w, S).mean((1, 3)) for a in want]
    got = _render_patch(tex, origin, ppm, Hm, r0, c0, h, w, radius_px, d_radius)
    assert len(got) == len(want) and all(g.shape == (h, w) for g in got), "picture, x and y slopes (, larger disc)"
    assert np.ptp(want[0]) > 0.5, "the patch shows the board's pattern"
    for name, g, e in zip(("picture", "x slope", "y slope", "larger disc"), got, want):
        assert np.abs(g - e).max() < 2e-6, f"{name}: {np.abs(g - e).max():.2e} from the direct convolution"


def test_markers_read_from_the_photo_as_encoded_unless_dark_or_over_range():
    """OpenCV reads the markers from the photo's own 8-bit encoding when its 99.9th percentile is within
    [DARK_PHOTO, 1] (stretching a frame at 0.82 reads the same markers at up to twice OpenCV's time), and from the
    photo scaled to that percentile when it is dark or above 1 (a linear render or HDR file)."""
    from camio.files import encode_srgb8, srgb_to_linear
    from tiltfit.detect.charuco import DARK_PHOTO, _srgb8

    g8 = np.random.default_rng(2).integers(0, 210, (60, 80)).astype(np.uint8)  # top ≈ sRGB 209: 0.64 linear
    lin = srgb_to_linear(g8 / 255.0)
    assert DARK_PHOTO < np.percentile(lin, 99.9) < 1.0
    assert np.array_equal(_srgb8(lin), g8), "a photo near the full range is read as encoded"
    for scale in (0.25, 3.0):
        top = np.percentile(lin * scale, 99.9)
        assert np.array_equal(_srgb8(lin * scale), encode_srgb8(lin * scale / top)), f"× {scale}: scaled to 99.9 %"
        assert _srgb8(lin * scale).max() == 255, f"× {scale}: the 8-bit copy spans the range"


@pytest.mark.slow
def test_better_than_opencv_on_sharp_views(blurred_partial_views):
    """On the same sharp renders our refinement is closer to the truth than OpenCV's CharucoDetector."""
    ours, theirs = [], []
    for (v, b), (img, truth, sq, det) in blurred_partial_views.items():
        if b == 0.0:
            oc = opencv_corners(img, TARGET)
            both = det.found & np.isfinite(oc).all(1)
            ours += list(np.hypot(*(det.corners_px[both] - truth.corners_px[both]).T))
            theirs += list(np.hypot(*(oc[both] - truth.corners_px[both]).T))
    rms_o, rms_t = np.sqrt(np.mean(np.square(ours))), np.sqrt(np.mean(np.square(theirs)))
    assert len(ours) >= 20 and rms_o < 0.5 * rms_t, f"RMS ours {rms_o:.3f} px, OpenCV {rms_t:.3f} px"


@pytest.mark.slow  # the blurred_partial_views fixture renders and detects ten views (~30 s of CPU)
def test_blur_measured_between_markers(blurred_partial_views):
    """The blur width at the corners (bands stopping at the markers' borders) is the rendered disc within 10 %."""
    for (v, b), (img, truth, sq, det) in blurred_partial_views.items():
        if 0.1 <= b <= 0.25:
            ratio = float(np.nanmedian(det.blur_px / (b * sq)))
            assert abs(ratio - 1) < 0.1, f"blur {b}: measured / rendered = {ratio:.3f}"


@pytest.mark.slow  # the blurred_partial_views fixture renders and detects ten views (~30 s of CPU)
def test_detect_board_dispatches_on_the_target_type(blurred_partial_views):
    img, truth, sq, det = blurred_partial_views[(PARTIAL[0], 0.1)]
    d = detect_board(img, TARGET, measure_blur=False)
    assert d.grid_found and d.found.sum() == det.found.sum(), "detect_board runs the ChArUco pipeline"
    with pytest.raises(DetectionError, match="ChArUco"):
        detect(img, TARGET)


# --- the ray tracer, and calibration from partial views ----------------------------------------------------
@pytest.fixture(scope="module")
def ray_traced():
    """Ray-traced views (the renderer's thin-lens camera, the board as a textured rectangle): partial and full."""
    cam = CAMERA.with_(U=420.0, d=0.8)
    out = {}
    for kind, views in (("partial", PARTIAL[:5]), ("full", FULL[:3])):
        dets, truths = [], []
        for k, v in enumerate(views):
            R, T = pose(v)
            r = render_view(TARGET, cam, R, T, method="renderer", spp=10, seed=k, srgb8=True)
            dets.append(detect_charuco(r.image, TARGET))
            truths.append(r.truth)
        out[kind] = (dets, truths)
    return cam, out


def _calibrate(dets):
    obs = Observations(TARGET.feature_points(), np.stack([d.corners_px for d in dets]),
                       np.stack([d.blur_px for d in dets]), CAMERA.sensor.size_px, CAMERA.sensor.pixel_pitch,
                       names=[f"view{k}" for k in range(len(dets))])
    result, _, _ = fit_with_held_out(obs, "unified", options=FitOptions(distortion="none",
                                                                        free_principal_point=False),
                                     held_out_folds=0)
    return result


@pytest.mark.slow
def test_ray_traced_partial_views_ids_and_calibration(ray_traced):
    """On the ray tracer's renders: ids right; w from views of a third of the board matches the whole-board
    calibration within their σ (two-sided: the difference within 3 σ, and σ not inflated past 1 %)."""
    cam, out = ray_traced
    for kind, (dets, truths) in out.items():
        for d, t in zip(dets, truths):
            f = d.found
            e = np.hypot(*(d.corners_px[f] - t.corners_px[f]).T)
            assert f.sum() >= 0.7 * t.in_image.sum(), f"{kind}: {f.sum()} of {t.in_image.sum()} found ({d.message})"
            assert e.max() < 0.5, f"{kind}: a corner {e.max():.2f} px from its id's truth"
        if kind == "partial":
            assert all(d.found.sum() < 0.45 * TARGET.n_points for d in dets), "partial views show ≤ 45 % of corners"
    part, full = _calibrate(out["partial"][0]), _calibrate(out["full"][0])
    w_p, w_f = part.values["w_mm"], full.values["w_mm"]
    s_p, s_f = part.sigma["w_mm"], full.sigma["w_mm"]
    diff, s = abs(w_p - w_f), math.hypot(s_p, s_f)
    assert diff <= 3 * s, f"w: partial {w_p:.4f} ± {s_p:.4f}, full {w_f:.4f} ± {s_f:.4f} mm: {diff / s:.1f} σ apart"
    assert s_p < 0.01 * w_p and s_f < 0.01 * w_f, f"σ of w too large to mean anything: {s_p:.4f}, {s_f:.4f} mm"
    assert abs(w_p - cam.w) <= 3 * s_p + 0.002 * cam.w, f"partial-view w {w_p:.4f} ± {s_p:.4f}, truth {cam.w}"


@pytest.mark.slow
def test_ray_traced_half_square_blur_within_005_px():
    """A generator other than the model's: the ray tracer's thin lens (aperture 24 mm, blur ~half a square, varying
    over the view), 256 spp, 8-bit, a view of a third of the board. Right ids, every corner within 0.05 px, and
    the RMS error at the noise's floor (the model fit's Cramér–Rao bound at the truth), two-sided: 0.5–2×."""
    from tiltfit.detect.chessboard import to_gray

    R, T = pose(PARTIAL[1])
    r = render_view(TARGET, CAMERA.with_(U=420.0, d=24.0), R, T, method="renderer", spp=256, seed=1, srgb8=True)
    t = r.truth
    sq = square_px(np.where(t.in_image[:, None], t.corners_px, np.nan))
    blur = float(np.median(t.blur_px[t.in_image])) / sq
    assert 0.4 <= blur <= 0.6, f"the view's blur is {blur:.2f} of a square, not about half"
    det = detect_charuco(r.image, TARGET)
    f = det.found
    e = np.hypot(*(det.corners_px[f] - t.corners_px[f]).T)
    assert f.sum() >= 0.7 * t.in_image.sum(), f"{f.sum()} of {t.in_image.sum()} corners found ({det.message})"
    rms = float(np.sqrt(np.mean(e ** 2)))
    assert e.max() <= 0.05, f"max error {e.max():.3f} px, RMS {rms:.3f} px at blur {blur:.2f} square"
    _, floor = refine_model(to_gray(r.image), TARGET, np.where(f[:, None], t.corners_px, np.nan),
                            np.where(f, t.blur_px, np.nan))
    rms_floor = float(np.sqrt(np.nanmean(floor[f] ** 2)))
    assert 0.5 * rms_floor <= rms <= 2.0 * rms_floor, f"RMS error {rms:.4f} px, noise floor {rms_floor:.4f} px"


@pytest.mark.slow  # the blurred_partial_views fixture renders and detects ten views (~30 s of CPU)
def test_tiltfit_detect_writes_ids_as_positions_and_nulls(tmp_path, blurred_partial_views):
    """`tiltfit detect` on a photo of a third of the board: a DET file with every corner of the board, the seen
    ones at their ids' positions and null elsewhere, which `read_det` accepts back."""
    import cv2

    from camio.files import linear_to_srgb
    from tiltfit.cli.main import main
    from tiltfit.files.det import read_det

    img, truth, sq, det = blurred_partial_views[(PARTIAL[0], 0.1)]
    cv2.imwrite(str(tmp_path / "p.png"), np.clip(np.round(255 * linear_to_srgb(np.clip(img, 0, 1))), 0, 255)
                .astype(np.uint8))
    TARGET.save(str(tmp_path / "t.json"))
    rc = main(["detect", str(tmp_path / "p.png"), "--target", str(tmp_path / "t.json"), "-o", str(tmp_path / "d.json"),
               "-q"])
    assert rc == 0, "tiltfit detect on a ChArUco photo"
    d = read_det(str(tmp_path / "d.json"), TARGET.n_points)
    corners = np.array([[np.nan, np.nan] if c is None else c for c in d["corners_px"]], dtype=np.float64)
    seen = np.isfinite(corners).all(1)
    assert 20 <= seen.sum() < 0.45 * TARGET.n_points, f"{seen.sum()} corners in the DET file"
    e = np.hypot(*(corners[seen] - truth.corners_px[seen]).T)
    assert e.max() < 0.1, f"DET corners up to {e.max():.3f} px from their ids' truth"


def test_photometric_refinement_refuses_charuco():
    """The photometric model renders checkerboards only: a ChArUco target is refused with one line, not fitted
    with its markers missing."""
    from tiltfit.photometric import PhotometricError, refine_photometric

    with pytest.raises(PhotometricError, match="ChArUco") as e:
        refine_photometric([np.zeros((24, 32))], TARGET, None)
    assert "\n" not in str(e.value), "one line"
