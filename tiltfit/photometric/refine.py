"""Photometric refinement: fit the calibration's camera and an exposure to the photographs' pixels.

This is the analysis-by-synthesis step. Starting from a corner-and-blur calibration (its `LensCamera`), every
photograph is re-rendered from the current parameters (`render`: the target seen through the camera's thin lens)
and compared with the photo pixel by pixel; the parameters move to make the two agree. Corners are only a
starting point, so their bias under heavy blur and lens tilt does not reach the result, and boards too blurred
for any corner detector can still be fitted.

What is fitted is the corner fit's own camera module: its lens (stored log w, 1/U, d/10 mm, θF) and each view's
pose (axis-angle, T / length scale), plus an `Exposure` (per-view white and black levels, the lens's
vignetting) and, with a Gaussian kernel, the Gaussian's σ. The principal point, the distortion and the pixel
pitch are held. The solver is `tiltfit.solve.levenberg_marquardt` with named blocks (lens, vignetting, psf
global; pose and levels per view, eliminated by the Schur complement), Huber weights on residuals in units of
their robust σ (re-estimated once the fit has moved, and the fit resumed when it changed).

The Jacobian: the exposure enters in closed form; the dark fraction D of a closed-form pixel depends on the
geometry only through each sub-point's focus point and the lens's centre and aperture axes
(`ThinLensCamera.focus_geometry`), so D is differentiated with respect to those per-point inputs by one
reverse pass (the aperture integral is elementwise in the points) and chained with the forward-mode Jacobian
of `focus_geometry` (10 tangents through cheap geometry). Lens-sample pixels likewise: their rays are lines
from the lens points through 4 sub-pixels' focus points, met with the board in closed form, so forward mode
runs through 7 focus points a pixel (the sub-pixels and the footprint's chief rays) and one reverse pass through
the samples' checker (benchmarks/results/photometric_profile.md: forward mode through the aperture integral, then
through the traced rays, was most of the time before).

σ: the per-view cluster-robust covariance of the corner fit (`tiltfit.uncertainty.covariance.view_cluster_covariance`: views
as clusters, each view's pose, levels and illumination profiled out, the CR2 small-sample correction, the
classical covariance as its floor), applied to the Huber fit's weighted residuals and Jacobian. A photograph's
pixels share their errors across the whole view, not only within a blur disc: a board that is not flat or not
the ideal print, a tone curve or an illumination the exposure model misses, move every edge of the view together,
and the lens absorbs them as it absorbs a view's correlated corner errors. Given the start's intrinsics
covariance, σ also carries the held principal point's and distortion's uncertainty (`_held_covariance`). The
textbook Gauss–Newton σ and the earlier sandwich over square tiles as wide as the blur disc stay beside it for
comparison (benchmarks/results/photometric_sigma.md: with per-view errors they are 0.46–0.77 and 0.61–1.02 of
the spread, the per-view σ 0.96–1.12; between real GoPro subsets w moved 25 tile σ, 0.66 of this σ).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from renderer.cameras import LENS_PARAMETERS

from tiltfit.detect.imaging import torch_threads
from tiltfit.calibrate.model import LensCamera
from ..solve import Block, SolverError, covariance
from tiltfit.target.layout import Target
from .render import SHARP_BLUR_PX, SUBPIXELS_SHARP, auto_lens_samples, board_blur_px, hammersley_disc_samples
from .bounds import TRUST_SIGMAS, _bound_record, _trust_region
from .checks import _corner_check, _held_out_costs
from .fit import _camera_of, _lens_values, _select_kernel, _solve
from .options import (AUTO_KERNEL_LENS_SAMPLES, CLOSED_FORM_MIN_BLUR_PX, Exposure, MIN_VIEWS, PSF_START_PX,
                      PhotometricError, PhotometricOptions, PhotometricResult, _ViewsLeftOut)
from .pixels import _choose_pixels
from .problem import _Problem
from .sigma import _cluster_sandwich, _held_covariance, _robust_sigma, _sigma_dict, _view_covariance


#: A free lens parameter whose step is beyond this fraction of its bound (|tanh| > AT_BOUND) is at its bound.
AT_BOUND = 0.95


#: Where the start could not determine the aperture, d starts where the median view's blur disc is this wide (px).
UNDETERMINED_BLUR_PX = 1.0


#: The held-out pixels reject the refinement where their mean Huber cost is higher than the start's by more than
#: this many standard errors of the paired difference (pixel by pixel); equal predictions are a coin flip, not a
#: reason to reject.
HELD_OUT_Z = 2.0


def refine_photometric(images, target: Target, camera: LensCamera, options: PhotometricOptions | None = None,
                       say=None, start_sigma: dict | None = None, corners=None,
                       corner_held_out_px: float | None = None,
                       start_covariance: dict | None = None) -> PhotometricResult:
    """Fit the camera's lens and poses, and an exposure, to the photographs by rendering the target.

    Args:
        images: list of (H, W) or (H, W, 3) linear images (decode sRGB first), one per view of `camera`.
        target: the board.
        camera: the start, a calibration's `LensCamera` (its principal point and distortion are held);
            not modified.
        options: PhotometricOptions.
        say: optional progress callback taking one line.
        start_sigma: the start's one-σ (the corner fit's `sigma`: w_mm, U_mm, d_mm, theta_F_deg). Given, the fit
            moves only the lens parameters the start determined (σ > 0: θF stays where a stage-1 fit held it, U
            and d where the corners could not tell them), each within TRUST_SIGMAS of its σ of the start; None:
            all four free and unbounded.
        corners: the start's `Observations` (corners of the same views). Given, the refinement is also judged
            by them: they are held out of the photometric fit, so its lens (each view's pose refitted to the
            corners) predicts them as the corner fit's lens predicts held-out views; it is kept only where its
            RMS is at most the corner fit's `corner_held_out_px` (its k-fold held-out RMS per corner; None:
            the start's own RMS with its poses refitted) times 1 + CORNER_TOLERANCE.
        start_covariance: the start's `intrinsics_covariance` ({names, matrix}: cx_px, cy_px, k1 … k6 among
            them). Given, σ includes what the uncertainty of the held principal point and distortion does to the
            fitted lens (`_held_covariance`); None: σ is conditional on them.
    Returns:
        PhotometricResult, with the refined camera.
    """
    # One torch thread, as `calibrate`: on a 2-core machine shared with other work OpenMP's spinning threads cost
    # more than they give (`tiltfit calibrate --refine photometric` on 4 industrial photos: 124 s with the default
    # threads, 13 s with one, on 2 shared cores).
    with torch_threads(1):
        return _refine(images, target, camera, options, say, start_sigma, corners, corner_held_out_px,
                       start_covariance)


def _refine(images, target, camera, options, say, start_sigma, corners, corner_held_out_px,
            start_covariance=None) -> PhotometricResult:
    """`refine_photometric`'s stages: the start, the pixels, the problem and its solve, the σ, the verdict (kept or
    not, and why), the result."""
    opts = options or PhotometricOptions()
    t0 = time.perf_counter()
    imgs = _grey_images(images, target, camera)
    cam, free, bound = _start_camera(camera, target, start_sigma)
    views = [cam.view_camera(v) for v in range(cam.n_views)]
    opts, disc_only, n_samples = _aperture_plan(cam, views, target, opts)
    lens_uv = hammersley_disc_samples(n_samples)
    try:
        data, held_data, levels = _choose_pixels(imgs, views, target, opts, disc_only, say, t0)
    except _ViewsLeftOut as e:
        return _without_views(e.views, imgs, target, camera, options, say, start_sigma, corners, corner_held_out_px,
                              start_covariance, t0)
    pixels = _pixel_record(data, n_samples, say)
    problem = _Problem(cam, target, data, lens_uv, say)
    if free is not None:
        problem.free, problem.bound = free, bound
    problem.camera_of = lambda x, v: _camera_of(cam.copy(), x, problem).view_camera(v)
    x0, blocks = _start_state(problem, cam, levels, opts)
    view_rows = torch.arange(len(imgs) * pixels.n_rows).reshape(len(imgs), pixels.n_rows)
    history = []
    res, iterations = _solve(problem, x0, blocks, view_rows, opts, history)
    scale = problem.scale
    selection = None
    if opts.kernel == "auto":
        res, iterations, scale, selection = _select_kernel(problem, res, iterations, blocks, view_rows, opts,
                                                           history, say)
    cov_tiles = _cluster_sandwich(res, problem)
    r = res.r * scale
    s_final = _robust_sigma(r)
    try:
        cov_gn = covariance(res, (s_final / scale) ** 2).dense()
    except SolverError:
        cov_gn = torch.full_like(cov_tiles, math.nan)
    verdict = _Verdict()
    refined = _camera_of(camera.copy(), res.x, problem)
    if opts.held_out_pixels:
        verdict.held_out = _held_out_costs(problem, held_data, res.x, x0, opts, scale)
        verdict.reject(_held_out_reason(verdict.held_out))
    verdict.at_bound, held = _at_bound(problem, res)
    cov_sigma, sigma_model = _view_covariance(res, (s_final / scale) ** 2, cov_tiles, held)
    cov_held = _held_covariance(problem, res, start_covariance) if not verdict.at_bound else None
    sigma_model["held_propagated"] = cov_held is not None
    if cov_held is not None:
        cov_sigma = cov_sigma + cov_held
    if verdict.at_bound:
        verdict.reject(_bound_reason(problem, res, verdict.at_bound))
    if corners is not None:
        verdict.corner_check = _corner_check(refined, camera, corners, corner_held_out_px, len(problem.free))
        verdict.reject(_corner_reason(verdict.corner_check))
    _say_verdict(say, verdict)
    covs = {"sigma": cov_sigma, "gn": cov_gn, "tiles": cov_tiles, "held": cov_held}
    return _result(camera, refined, problem, res, r, view_rows, pixels, iterations, history, selection, covs,
                   sigma_model, verdict, t0)


def _grey_images(images, target: Target, camera: LensCamera) -> list:
    """The photographs as float64 grey images (H, W) (the channels' mean), after the checks that the refinement
    can take them: some images, a checkerboard, one image a view."""
    imgs = [np.asarray(im, dtype=np.float64) for im in images]
    imgs = [im.mean(-1) if im.ndim == 3 else im for im in imgs]
    if not imgs:
        raise PhotometricError("no images to refine")
    if target.dark_rectangles():
        raise PhotometricError("target: the photometric model renders checkerboards; a ChArUco board's markers "
                               "are not modelled (use the corner-and-blur calibration)")
    if camera.n_views != len(imgs):
        raise PhotometricError(f"the camera has {camera.n_views} views for {len(imgs)} images")
    return imgs


def _start_camera(camera: LensCamera, target: Target, start_sigma: dict | None):
    """(the start: a float64 copy of `camera` with a lens the photometric model can render; the free lens
    parameters and their bounds, None without `start_sigma`, see `_trust_region`)."""
    cam = camera.copy().double()
    for p in cam.parameters():
        p.requires_grad_(False)
    with torch.no_grad():   # a lens the photometric model can render: finite focus, a non-zero aperture
        cam.inv_U_per_m.clamp_(min=1e-3)
        cam.d_scaled.copy_(cam.d_scaled.abs().clamp(min=1e-4))
    free = bound = None
    if start_sigma is not None:
        free, bound = _trust_region(cam, start_sigma)
        if 2 not in free:
            # The corners could not tell the aperture (a lens in focus everywhere, U and d undetermined): a
            # placeholder d would render blur that is not there, so d starts where the views' median blur disc
            # is UNDETERMINED_BLUR_PX and is fitted (unbounded) with U held.
            b = float(np.median([board_blur_px(cam.view_camera(v), target) for v in range(cam.n_views)]))
            with torch.no_grad():
                cam.d_scaled.mul_(UNDETERMINED_BLUR_PX / max(b, 1e-9))
            free, bound = sorted(free + [2]), bound.clone()
            bound[2] = math.inf
    return cam, free, bound


def _aperture_plan(cam: LensCamera, views: list, target: Target, opts: PhotometricOptions):
    """(the options, the closed form on a distorted lens; whether every pixel may take the closed-form disc;
    the fixed lens samples a pixel of the others)."""
    blur = max(board_blur_px(vc, target) for vc in views)
    disc_only = opts.kernel == "disc" and opts.aperture != "samples"
    if disc_only and opts.aperture == "auto" and bool((cam.distortion.detach() != 0).any()):
        # A distorted lens: every lens sample of every sub-pixel would be undistorted on its own (256 a pixel),
        # 10-40 times the closed form's time on real photographs; the closed form models the pixel's box by
        # 4 x 4 points (on sharp synthetic boards about 2σ of θL worse than the samples' Gaussian footprints).
        opts = replace(opts, aperture="closed_form")
    n_samples = opts.lens_samples
    if not disc_only and n_samples == 0:
        n_samples = auto_lens_samples(blur, AUTO_KERNEL_LENS_SAMPLES if opts.kernel == "auto" else 64)
    elif n_samples == 0:
        n_samples = auto_lens_samples(CLOSED_FORM_MIN_BLUR_PX)   # for the sharper pixels only
    return opts, disc_only, n_samples


@dataclass(frozen=True)
class _Pixels:
    """The fitted pixels: per view (`n_rows`), in all, in closed form, how the aperture is integrated
    (closed_form, samples or mixed) and the fixed lens samples a pixel of the others."""
    n_rows: int
    n_pixels: int
    n_closed: int
    aperture: str
    n_samples: int


def _pixel_record(data: list, n_samples: int, say) -> _Pixels:
    """The `_Pixels` of the chosen views' data, said in one progress line."""
    n_rows = int(data[0].uv.shape[0])
    n_closed = sum(d.n_closed_form for d in data)
    n_pixels = sum(int(d.uv.shape[0]) for d in data)
    aperture = "closed_form" if n_closed == n_pixels else "samples" if n_closed == 0 else "mixed"
    if say:
        say(f"photometric: {len(data)} views, {n_pixels} pixels, aperture "
            + {"closed_form": f"in closed form (4x4 points per pixel, {SUBPIXELS_SHARP}x{SUBPIXELS_SHARP} for the "
                              f"{sum(d.n_sharp for d in data)} blurred less than {SHARP_BLUR_PX:g} px)",
               "samples": f"by {n_samples} lens samples per pixel",
               "mixed": f"in closed form for {n_closed} pixels (blur from {CLOSED_FORM_MIN_BLUR_PX:g} px), "
                        f"by {n_samples} lens samples for the other {n_pixels - n_closed}"}[aperture])
    return _Pixels(n_rows, n_pixels, n_closed, aperture, n_samples)


def _start_state(problem: _Problem, cam: LensCamera, levels: list, opts: PhotometricOptions):
    """(the solver's start {block: tensor}, its `Block`s): the lens's free parameters, each view's pose and levels,
    the illumination gradient, the vignetting and the Gaussian kernel's σ where they are fitted."""
    V = cam.n_views
    psf0 = PSF_START_PX if opts.kernel == "disc_gaussian" else 0.0
    x0 = {"lens": torch.zeros(len(problem.free), dtype=torch.float64),
          "pose": torch.cat([cam.rvec.detach(), cam.T_scaled.detach()], 1),
          "levels": torch.tensor(levels, dtype=torch.float64)}
    blocks = [Block("lens", (len(problem.free),)), Block("pose", (V, 6), per_view=True),
              Block("levels", (V, 2), per_view=True)]
    if opts.illumination == "gradient":
        x0["gain"] = torch.zeros(V, 2, dtype=torch.float64)
        blocks.append(Block("gain", (V, 2), per_view=True))
    if opts.fit_vignetting:
        x0["vignetting"] = torch.zeros(1, dtype=torch.float64)
        blocks.append(Block("vignetting", (1,)))
    problem.psf_fixed = psf0
    if opts.kernel == "disc_gaussian":
        x0["psf"] = torch.tensor([psf0], dtype=torch.float64)
        blocks.append(Block("psf", (1,)))
    return x0, blocks


@dataclass
class _Verdict:
    """Whether the refinement is kept ("photometric") or the corner fit ("corner fit"), and why: the held-out
    pixels' costs, the lens parameters at their trust bound, the held-out corners' check."""
    kept: str = "photometric"
    reasons: list = field(default_factory=list)
    held_out: dict | None = None
    at_bound: list = field(default_factory=list)
    corner_check: dict | None = None

    def reject(self, reason: str | None) -> None:
        """Keep the corner fit for `reason` (None: no objection)."""
        if reason is not None:
            self.kept = "corner fit"
            self.reasons.append(reason)


def _held_out_reason(held_out: dict) -> str | None:
    """Why the held-out pixels reject the refinement (it costs more than HELD_OUT_Z standard errors above the
    corner fit), or None."""
    if held_out["refined"] - held_out["start"] > HELD_OUT_Z * held_out["difference_se"]:
        return (f"held-out pixels cost {held_out['refined']:.4g} refined, {held_out['start']:.4g} "
                f"for the corner fit (more than {HELD_OUT_Z:g} standard errors, "
                f"{held_out['difference_se']:.2g}, apart)")
    return None


def _at_bound(problem: _Problem, res) -> tuple[list, list]:
    """(the free lens parameters within AT_BOUND of their trust bound, their indices in the solver's flat order)."""
    at_bound = []
    if problem.free:
        b = problem.bound[problem.free]
        t = torch.tanh(res.x["lens"].detach() / b.clamp(max=1e300))
        at_bound = [LENS_PARAMETERS[i] for i, bi, ti in zip(problem.free, b, t)
                    if math.isfinite(float(bi)) and abs(float(ti)) > AT_BOUND]
    held = []
    if at_bound:
        a = res.layout.offsets["lens"][0]
        held = [a + problem.free.index(LENS_PARAMETERS.index(n)) for n in at_bound]
    return at_bound, held


def _bound_reason(problem: _Problem, res, at_bound: list) -> str:
    """Why lens parameters at their trust bound reject the refinement, naming each with its bound."""
    hit = "; ".join(f"{e['parameter']} {e['refined']:.6g} at the bound [{e['low']:.6g}, {e['high']:.6g}] "
                    f"(start {e['start']:.6g})" for e in _bound_record(problem, res.x["lens"], at_bound)
                    if e["at_bound"])
    return (f"{', '.join(at_bound)} at the trust bound ({hit}; the refinement is held within "
            f"{TRUST_SIGMAS:g}σ of the corner fit): the pixels and the corners disagree beyond what "
            "either's σ allows")


def _corner_reason(corner_check: dict) -> str | None:
    """Why the held-out corners reject the refinement (`_corner_check` above its limit), or None."""
    if not corner_check["refined_px"] <= corner_check["limit_px"]:
        return (f"held-out corners RMS {corner_check['refined_px']:.4f} px refined, "
                f"{corner_check['start_px']:.4f} px for the corner fit")
    return None


def _say_verdict(say, verdict: _Verdict) -> None:
    """One progress line: what the checks measured and whether the refinement is kept."""
    held_out, corner_check, at_bound = verdict.held_out, verdict.corner_check, verdict.at_bound
    if say and (held_out is not None or corner_check is not None or at_bound):
        parts = [f"{', '.join(at_bound)} at the trust bound"] if at_bound else []
        if held_out is not None:
            parts.append(f"held-out pixels ({held_out['pixels']}) cost {held_out['refined']:.4g} refined, "
                         f"{held_out['start']:.4g} from the start")
        if corner_check is not None:
            parts.append(f"corners (held out of the photometric fit) RMS {corner_check['refined_px']:.4f} px "
                         f"refined, {corner_check['start_px']:.4f} px the corner fit's held-out")
        say("photometric: " + "; ".join(parts) + ": keeping the "
            + ("refinement" if verdict.kept == "photometric" else "start (the corner fit)"))


def _result(camera: LensCamera, refined: LensCamera, problem: _Problem, res, r, view_rows, pixels: _Pixels,
            iterations: int, history: list, selection, covs: dict, sigma_model: dict, verdict: _Verdict,
            t0: float) -> PhotometricResult:
    """The `PhotometricResult`: the refined camera and exposure, the values, σ under each error model, each
    view's pose, levels and RMS, and the verdict."""
    kernel = "disc_gaussian" if "psf" in res.x else "disc"
    lens_full = problem.full_lens(res.x["lens"])
    exposure = Exposure(res.x["levels"], float(res.x["vignetting"][0]) if "vignetting" in res.x else 0.0,
                        res.x.get("gain"))
    values = {**_lens_values(lens_full), "inv_U_per_m": float(lens_full[LENS_PARAMETERS.index("inv_U_per_m")]),
              "vignetting": float(exposure.vignetting.detach()), "psf_sigma_px": abs(float(res.x["psf"][0])) if "psf" in res.x
              else 0.0, "kernel": kernel, "lens_samples": pixels.n_samples if pixels.aperture != "closed_form" else 0,
              "aperture": pixels.aperture, "closed_form_pixels": pixels.n_closed}
    out_views = []
    with torch.no_grad():
        for v in range(view_rows.shape[0]):
            rv = r[view_rows[v]]
            out_views.append({"R": refined.R[v].numpy().copy(), "T_mm": refined.T_mm[v].numpy().copy(),
                              "white": float(res.x["levels"][v, 0]), "black": float(res.x["levels"][v, 1]),
                              "rms": float(torch.sqrt((rv * rv).mean())), "n_pixels": pixels.n_rows,
                              **({"gain_x": float(res.x["gain"][v, 0]), "gain_y": float(res.x["gain"][v, 1])}
                                 if "gain" in res.x else {})})
    free = [LENS_PARAMETERS[i] for i in problem.free]
    bounds = _bound_record(problem, res.x["lens"], verdict.at_bound)
    cov_held = covs["held"]
    return PhotometricResult(refined, exposure, values, _sigma_dict(res, covs["sigma"], problem), out_views,
                             float(torch.sqrt((r * r).mean())), iterations, time.perf_counter() - t0, history,
                             selection, _sigma_dict(res, covs["gn"], problem), verdict.kept, verdict.held_out,
                             camera.copy(), verdict.corner_check, "; ".join(verdict.reasons), free, verdict.at_bound,
                             _sigma_dict(res, covs["tiles"], problem), sigma_model,
                             _sigma_dict(res, cov_held, problem) if cov_held is not None else None,
                             bounds=bounds)


def _camera_views(camera: LensCamera, views: list) -> LensCamera:
    """A copy of `camera` with the listed views' poses only."""
    sub = camera.copy()
    for name in ("rvec", "T_scaled"):
        p = getattr(camera, name)
        setattr(sub, name, torch.nn.Parameter(p.detach()[views].clone(), requires_grad=p.requires_grad))
    return sub


def _without_views(left_out: list, imgs: list, target: Target, camera: LensCamera, options, say, start_sigma,
                   corners, corner_held_out_px, start_covariance, t0: float) -> PhotometricResult:
    """The refinement on the views not in `left_out` ((index, reason) pairs), exactly as if only they had been
    given; the left-out views' poses stay the start's. Stops where fewer than MIN_VIEWS remain."""
    names = list(corners.names) if corners is not None else None

    def label(k):
        return f"view {k}" + (f" ({names[k]})" if names else "")

    out = {k for k, _ in left_out}
    keep = [k for k in range(len(imgs)) if k not in out]
    if len(keep) < MIN_VIEWS:
        k, why = left_out[0]
        raise PhotometricError(f"no view left to fit ({len(left_out)} of {len(imgs)} left out; {label(k)}: {why}"
                               + (", …" if len(left_out) > 1 else "") + ")")
    for k, why in left_out:
        if say:
            say(f"photometric: {label(k)} left out of the fit (its pose stays the start's): {why}")
    res = _refine([imgs[k] for k in keep], target, _camera_views(camera, keep), options, say, start_sigma,
                  corners.subset(keep) if corners is not None else None, corner_held_out_px, start_covariance)
    # Back to every view: the fitted views' poses from the refinement, the left-out ones' the start's.
    full, start = camera.copy(), camera.copy()
    with torch.no_grad():
        full.load_state_dict({k: v for k, v in res.camera.state_dict().items() if k not in ("rvec", "T_scaled")},
                             strict=False)
        full.rvec[keep] = res.camera.rvec.detach().to(full.rvec)
        full.T_scaled[keep] = res.camera.T_scaled.detach().to(full.T_scaled)
    views = [None] * len(imgs)
    for k, v in zip(keep, res.views):
        views[k] = v
    reasons = dict(left_out)
    for k in out:
        views[k] = {"R": start.R[k].detach().numpy().copy(), "T_mm": start.T_mm[k].detach().numpy().copy(),
                    "left_out": reasons[k], "n_pixels": 0}
    # Views the inner run left out in turn (its own pixel draws): their indices back to this run's.
    inner = [(keep[e["view"]], e["reason"]) for e in res.left_out]
    res.camera, res.start_camera, res.views = full, start, views
    res.left_out = [{"view": k, **({"image": names[k]} if names else {}), "reason": why}
                    for k, why in sorted(left_out + inner)]
    res.runtime_s = time.perf_counter() - t0
    return res
