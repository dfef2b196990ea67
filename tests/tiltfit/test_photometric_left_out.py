"""A view whose board leaves too few usable pixels is left out of the photometric fit, not the end of it.

Unit level: the fit's own model (noise-free, 3 views, as test_photometric.py's `own_model`) with a fourth view
inserted whose board is tiny (30 m away, its blur disc wider than the board) or not on the image at all: the
refinement runs on the other three, names the view and why, keeps its pose the start's, and lands exactly where
the same fit without that view lands. Real photos: the subset of data/real/gopro_wide where the refinement stopped
("view 6: the board covers fewer than 100 usable pixels": GOPR0053.jpg, among every third view from the third,
whose box holds a pixel that meets the board's plane 255 m away, which widened the mask's guard past the
board): the mask now has thousands of usable pixels there, and the subset runs through the function
`tiltfit calibrate --refine photometric` runs, up to the CALIB.json block.
"""
from __future__ import annotations

import argparse
import copy
import functools
import math
import os
import sys

import numpy as np
import pytest
import torch

sys.path.insert(0, os.path.dirname(__file__))
import test_photometric as tp  # noqa: E402  (the fit's own model and its helpers)

from tiltfit.experiments import reproduce  # noqa: E402
from tiltfit.photometric import PhotometricError, PhotometricOptions, refine_photometric  # noqa: E402
from tiltfit.photometric.refine import _camera_views  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
OPTIONS = PhotometricOptions(max_pixels=300, aperture="closed_form")


def _with_view(camera, at: int, R, T_mm):
    """A copy of `camera` with a view of pose (R, T_mm) inserted at index `at`."""
    import cv2

    cam = camera.copy()
    rvec = torch.as_tensor(cv2.Rodrigues(np.asarray(R, dtype=np.float64))[0].reshape(1, 3), dtype=cam.rvec.dtype)
    T = torch.as_tensor(np.asarray(T_mm, dtype=np.float64).reshape(1, 3), dtype=cam.T_scaled.dtype) / cam.length_scale_mm
    for name, new in (("rvec", rvec), ("T_scaled", T)):
        p = getattr(camera, name).detach()
        setattr(cam, name, torch.nn.Parameter(torch.cat([p[:at], new, p[at:]]), requires_grad=False))
    return cam


@functools.lru_cache(maxsize=1)
def _own_model():
    """test_photometric.py's `own_model` (noise-free captures of the fit's own model, 171 x 114, 3 views, and a
    start off like a corner fit's): (images, truth camera, start camera)."""
    from renderer import Lens, Sensor
    from renderer.cameras import optics
    from renderer.cameras import EOS_6D
    from tiltfit.photometric.render import dark_fraction_disc, shade

    w_px, h_px = EOS_6D.binned(32).size_px
    pitch = EOS_6D.pixel_pitch * 32
    lens = Lens.from_tilt(tp.W_MM, float(optics.focal_length(tp.W_MM, 1000.0)), math.radians(tp.THETA_L_DEG), tp.D_MM,
                          sensor=Sensor(w_px, h_px, pitch))
    poses = [reproduce.target_pose(tp.BOARD, *reproduce.TARGET_VIEWS[i]) for i in tp.VIEWS]
    truth = {"U_mm": lens.U, "theta_F": lens.theta_F, "pitch": pitch}
    start = {"w_mm": tp.W_MM, "U_mm": truth["U_mm"], "d_mm": tp.D_MM, "theta_F_deg": math.degrees(truth["theta_F"]),
             "views": [{"R": R, "T_mm": T} for R, T in poses]}
    camera = tp._camera(start, [np.zeros((h_px, w_px))], pitch)
    yy, xx = np.mgrid[0:h_px, 0:w_px]
    uv = torch.tensor(np.stack([xx.ravel(), yy.ravel()], -1), dtype=torch.float64)
    with torch.no_grad():
        images = [shade(dark_fraction_disc(tp.BOARD, camera.view_camera(v), uv, 7), uv, (w_px, h_px), 0.8 - 0.05 * v,
                        0.06, 0.05).reshape(h_px, w_px).numpy() for v in range(len(tp.VIEWS))]
    return images, camera, tp._camera(tp._perturbed_init(poses, truth), images, pitch)


@pytest.fixture(scope="module")
def without():
    """The fit on the three good views alone (the reference)."""
    images, _, start = _own_model()
    return images, start, refine_photometric(images, tp.BOARD, start, OPTIONS)


@pytest.mark.parametrize("case", ["tiny board", "off the image"])
def test_a_view_with_too_few_usable_pixels_is_left_out(without, case):
    """A fourth view (inserted second) with a tiny board or none on the image: one `say` line names it and why,
    `left_out` lists it, its pose stays the start's, and lens, σ, poses and levels are those of the fit without it."""
    images, start, ref = without
    if case == "tiny board":   # 30 m away: a few pixels wide, its blur disc wider than the board
        R, T = reproduce.target_pose(tp.BOARD, 0.0, 0.0, 30000.0)
        why = "usable pixels"
    else:                      # 5 m to the side: not on the image
        R, T = reproduce.target_pose(tp.BOARD, 0.0, 0.0, 600.0)
        T = np.asarray(T) + np.array([5000.0, 0.0, 0.0])
        why = "not on the image"
    cam = _with_view(start, 1, R, T)
    imgs = [images[0], np.full_like(images[0], 0.7), images[1], images[2]]
    lines = []
    res = refine_photometric(imgs, tp.BOARD, cam, OPTIONS, say=lines.append)
    said = [s for s in lines if "left out" in s]
    assert len(said) == 1 and "view 1" in said[0] and why in said[0], f"{case}: one line naming view 1: {said}"
    assert [e["view"] for e in res.left_out] == [1] and why in res.left_out[0]["reason"], f"left_out {res.left_out}"
    # The same fit as without the view: lens, σ, kept, and the three views' poses and levels.
    for key in ("w_mm", "U_mm", "d_mm", "theta_L_deg"):
        assert res.values[key] == pytest.approx(ref.values[key], rel=1e-12, abs=1e-12), \
            f"{case}: {key} {res.values[key]} with the view left out, {ref.values[key]} without it"
        assert res.sigma[key] == pytest.approx(ref.sigma[key], rel=1e-9, abs=1e-15), f"{case}: σ of {key}"
    assert res.kept == ref.kept and res.rms == pytest.approx(ref.rms, rel=1e-12), f"kept {res.kept}, rms {res.rms}"
    assert res.camera.n_views == 4 and res.start_camera.n_views == 4, "the result keeps every view"
    for k, j in ((0, 0), (2, 1), (3, 2)):
        assert torch.allclose(res.camera.T_mm[k], ref.camera.T_mm[j], rtol=0, atol=1e-9), f"pose of view {k}"
        assert res.views[k]["white"] == pytest.approx(ref.views[j]["white"], rel=1e-12), f"levels of view {k}"
    assert torch.equal(res.camera.T_mm[1], cam.T_mm[1]) and torch.equal(res.camera.R[1], cam.R[1]), \
        "the left-out view's pose stays the start's"
    assert "left_out" in res.views[1] and "white" not in res.views[1], f"view 1's entry {res.views[1]}"
    # And the truth: the three views still recover the lens (the start is off by 0.3 % in w).
    truth = _own_model()[1].summary()
    assert abs(res.values["w_mm"] - truth["w_mm"]) < 1e-5, f"w {res.values['w_mm']} vs truth {truth['w_mm']}"


def test_no_view_left_is_an_error(without):
    """Only a view without usable pixels: a one-line PhotometricError naming the view and the cause."""
    images, start, _ = without
    R, T = reproduce.target_pose(tp.BOARD, 0.0, 0.0, 30000.0)
    cam = _camera_views(_with_view(start, 0, R, T), [0])
    with pytest.raises(PhotometricError, match=r"^no view left to fit \(1 of 1 left out; view 0: the board covers "
                                               r"0 usable pixels") as e:
        refine_photometric([np.full_like(images[0], 0.7)], tp.BOARD, cam, OPTIONS)
    assert "\n" not in str(e.value), f"one line: {e.value!r}"


def _gopro_third_subset():
    """data/real/gopro_wide, every third view from the third (benchmarks/photometric/bench_photometric_sigma.py's third subset),
    its corner fit as `tiltfit calibrate` makes it (unified, free principal point, opencv5, 5-fold held-out error):
    (target, Observations with the photos' paths as names, result, used, held_out)."""
    sys.path.insert(0, os.path.join(ROOT, "tests"))
    from real_detections import observations

    from tiltfit.calibrate.fit import FitOptions
    from tiltfit.calibrate.photos import fit_with_held_out
    from tiltfit.target.layout import load_target

    folder = os.path.join(ROOT, "data", "real", "gopro_wide")
    target = load_target(os.path.join(folder, "target.json"))
    obs, _ = observations(folder, 0.005)
    sub = obs.subset(range(2, obs.n_views, 3))
    sub.names = [os.path.join(folder, n) for n in sub.names]
    result, used, held_out = fit_with_held_out(sub, "unified", options=FitOptions(
        free_principal_point=True, distortion="opencv5", model_selection=False))
    return target, sub, result, used, held_out


@pytest.fixture(scope="module")
def gopro_third():
    torch.set_num_threads(1)
    return _gopro_third_subset()


def test_grazing_pixels_of_the_box_do_not_empty_the_usable_mask(gopro_third):
    """GOPR0053.jpg under that subset's corner fit: a pixel of its board's box meets the board's plane 255 m away.
    The mask's guard (two pixels' footprint at the longest chief ray) came from it and covered the whole board:
    0 usable pixels, and `refine_photometric` stopped ("view 6: the board covers fewer than 100 usable pixels").
    The guard now comes from the rays that meet the plane near the board: thousands usable, and the pixels far
    off the board do not change the mask of the others."""
    from tiltfit.photometric.render import board_box, usable_pixels

    target, sub, result, _, _ = gopro_third
    k = [os.path.basename(n) for n in sub.names].index("GOPR0053.jpg")
    vc = result.camera.copy().double().view_camera(k)
    x0, y0, x1, y1 = board_box(target, vc)
    yy, xx = np.mgrid[y0:y1 + 1:4, x0:x1 + 1:4]
    uv = torch.tensor(np.stack([xx.ravel(), yy.ravel()], -1), dtype=torch.float64)
    with torch.no_grad():
        rays = vc.generate_rays(uv)
        t = -rays.origin[..., 2] / rays.direction[..., 2]
    assert float(t.abs().max()) > 1e5, f"the case this test is about: a ray meets the plane {float(t.abs().max()):.0f} mm away"
    ok = usable_pixels(target, vc, uv)
    assert ok.sum() > 1000, f"GOPR0053.jpg: {ok.sum()} usable pixels of {len(ok)} on a 4-px grid of its box"
    near = torch.from_numpy(np.asarray(t < 1000.0).copy())
    assert np.array_equal(usable_pixels(target, vc, uv[near]), ok[near.numpy()]), \
        "the pixels whose rays meet the plane far away do not change the others' mask"


def _three_views(gopro_third):
    """The subset's corner fit cut to GOPR0047, GOPR0053 and GOPR0061 (small enough for a test): (target, the
    cut result, its observations, the held-out check)."""
    target, sub, result, used, held_out = gopro_third
    names = [os.path.basename(n) for n in sub.names]
    keep = [names.index(n) for n in ("GOPR0047.jpg", "GOPR0053.jpg", "GOPR0061.jpg")]
    small = copy.copy(result)
    small.camera = _camera_views(result.camera, keep)
    small.views = [copy.deepcopy(result.views[k]) for k in keep]
    small.values, small.sigma, small.rss = dict(result.values), dict(result.sigma), dict(result.rss)
    return target, small, used.subset(keep), held_out


@pytest.mark.slow
def test_real_gopro_subset_end_to_end(gopro_third, capsys):
    """The same subset through the function `tiltfit calibrate --refine photometric -q` runs
    (`tiltfit.cli.photometric.refine_calibration`), on three of its views to stay small (GOPR0047, GOPR0053,
    GOPR0061; the corner fit of all eleven): it finishes, GOPR0053.jpg is fitted (not left out), the block says
    `left_out: []`."""
    from tiltfit.cli.photometric import refine_calibration

    target, small, used, held_out = _three_views(gopro_third)
    assert {"U_mm", "d_mm"} <= set(small.undetermined), f"the GoPro's blur cannot tell U, d: {small.undetermined}"
    args = argparse.Namespace(psf="disc", encoding=None, inputs=small.views[0]["image"], quiet=True)
    block = refine_calibration(small, used, target, args, lambda line: None, held_out=held_out)
    err = capsys.readouterr().err
    # U was held at the start's placeholder (not free), so U and d stay undetermined though the refinement is kept.
    assert block["kept"] == "photometric", f"the case this is about: the refinement kept ({block['rejected_because']})"
    assert "inv_U_per_m" not in block["free"] and {"U_mm", "d_mm"} <= set(small.undetermined), \
        f"free {block['free']}, undetermined {small.undetermined}"
    assert block["left_out"] == [] and "left out" not in err, f"left_out {block['left_out']}; stderr {err!r}"
    assert block["kept"] in ("photometric", "corner fit") and math.isfinite(block["rms_linear"]), f"block {block}"
    assert block["corner_check"]["views"] == 3, f"the corner check scores the three views: {block['corner_check']}"
    assert block["held_out"]["pixels"] == 3 * 300, f"held-out pixels of every view: {block['held_out']}"


@pytest.mark.slow
def test_command_line_path_records_a_left_out_view(gopro_third, capsys, monkeypatch):
    """The same three views with GOPR0053.jpg's mask emptied (as the old guard did):
    `tiltfit.cli.photometric.refine_calibration` under -q prints one note naming the photo and why, records it in
    the block's `left_out`, writes no levels and no `rms_photometric` for it, and fits the other two."""
    from tiltfit.cli.photometric import refine_calibration
    from tiltfit.photometric import pixels

    target, small, used, held_out = _three_views(gopro_third)
    plain, calls = pixels.usable_pixels, []

    def second_view_empty(target, cam, uv, t_max=None):
        calls.append(1)
        ok = plain(target, cam, uv, t_max)
        return ok & False if len(calls) == 2 else ok   # the first pass's second view: GOPR0053.jpg

    monkeypatch.setattr(pixels, "usable_pixels", second_view_empty)
    args = argparse.Namespace(psf="disc", encoding=None, inputs=small.views[0]["image"], quiet=True)
    block = refine_calibration(small, used, target, args, lambda line: None, held_out=held_out)
    notes = [s for s in capsys.readouterr().err.splitlines() if "left out" in s]
    assert len(notes) == 1 and "GOPR0053.jpg" in notes[0] and "0 usable pixels" in notes[0], f"stderr {notes}"
    assert [(e["view"], os.path.basename(e["image"])) for e in block["left_out"]] == [(1, "GOPR0053.jpg")], \
        f"left_out {block['left_out']}"
    assert block["corner_check"]["views"] == 2, f"the two fitted views: {block['corner_check']}"
    if block["kept"] == "photometric":
        assert block["levels"][1] is None and None not in (block["levels"][0], block["levels"][2]), block["levels"]
        assert "rms_photometric" not in small.views[1] and "rms_photometric" in small.views[0], "per-view RMS"
