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
of `focus_geometry` (10 tangents through cheap geometry). Lens-sample pixels take forward mode through their
rays (benchmarks/results/photometric_profile.md: forward mode through the aperture integral was 78 % of the
time before).

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

from renderer.cameras import (LENS_PARAMETERS, Lens, U_from_stored, d_from_stored, image_centre_px, lens_values,
                              stored_lens_sigma, w_from_stored)
from renderer.cameras.optics import theta_L_from_theta_F

from tiltfit.photometric.aperture import checker_dark_fraction_disc, lines_cut
from tiltfit.detect.imaging import torch_threads
from tiltfit.calibrate.model import LensCamera, axis_angle_to_matrix, robust_rho, robust_weight
from ..solve import (Block, LMOptions, SolverError, covariance, dense_jacobian, least_squares,
                     levenberg_marquardt, solve_rescaling)
from tiltfit.select.stats import nested_test
from tiltfit.target.layout import Target
from .render import (SHARP_BLUR_PX, SUBPIXELS, SUBPIXELS_SHARP, auto_lens_samples, board_blur_px,
                     dark_fraction_samples, hammersley_disc_samples, on_board, pixel_blur_px, predicted_dark_fraction,
                     sub_points, board_box, usable_pixels)

#: Blur kernels: the lens's disc alone, or the disc convolved with a Gaussian (diffraction, aberrations,
#: the sensor's own spread) of std psf_sigma_px in pixels (stored signed, squared in the model, so it has no
#: bound to stall on); `auto` frees the Gaussian where the data justify it (likelihood-ratio test and BIC on
#: the same pixels) and it is at least PSF_EVIDENCE_PX wide.
KERNELS = ("disc", "disc_gaussian", "auto")
AUTO_KERNEL_LENS_SAMPLES = 128
PSF_EVIDENCE_PX = 0.5    # narrower Gaussians `auto` rejects: the fixed lens samples' own coarseness
PSF_START_PX = 0.5       # where a freed Gaussian starts (σ = 0 is a stationary point of σ²)
#: `aperture="auto"` integrates the disc in closed form from this blur-disc diameter (px) at the start on (with
#: 8 x 8 points per pixel below render.SHARP_BLUR_PX), the fixed lens samples below it. Measured against a 40 x 40
#: grid of the closed form (benchmarks/results/photometric_forward_extras.md, "pixel quadrature"), the 8 x 8 closed
#: form is nearer than the 64 (and 256) lens samples' Gaussian footprints at every blur size: the d a fit would take
#: −0.05 % against +0.28 % at 1.5 px facing, −0.07 % against +17 % on a tilted, inclined board at 0-0.5 px (the
#: footprints' Gaussian is not the box where the disc is sub-pixel), −0.23 % against −0.30 % at 1 px facing; and
#: cheaper (0.14 s against 0.17 s for 629 pixels). So 0: the disc kernel is integrated in closed form at every
#: pixel (it was 3 px; the lens samples remain for the Gaussian kernels and `aperture="samples"`).
CLOSED_FORM_MIN_BLUR_PX = 0.0
APERTURES = ("auto", "closed_form", "samples")
#: Pixels per block of the Jacobian (bounds its memory; results do not depend on it).
JACOBIAN_BLOCK = 2048
#: Candidate pixels of a view whose brightness is predicted before picking the pixels to fit: at most this many
#: drawn at random from the board's bounding box (a 1280 x 1024 photo's board has about 700,000: predicting all
#: of them took most of the 30-60 s of set-up a view).
MAX_CANDIDATE_PIXELS = 1 << 16
# The camera's stored lens parameters the fit moves, in the order of the `lens` block: `LENS_PARAMETERS`, the lens
# vector of `renderer.cameras.lens_model` (which decodes it: `lens_values`).
#: Illumination models of `PhotometricOptions.illumination`.
ILLUMINATIONS = ("flat", "gradient")
#: With the start's σ (`refine_photometric(start_sigma=...)`), each free lens parameter stays within this many of
#: its σ of the start (a smooth bound, start + b tanh(z / b)): the pixels cannot carry the lens far from what the
#: corners say (unbounded, stage-1 fits of real photos drifted to θF ≈ 60-80°).
TRUST_SIGMAS = 10.0
#: A free lens parameter whose step is beyond this fraction of its bound (|tanh| > AT_BOUND) is at its bound.
AT_BOUND = 0.95
#: Where the start could not determine the aperture, d starts where the median view's blur disc is this wide (px).
UNDETERMINED_BLUR_PX = 1.0
#: The refinement is kept only where its RMS on the (held-out) corners is at most 1 + this times the corner
#: fit's held-out RMS.
CORNER_TOLERANCE = 0.02
#: Without the corner fit's held-out RMS the corners are compared in sample (the corner fit minimised their cost, so
#: any other lens costs more): kept while the cost rises by at most the χ² quantile of this level for the free lens
#: parameters, in units of the corners' own noise: the refined lens inside the corner fit's confidence region.
#: (A tolerance of 2 % on the RMS rejected refinements one corner-fit σ from the start, where the corners were
#: few: on 2 heavy-blur views, 0.0210 against 0.0207 px, the refinement nearer the truth in w, U and d;
#: benchmarks/results/photometric_refine.md.)
CORNER_CONFIDENCE = 0.99
#: The held-out pixels reject the refinement where their mean Huber cost is higher than the start's by more than
#: this many standard errors of the paired difference (pixel by pixel); equal predictions are a coin flip, not a
#: reason to reject.
HELD_OUT_Z = 2.0
#: Relative cost decrease at which a solve has converged: thousands of pixels put the cost in the thousands, and a
#: step that lowers it by less moves the lens by a few hundredths of its σ (the solver's default, 1e-7, spent
#: half of a real photo's iterations there).
SOLVE_FTOL = 1e-5
#: A fit whose robust residual σ moved by more than this fraction resumes with the new σ (the Huber weights).
SCALE_TOLERANCE = 0.05
#: A view needs at least this many usable pixels (blur disc on the board inside its margin, not saturated) to
#: take part in the fit; a view with fewer is left out of it (its pose stays the start's).
MIN_USABLE_PIXELS = 100
#: Views the fit needs: with fewer left after leaving out those without enough usable pixels, it stops.
MIN_VIEWS = 1


class PhotometricError(RuntimeError):
    """The photometric fit cannot run or did not converge (one-line message)."""


class _ViewsLeftOut(Exception):
    """Raised by `_choose_pixels`: these views (index, reason) cannot take part in the fit."""

    def __init__(self, views: list):
        super().__init__(f"{len(views)} views left out")
        self.views = views


@dataclass(frozen=True)
class PhotometricOptions:
    """How the refinement runs.

    Attributes:
        lens_samples: fixed lens samples per pixel [64] (a whitened Hammersley set), each traced from the
            pixel's 4 sub-pixel centres; 0: from the start's blur (`render.auto_lens_samples`).
        max_pixels: pixels used per view [2000], chosen where the image carries information (edges), plus
            a share of flat pixels for the exposure levels.
        iterations: Levenberg–Marquardt iterations at most [30].
        huber_scale: Huber threshold in units of the residuals' robust σ [3].
        fit_vignetting: fit the vignetting coefficient [True].
        kernel: blur kernel, one of KERNELS [disc]. `auto` needs at least AUTO_KERNEL_LENS_SAMPLES lens
            samples and a Gaussian of at least PSF_EVIDENCE_PX (docs/photometric.md).
        alpha: level of the kernel's likelihood-ratio test under `auto` [0.01].
        seed: seed of the pixel selection [0].
        aperture: how each pixel integrates the lens's disc, one of APERTURES [auto]: `closed_form` exactly
            (disc kernel only), `samples` by the fixed lens samples, `auto` the closed form for the pixels whose
            blur disc at the start is at least CLOSED_FORM_MIN_BLUR_PX (with the disc kernel), the samples for
            the others; with a distorted lens (any non-zero coefficient) the closed form for all pixels.
        held_out_pixels: pixels per view kept out of the fit [300], chosen as the fitted ones are; the refinement
            is kept only where it predicts them better than the start's lens and poses do (with the exposure
            fitted to the same pixels as the refinement's); 0: always kept.
        saturation: pixels at least this fraction of the view's brightest are left out (glare, clipped
            highlights) [0.995]; None: none left out.
        illumination: one of ILLUMINATIONS [gradient]: `flat` the per-view white and black levels and the
            vignetting only; `gradient` also a linear gain across each view (1 + g_x x + g_y y).
    """

    lens_samples: int = 64
    max_pixels: int = 2000
    iterations: int = 30
    huber_scale: float = 3.0
    fit_vignetting: bool = True
    kernel: str = "disc"
    alpha: float = 0.01
    seed: int = 0
    aperture: str = "auto"
    held_out_pixels: int = 300
    saturation: float | None = 0.995
    illumination: str = "gradient"

    def __post_init__(self):
        if self.illumination not in ILLUMINATIONS:
            raise ValueError(f"illumination: expected one of {', '.join(ILLUMINATIONS)}, got {self.illumination!r}")
        if self.held_out_pixels < 0:
            raise ValueError(f"held_out_pixels: expected 0 or a positive count, got {self.held_out_pixels}")
        if self.lens_samples < 0:
            raise ValueError(f"lens_samples: expected 0 (auto) or a positive count, got {self.lens_samples}")
        if self.kernel not in KERNELS:
            raise ValueError(f"kernel: expected one of {', '.join(KERNELS)}, got {self.kernel!r}")
        if self.aperture not in APERTURES:
            raise ValueError(f"aperture: expected one of {', '.join(APERTURES)}, got {self.aperture!r}")
        if self.aperture == "closed_form" and self.kernel != "disc":
            raise ValueError(f"aperture closed_form: integrates the disc kernel only, got kernel {self.kernel!r}")
        if self.kernel == "auto" and 0 < self.lens_samples < AUTO_KERNEL_LENS_SAMPLES:
            raise ValueError(f"kernel auto: needs at least {AUTO_KERNEL_LENS_SAMPLES} lens samples (got "
                             f"{self.lens_samples}); fewer make the disc itself look Gaussian-blurred")


class Exposure(torch.nn.Module):
    """How the board's dark fraction D becomes a photograph's linear intensity:
    I = (1 − v ρ²) (1 + g_x,k x + g_y,k y) · (white_k − (white_k − black_k) · D) (`render.shade`; x, y the pixel
    about the image centre, ±1 at the edges: the illumination's gradient across view k, or a tilted board's
    reflectance).

    Attributes:
        levels: (V, 2) per view the radiance of white paper and of the dark cells (linear units).
        vignetting: () v, the lens's fall-off at the image corners.
        gain: (V, 2) per view the illumination's gradient (g_x, g_y) (zeros without `illumination="gradient"`).
    """

    def __init__(self, levels, vignetting: float = 0.0, gain=None):
        super().__init__()
        self.levels = torch.nn.Parameter(torch.as_tensor(levels, dtype=torch.float64).reshape(-1, 2).clone())
        self.vignetting = torch.nn.Parameter(torch.tensor(float(vignetting), dtype=torch.float64))
        g = torch.zeros_like(self.levels) if gain is None else torch.as_tensor(gain, dtype=torch.float64).reshape(-1, 2)
        self.gain = torch.nn.Parameter(g.detach().clone())


@dataclass
class PhotometricResult:
    """What `refine_photometric` found.

    Attributes:
        camera: the refined `LensCamera` (a copy of the start's, lens and poses moved).
        exposure: the fitted `Exposure`.
        values: w_mm, U_mm (inf when 1/U = 0), inv_U_per_m, d_mm, theta_F_deg, theta_L_deg, vignetting,
            psf_sigma_px (σ of the Gaussian part of the kernel, 0 for the disc alone), kernel, lens_samples,
            aperture, closed_form_pixels.
        sigma: one-σ of the same keys under the error model `sigma_model` (per-view cluster-robust).
        sigma_gauss_newton: the textbook σ, (JᵀWJ)⁻¹ scaled by the residuals' robust σ (kept for comparison).
        sigma_tiles: the sandwich over square tiles as wide as the blur disc (kept for comparison).
        sigma_model: the error model of `sigma`: {name: "views" | "tiles" (fewer than 2 views, or the per-view
            covariance singular), design_effect, ratio_min, ratio_max, n_views (`tiltfit.uncertainty.covariance`),
            held_propagated: whether `sigma` includes the held principal point's and distortion's uncertainty}.
        sigma_held: with `start_covariance`, the part of `sigma` the held principal point and distortion
            contribute alone (`sigma`² = conditional² + held²); `sigma_tiles` and `sigma_gauss_newton` are
            conditional on them.
        views: per view: R (3×3), T_mm, white, black, rms (linear units), n_pixels.
        rms: RMS photometric residual over all views (linear intensity units).
        iterations, runtime_s, history: LM iterations, wall time, cost of each solve (½ Σ ρ of residuals in
            units of their robust σ).
        kernel_selection: under kernel `auto`, the test that chose the kernel (Λ, p, ΔBIC, costs).
        kept: "photometric" where the refinement predicts the held-out pixels better than the start did and, with
            `corners`, the corners about as well as the corner fit predicts held-out views, else "corner fit"
            (`PhotometricOptions.held_out_pixels`); `chosen_camera` is that camera.
        held_out: pixels, and mean Huber cost of their residuals (in units of the fit's robust σ) for the
            refinement and for the start (its lens and poses, the exposure fitted with them held).
        start_camera: the camera the refinement started from (a copy).
        corner_check: with `corners`: start_px (the corner fit's held-out RMS per corner), refined_px (the
            refinement's lens, poses refitted to the corners), limit_px, views; else None.
        rejected_because: why the start was kept ("" where the refinement is).
        free: the stored lens parameters the fit moved (`start_sigma`).
        at_bound: those of them that ended at their trust bound (then the start is kept, and their σ is 0).
        left_out: the views left out of the fit, each {view (index), image (the corners' name, where given),
            reason}: too few usable pixels (fewer than MIN_USABLE_PIXELS whose blur disc lies on the board inside
            its margin, saturated ones dropped) or no board on the image at the start. Their poses in `camera` stay
            the start's, and `views` holds {R, T_mm, left_out: reason} for them; the fit is the one the other views
            alone give.
        bounds: per free lens parameter with a trust bound, {parameter (w_mm, U_mm, d_mm or theta_F_deg), start,
            low, high (the bound's ends, same units), refined, at_bound}: which parameter hit which bound.
    """

    camera: LensCamera
    exposure: Exposure
    values: dict
    sigma: dict
    views: list
    rms: float
    iterations: int
    runtime_s: float
    history: list = field(default_factory=list)
    kernel_selection: dict | None = None
    sigma_gauss_newton: dict | None = None
    kept: str = "photometric"
    held_out: dict | None = None
    start_camera: LensCamera | None = None
    corner_check: dict | None = None
    rejected_because: str = ""
    free: list = field(default_factory=lambda: list(LENS_PARAMETERS))
    at_bound: list = field(default_factory=list)
    sigma_tiles: dict | None = None
    sigma_model: dict = field(default_factory=dict)
    sigma_held: dict | None = None
    left_out: list = field(default_factory=list)
    bounds: list = field(default_factory=list)

    @property
    def chosen_camera(self) -> LensCamera:
        """The refined camera where the held-out pixels kept it, else the start's (`kept`)."""
        return self.camera if self.kept == "photometric" else self.start_camera


@dataclass
class _View:
    uv: torch.Tensor          # (N, 2) pixels used
    observed: torch.Tensor    # (N,) linear intensities
    n_closed_form: int        # the first n_closed_form pixels integrate the aperture in closed form
    rho2: torch.Tensor        # (N,) squared distance from the image centre, 1 at the corners
    xy: torch.Tensor | None = None   # (N, 2) pixel coordinates about the image centre, ±1 at the edges
    n_sharp: int = 0          # the first n_sharp of them with SUBPIXELS_SHARP points a side (blur < SHARP_BLUR_PX)


class _ViewGeometry(torch.nn.Module):
    """The camera under `torch.func.functional_call`: `fn(camera.view_camera(view))` with substituted tensors."""

    def __init__(self, camera: LensCamera):
        super().__init__()
        self.camera = camera

    def forward(self, view: int, fn):
        return fn(self.camera.view_camera(view))


def _select_pixels(predicted: np.ndarray, usable: np.ndarray, white: float, black: float, max_pixels: int,
                   rng: np.random.Generator) -> np.ndarray:
    """Indices (flat) of the pixels to fit: mostly transitions (edges, blur), some flat ones for the levels."""
    span = max(white - black, 1e-6)
    frac = (white - predicted) / span
    edge = usable & (frac > 0.03) & (frac < 0.97)
    flat = usable & ~edge
    idx_edge, idx_flat = np.flatnonzero(edge), np.flatnonzero(flat)
    n_edge = min(idx_edge.size, int(0.8 * max_pixels))
    n_flat = min(idx_flat.size, max_pixels - n_edge)
    pick = [rng.choice(idx_edge, n_edge, replace=False) if n_edge else idx_edge[:0],
            rng.choice(idx_flat, n_flat, replace=False) if n_flat else idx_flat[:0]]
    return np.sort(np.concatenate(pick))


def _initial_levels(vals: np.ndarray) -> tuple[float, float]:
    return float(np.percentile(vals, 97)), float(np.percentile(vals, 3))


class _Problem:
    """The photometric least-squares problem: pixels of every view, the camera they are rendered with, and
    `evaluate` in the solver's form (residuals in units of `scale`, Jacobians by block)."""

    def __init__(self, camera: LensCamera, target: Target, data: list, lens_uv: torch.Tensor, say=None):
        self.camera, self.target, self.data, self.lens_uv = camera, target, data, lens_uv
        self.geometry = _ViewGeometry(camera)
        self.near = 1
        self.n_edges = max(len(target.x_edges), len(target.y_edges))
        self.scale = 1.0
        self.psf_fixed = 0.0
        self.say, self.t0, self.n_jacobians = say, time.perf_counter(), 0
        self.lens_start = torch.stack([getattr(camera, n).detach() for n in LENS_PARAMETERS]).to(torch.float64)
        self.free = list(range(4))                     # the stored lens parameters the fit moves
        self.bound = torch.full((4,), math.inf, dtype=torch.float64)

    # --- the lens block: the free stored parameters, each within ±bound of the start (smoothly, by tanh) -----
    def full_lens(self, z: torch.Tensor) -> torch.Tensor:
        """(4,) stored lens parameters of the solver's lens block z (len(free),): start + b tanh(z / b)."""
        lens = self.lens_start.clone()
        if self.free:
            b = self.bound[self.free]
            step = torch.where(torch.isfinite(b), b * torch.tanh(z / b.clamp(max=1e300)), z)
            lens[self.free] = self.lens_start[self.free] + step
        return lens

    def lens_jacobian(self, z: torch.Tensor) -> torch.Tensor:
        """(4, len(free)) d full_lens / dz."""
        J = torch.zeros(4, len(self.free), dtype=torch.float64)
        if self.free:
            b = self.bound[self.free]
            d = torch.where(torch.isfinite(b), 1.0 / torch.cosh(z / b.clamp(max=1e300)) ** 2, torch.ones_like(z))
            J[self.free, torch.arange(len(self.free))] = d
        return J

    # --- the camera of a state -----------------------------------------------------------------------------
    def _params(self, v: int, lens: torch.Tensor, pose: torch.Tensor) -> dict:
        rv, Ts = self.camera.rvec.detach(), self.camera.T_scaled.detach()
        out = {f"camera.{n}": lens[i] for i, n in enumerate(LENS_PARAMETERS)}
        out["camera.rvec"] = torch.cat([rv[:v], pose[None, :3], rv[v + 1:]])
        out["camera.T_scaled"] = torch.cat([Ts[:v], pose[None, 3:6], Ts[v + 1:]])
        return out

    def _call(self, v: int, geo: torch.Tensor, fn):
        """fn(view camera of view v) with lens = geo[:4], pose = geo[4:10]."""
        return torch.func.functional_call(self.geometry, self._params(v, geo[:4], geo[4:10]), (v, fn))

    # --- dark fractions and their Jacobians ------------------------------------------------------------------
    def _closed(self, v: int, geo: torch.Tensor, uv: torch.Tensor, jacobian: bool, subpixels: int = SUBPIXELS):
        pts = sub_points(uv, subpixels)
        if not jacobian:
            with torch.no_grad():
                q, c, a = self._call(v, geo, lambda cam: cam.focus_geometry(pts)[:3])
                return checker_dark_fraction_disc(q, c, a, self.target, self.near).mean(-1), None

        def focus(g):
            out = self._call(v, g, lambda cam: cam.focus_geometry(pts)[:3])
            return out, tuple(o.detach() for o in out)

        (dq, dc, da), (q, c, a) = torch.func.jacfwd(focus, has_aux=True)(geo)
        self.near = min(self.n_edges, max(self.near, lines_cut(q, c, a, self.target) + 1))
        n, s = pts.shape[:2]
        with torch.enable_grad():
            # Each point's own copy of the lens centre and axes: the gradient of the sum is every point's partials.
            qq = q.clone().requires_grad_()
            cc = c.expand(n, s, 3).clone().requires_grad_()
            aa = a.expand(n, s, 2, 3).clone().requires_grad_()
            dark = checker_dark_fraction_disc(qq, cc, aa, self.target, self.near)
            grads = torch.autograd.grad(dark.sum(), (qq, cc, aa), allow_unused=True)
        gq, gc, ga = (torch.zeros_like(t) if g is None else g for g, t in zip(grads, (qq, cc, aa)))
        dD = (torch.einsum("nsk,nskp->np", gq, dq) + torch.einsum("nsk,kp->np", gc, dc)
              + torch.einsum("nsij,ijp->np", ga, da)) / s
        return dark.detach().mean(-1), dD

    def _samples(self, v: int, geo: torch.Tensor, psf: torch.Tensor, uv: torch.Tensor, jacobian: bool):
        def dark(g):
            d = self._call(v, g[:10], lambda cam: dark_fraction_samples(self.target, cam, uv, self.lens_uv,
                                                                         g[10] ** 2))
            return d, d.detach()

        g = torch.cat([geo, psf.reshape(1)])
        if not jacobian:
            with torch.no_grad():
                return dark(g)[1], None
        dD, D = torch.func.jacfwd(dark, has_aux=True)(g)
        return D, dD

    def _dark(self, v: int, geo: torch.Tensor, psf: torch.Tensor, jacobian: bool):
        """(N,) dark fractions of view v's pixels and (N, 11) their derivatives by (lens, pose, psf)."""
        dv = self.data[v]
        Ds, dDs = [], []
        # Pixels in three runs: closed form with SUBPIXELS_SHARP points a side, closed form with SUBPIXELS, samples.
        runs = ((0, dv.n_sharp, SUBPIXELS_SHARP), (dv.n_sharp, dv.n_closed_form, SUBPIXELS),
                (dv.n_closed_form, dv.uv.shape[0], None))
        for a in range(0, dv.uv.shape[0], JACOBIAN_BLOCK):
            b = min(a + JACOBIAN_BLOCK, dv.uv.shape[0])
            for lo, hi, sub in runs:
                lo, hi = max(lo, a), min(hi, b)
                if lo >= hi:
                    continue
                if sub is None:
                    D, dD = self._samples(v, geo, psf, dv.uv[lo:hi], jacobian)
                else:
                    D, dD = self._closed(v, geo, dv.uv[lo:hi], jacobian, sub)
                    dD = None if dD is None else torch.cat([dD, dD.new_zeros(hi - lo, 1)], 1)
                Ds.append(D)
                dDs.append(dD)
        return torch.cat(Ds), (torch.cat(dDs) if jacobian else None)

    # --- the solver's callback -------------------------------------------------------------------------------
    def evaluate(self, x: dict, with_jacobian: bool):
        lens, pose, levels = self.full_lens(x["lens"]), x["pose"], x["levels"]
        gain = x.get("gain")
        vig = x["vignetting"][0] if "vignetting" in x else torch.zeros((), dtype=torch.float64)
        psf = x["psf"][0] if "psf" in x else torch.tensor(self.psf_fixed, dtype=torch.float64)
        M = sum(int(d.uv.shape[0]) for d in self.data)
        stored = dict(zip(LENS_PARAMETERS, (float(v) for v in lens)))
        if not (stored["inv_U_per_m"] > 0 and stored["d_scaled"] > 0 and abs(stored["theta_F"]) < 1.5):
            nan = torch.full((M,), math.nan, dtype=torch.float64)   # outside the lens's domain
            sizes = {"lens": len(self.free), "pose": 6, "levels": 2, "vignetting": 1, "psf": 1, "gain": 2}
            return nan, ({k: nan[:, None].expand(M, sizes[k]) for k in x} if with_jacobian else None)
        rs, jac = [], {k: [] for k in x}
        for v, dv in enumerate(self.data):
            D, dD = self._dark(v, torch.cat([lens, pose[v]]), psf, with_jacobian)
            falloff = 1.0 - vig * dv.rho2
            if gain is not None:   # the illumination's gradient across the view: 1 + g_x x + g_y y
                falloff = falloff * (1.0 + dv.xy @ gain[v])
            white, black = levels[v, 0], levels[v, 1]
            shade = white - (white - black) * D
            rs.append((falloff * shade - dv.observed) / self.scale)
            if with_jacobian:
                Jg = (-falloff * (white - black) / self.scale)[:, None] * dD
                jac["lens"].append(Jg[:, :4] @ self.lens_jacobian(x["lens"]))
                if gain is not None:
                    jac["gain"].append(((1.0 - vig * dv.rho2) * shade / self.scale)[:, None] * dv.xy)
                jac["pose"].append(Jg[:, 4:10])
                jac["levels"].append(torch.stack([falloff * (1 - D), falloff * D], 1) / self.scale)
                if "vignetting" in jac:
                    g = 1.0 if gain is None else 1.0 + dv.xy @ gain[v]
                    jac["vignetting"].append((-dv.rho2 * g * shade / self.scale)[:, None])
                if "psf" in jac:
                    jac["psf"].append(Jg[:, 10:11])
        r = torch.cat(rs)
        if not with_jacobian:
            return r, None
        jac = {k: torch.cat(v) for k, v in jac.items()}
        self.n_jacobians += 1
        if self.say:
            cost = 0.5 * float((r * r).sum())
            _, U, d, theta_F = lens_values([float(v) for v in lens])
            self.say(f"photometric: linearisation {self.n_jacobians}, cost {cost:.6g}, θF "
                     f"{math.degrees(theta_F):+.4f}°, U {U:.2f} mm, d {d:.4f} mm "
                     f"({time.perf_counter() - self.t0:.1f} s)")
        return r, jac

    def residuals(self, x: dict) -> torch.Tensor:
        """(M,) residuals in linear intensity units."""
        with torch.no_grad():
            return self.evaluate(x, False)[0] * self.scale


def _robust_sigma(r: torch.Tensor) -> float:
    return 1.4826 * float(torch.median(r.abs())) + 1e-12


def _solve(problem: _Problem, x0: dict, blocks: list, view_rows: torch.Tensor, opts: PhotometricOptions,
           history: list):
    """Huber IRLS by `tiltfit.solve.levenberg_marquardt`, the residuals' robust σ re-estimated after each solve
    until it holds (at most three solves). Returns (LMResult, iterations)."""
    k = opts.huber_scale
    lm = LMOptions(max_iterations=opts.iterations, rho=lambda s2: robust_rho(s2, "huber", k),
                   weight=lambda s2: robust_weight(s2, "huber", k), ftol=SOLVE_FTOL)
    problem.scale = _robust_sigma(problem.residuals(x0))

    def solve(x):
        try:
            return levenberg_marquardt(problem.evaluate, x, blocks, view_rows, lm)
        except SolverError as e:
            raise PhotometricError(str(e)) from None

    def rescale(res, k: int, last: bool):
        history.append(res.cost)
        new = _robust_sigma(res.r * problem.scale)
        if abs(new / problem.scale - 1) <= SCALE_TOLERANCE:
            return res, False
        if problem.say:
            problem.say(f"photometric: the residuals' robust σ re-estimated ({problem.scale:.4g} → {new:.4g}); the "
                        "fit resumes with the new Huber weights, and its cost is not comparable with the lines above")
        problem.scale = new
        return res, True

    return solve_rescaling(solve, rescale, x0, 3)


def _cluster_sandwich(res, problem: _Problem) -> torch.Tensor:
    """Covariance (P, P) of the flat parameters by the cluster-robust sandwich A⁻¹ B A⁻¹ of the Huber fit.

    A = Σ w J Jᵀ is the fit's own normal matrix; B = Σ_c g_c g_cᵀ sums the score g_c = Σ_{i ∈ c} w_i r_i J_i
    of each cluster c: the pixels of one square tile of a view, as wide as that view's blur disc (at least
    8 px). Residuals of neighbouring pixels share their errors (the same blurred edge mis-modelled, render and
    shot noise largest on edges), so the textbook (JᵀWJ)⁻¹ s², which assumes independent residuals of one
    variance, comes out too small. Scaled by C / (C − 1) for C clusters; invariant to the residuals' scale.
    """
    J = dense_jacobian(res.jacobian)
    psi = (res.weights * res.r)[:, None] * J
    scores, offset = [], 0
    for v, dv in enumerate(problem.data):
        n = dv.uv.shape[0]
        side = max(8.0, board_blur_px(problem.camera_of(res.x, v), problem.target))
        tile = torch.floor(dv.uv / side).to(torch.int64)
        _, cluster = torch.unique(tile[:, 0] * 100003 + tile[:, 1], return_inverse=True)
        scores.append(torch.zeros(int(cluster.max()) + 1, J.shape[1], dtype=J.dtype).index_add_(
            0, cluster, psi[offset:offset + n]))
        offset += n
    G = torch.cat(scores)
    C = G.shape[0]
    B = G.T @ G * (C / max(C - 1, 1))
    try:
        A_inv = res.normal.covariance().dense()
    except RuntimeError:   # a parameter the data no longer move (one at its trust bound): held, σ 0
        try:
            A_inv = torch.linalg.pinv(res.normal.dense(), hermitian=True)
        except RuntimeError:
            return torch.full_like(B, math.nan)
    return A_inv @ B @ A_inv


def _view_covariance(res, s2: float, cov_tiles: torch.Tensor, held: list | None = None):
    """(covariance (P, P), sigma_model) of the Huber fit under the per-view error model (module docstring):
    `tiltfit.uncertainty.covariance.view_cluster_covariance` with views as clusters. `held`: flat positions of global
    parameters the data no longer move (a lens parameter at its trust bound), left out of the covariance (σ 0).
    The tile sandwich `cov_tiles` where the per-view one cannot be formed (one view, a singular Schur complement)."""
    from types import SimpleNamespace

    from ..solve.blocks import BlockJacobian
    from tiltfit.uncertainty.covariance import view_cluster_covariance

    bj = res.jacobian
    if not isinstance(bj, BlockJacobian):
        return cov_tiles, {"name": "tiles", "n_views": 1}
    P = bj.n_params
    keep = torch.ones(P, dtype=torch.bool)
    if held:
        keep[torch.tensor(held)] = False
    pos = torch.cumsum(keep.to(torch.int64), 0) - 1           # each kept parameter's place in the reduced vector
    cols = keep[bj.s_idx]
    reduced = BlockJacobian(bj.Js[:, cols], bj.Jp, bj.rows, pos[bj.s_idx[cols]], pos[bj.p_idx], int(keep.sum()))
    try:
        got = view_cluster_covariance(SimpleNamespace(jacobian=reduced, weights=res.weights, r=res.r), s2)
    except RuntimeError:   # a singular per-view block (a view whose pixels no longer move its pose)
        got = None
    if got is None:
        return cov_tiles, {"name": "tiles", "n_views": int(bj.rows.shape[0])}
    cov, info = got
    idx = torch.nonzero(keep).squeeze(1)
    full = torch.zeros(P, P, dtype=cov_tiles.dtype)
    full[idx[:, None], idx[None, :]] = cov.dense()
    return full, {"name": "views", **info}


def _held_covariance(problem: "_Problem", res, start_covariance: dict | None):
    """(P, P) covariance the held principal point and distortion add to the fitted parameters, or None.

    The fit holds them at the corner fit's values, so its own covariance is conditional on them; they carry the
    corner fit's uncertainty (`start_covariance`: its `intrinsics_covariance`, {names, matrix}, cx_px, cy_px,
    k1 … k6 among the names), which moves the solution by dx/dh = −A⁻¹ JᵀW J_h (J_h: the residuals'
    derivatives with respect to each held h, by forward differences of 0.1 of its σ). Returns D C_hh Dᵀ with
    D = dx/dh (in the solver's flat order), ignoring the correlation between the corners' errors and the pixels'
    (the same views): on the real sets the held parameters alone moved w between subsets by many times the
    conditional σ (benchmarks/results/photometric_sigma.md)."""
    from tiltfit.uncertainty.covariance import INTRINSIC_NAMES

    if not isinstance(start_covariance, dict) or "names" not in start_covariance:
        return None
    names, M = list(start_covariance["names"]), torch.as_tensor(start_covariance["matrix"], dtype=torch.float64)
    cam = problem.camera
    dist = cam.parameter_names("distortion")
    # Each held intrinsic: (index in the matrix, camera parameter, element, camera units per intrinsic unit).
    targets = {"cx_px": ("pp_scaled", 0, 1.0 / cam.pixel_scale_px), "cy_px": ("pp_scaled", 1, 1.0 / cam.pixel_scale_px)}
    targets |= {n: (dn, None, 1.0) for n, dn in zip(INTRINSIC_NAMES[3:], dist)}
    held = [(names.index(n), *targets[n]) for n in names if n in targets and float(M[names.index(n), names.index(n)]) > 0]
    if not held:
        return None
    idx = torch.tensor([h[0] for h in held])
    C_hh = M[idx[:, None], idx[None, :]]
    try:
        cov = res.normal.covariance()
    except RuntimeError:   # a parameter the data no longer move: no sensitivities
        return None
    with torch.no_grad():
        r0 = problem.evaluate(res.x, False)[0]
        cols = []
        for (i, name, el, unit), var in zip(held, torch.diagonal(C_hh)):
            step = 0.1 * math.sqrt(float(var))
            param = getattr(cam, name)
            before = param.detach().clone()
            if el is None:
                param.add_(step * unit)
            else:
                param[el] += step * unit
            cols.append((problem.evaluate(res.x, False)[0] - r0) / step)
            param.copy_(before)
    Jh = torch.stack(cols, 1)
    if not bool(torch.isfinite(Jh).all()):
        return None
    g = torch.stack([res.normal.gradient(Jh[:, j]) for j in range(Jh.shape[1])], 1)   # JᵀW J_h (P, H)
    D = -cov.matmul(g)
    return D @ C_hh @ D.T


def _lens_sigma(lens: torch.Tensor, cov_lens: torch.Tensor) -> dict:
    """One-σ of w, 1/U, U, d, θF, θL (mm, 1/m, degrees) from the covariance of the stored lens block."""
    def physical(p):
        w, U, d, theta_F = lens_values(p)
        inv_U = p[LENS_PARAMETERS.index("inv_U_per_m")]
        return torch.stack([w, inv_U, U, d, theta_F, theta_L_from_theta_F(theta_F, w, U)])

    Jp = torch.func.jacrev(physical)(lens.detach())
    var = torch.diagonal(Jp @ cov_lens @ Jp.T)
    sd = [math.sqrt(max(float(x), 0.0)) if math.isfinite(float(x)) else math.nan for x in var]
    return {"w_mm": sd[0], "inv_U_per_m": sd[1], "U_mm": sd[2], "d_mm": sd[3],
            "theta_F_deg": math.degrees(sd[4]), "theta_L_deg": math.degrees(sd[5])}


def _sigma_dict(res, cov: torch.Tensor, problem: "_Problem") -> dict:
    layout = res.layout

    def block(name):
        if name not in layout.offsets:
            return None
        a, n = layout.offsets[name]
        return slice(a, a + n)

    s = block("lens")
    Jm = problem.lens_jacobian(res.x["lens"])
    out = _lens_sigma(problem.full_lens(res.x["lens"]), Jm @ cov[s, s] @ Jm.T)
    for name, key in (("vignetting", "vignetting"), ("psf", "psf_sigma_px")):
        b = block(name)
        out[key] = math.sqrt(max(float(cov[b, b][0, 0]), 0.0)) if b is not None else 0.0
    return out


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
    opts = options or PhotometricOptions()
    t0 = time.perf_counter()
    imgs = [np.asarray(im, dtype=np.float64) for im in images]
    imgs = [im.mean(-1) if im.ndim == 3 else im for im in imgs]
    if not imgs:
        raise PhotometricError("no images to refine")
    if target.dark_rectangles():
        raise PhotometricError("target: the photometric model renders checkerboards; a ChArUco board's markers "
                               "are not modelled (use the corner-and-blur calibration)")
    if camera.n_views != len(imgs):
        raise PhotometricError(f"the camera has {camera.n_views} views for {len(imgs)} images")
    W, H = camera.image_size_px
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
    psf0 = PSF_START_PX if opts.kernel == "disc_gaussian" else 0.0
    views = [cam.view_camera(v) for v in range(cam.n_views)]
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
    lens_uv = hammersley_disc_samples(n_samples)
    try:
        data, held_data, levels = _choose_pixels(imgs, views, target, opts, disc_only, say, t0)
    except _ViewsLeftOut as e:
        return _without_views(e.views, imgs, target, camera, options, say, start_sigma, corners, corner_held_out_px,
                              start_covariance, t0)
    n_rows = int(data[0].uv.shape[0])
    n_closed = sum(d.n_closed_form for d in data)
    n_pixels = sum(int(d.uv.shape[0]) for d in data)
    aperture = "closed_form" if n_closed == n_pixels else "samples" if n_closed == 0 else "mixed"
    if say:
        say(f"photometric: {len(imgs)} views, {n_pixels} pixels, aperture "
            + {"closed_form": f"in closed form (4x4 points per pixel, {SUBPIXELS_SHARP}x{SUBPIXELS_SHARP} for the "
                              f"{sum(d.n_sharp for d in data)} blurred less than {SHARP_BLUR_PX:g} px)",
               "samples": f"by {n_samples} lens samples per pixel",
               "mixed": f"in closed form for {n_closed} pixels (blur from {CLOSED_FORM_MIN_BLUR_PX:g} px), "
                        f"by {n_samples} lens samples for the other {n_pixels - n_closed}"}[aperture])

    problem = _Problem(cam, target, data, lens_uv, say)
    if free is not None:
        problem.free, problem.bound = free, bound
    problem.camera_of = lambda x, v: _camera_of(cam.copy(), x, problem).view_camera(v)
    V = len(imgs)
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
    view_rows = torch.arange(V * n_rows).reshape(V, n_rows)
    history = []
    res, iterations = _solve(problem, x0, blocks, view_rows, opts, history)
    scale = problem.scale
    selection = None
    if opts.kernel == "auto":
        res, iterations, scale, selection = _select_kernel(problem, res, iterations, blocks, view_rows, opts,
                                                           history, say)
    kernel = "disc_gaussian" if "psf" in res.x else "disc"
    cov_tiles = _cluster_sandwich(res, problem)
    r = res.r * scale
    s_final = _robust_sigma(r)
    try:
        cov_gn = covariance(res, (s_final / scale) ** 2).dense()
    except SolverError:
        cov_gn = torch.full_like(cov_tiles, math.nan)
    kept, held_out, reasons = "photometric", None, []
    refined = _camera_of(camera.copy(), res.x, problem)
    if opts.held_out_pixels:
        held_out = _held_out_costs(problem, held_data, res.x, x0, opts, scale)
        if held_out["refined"] - held_out["start"] > HELD_OUT_Z * held_out["difference_se"]:
            kept = "corner fit"
            reasons.append(f"held-out pixels cost {held_out['refined']:.4g} refined, {held_out['start']:.4g} "
                           f"for the corner fit (more than {HELD_OUT_Z:g} standard errors, "
                           f"{held_out['difference_se']:.2g}, apart)")
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
    cov_sigma, sigma_model = _view_covariance(res, (s_final / scale) ** 2, cov_tiles, held)
    cov_held = _held_covariance(problem, res, start_covariance) if not at_bound else None
    sigma_model["held_propagated"] = cov_held is not None
    if cov_held is not None:
        cov_sigma = cov_sigma + cov_held
    if at_bound:
        kept = "corner fit"
        hit = "; ".join(f"{e['parameter']} {e['refined']:.6g} at the bound [{e['low']:.6g}, {e['high']:.6g}] "
                        f"(start {e['start']:.6g})" for e in _bound_record(problem, res.x["lens"], at_bound)
                        if e["at_bound"])
        reasons.append(f"{', '.join(at_bound)} at the trust bound ({hit}; the refinement is held within "
                       f"{TRUST_SIGMAS:g}σ of the corner fit): the pixels and the corners disagree beyond what "
                       "either's σ allows")
    corner_check = None
    if corners is not None:
        corner_check = _corner_check(refined, camera, corners, corner_held_out_px, len(problem.free))
        if not corner_check["refined_px"] <= corner_check["limit_px"]:
            kept = "corner fit"
            reasons.append(f"held-out corners RMS {corner_check['refined_px']:.4f} px refined, "
                           f"{corner_check['start_px']:.4f} px for the corner fit")
    if say and (held_out is not None or corner_check is not None or at_bound):
        parts = [f"{', '.join(at_bound)} at the trust bound"] if at_bound else []
        if held_out is not None:
            parts.append(f"held-out pixels ({held_out['pixels']}) cost {held_out['refined']:.4g} refined, "
                         f"{held_out['start']:.4g} from the start")
        if corner_check is not None:
            parts.append(f"corners (held out of the photometric fit) RMS {corner_check['refined_px']:.4f} px "
                         f"refined, {corner_check['start_px']:.4f} px the corner fit's held-out")
        say("photometric: " + "; ".join(parts) + ": keeping the "
            + ("refinement" if kept == "photometric" else "start (the corner fit)"))
    lens_full = problem.full_lens(res.x["lens"])
    exposure = Exposure(res.x["levels"], float(res.x["vignetting"][0]) if "vignetting" in res.x else 0.0,
                        res.x.get("gain"))
    values = {**_lens_values(lens_full), "inv_U_per_m": float(lens_full[LENS_PARAMETERS.index("inv_U_per_m")]),
              "vignetting": float(exposure.vignetting.detach()), "psf_sigma_px": abs(float(res.x["psf"][0])) if "psf" in res.x
              else 0.0, "kernel": kernel, "lens_samples": n_samples if aperture != "closed_form" else 0,
              "aperture": aperture, "closed_form_pixels": n_closed}
    out_views = []
    with torch.no_grad():
        for v in range(V):
            rv = r[view_rows[v]]
            out_views.append({"R": refined.R[v].numpy().copy(), "T_mm": refined.T_mm[v].numpy().copy(),
                              "white": float(res.x["levels"][v, 0]), "black": float(res.x["levels"][v, 1]),
                              "rms": float(torch.sqrt((rv * rv).mean())), "n_pixels": n_rows,
                              **({"gain_x": float(res.x["gain"][v, 0]), "gain_y": float(res.x["gain"][v, 1])}
                                 if "gain" in res.x else {})})
    free = [LENS_PARAMETERS[i] for i in problem.free]
    bounds = _bound_record(problem, res.x["lens"], at_bound)
    return PhotometricResult(refined, exposure, values, _sigma_dict(res, cov_sigma, problem), out_views,
                             float(torch.sqrt((r * r).mean())), iterations, time.perf_counter() - t0, history,
                             selection, _sigma_dict(res, cov_gn, problem), kept, held_out, camera.copy(),
                             corner_check, "; ".join(reasons), free, at_bound, _sigma_dict(res, cov_tiles, problem),
                             sigma_model, _sigma_dict(res, cov_held, problem) if cov_held is not None else None,
                             bounds=bounds)


def _choose_pixels(imgs: list, views: list, target: Target, opts: PhotometricOptions, disc_only: bool, say,
                   t0: float):
    """Per view the pixels to fit (the same count in every view) and the held-out ones, where the start's
    prediction is between the levels (edges, blur) or flat; and the start's levels. Returns (data, held_data,
    levels): `_View`s, closed-form pixels first."""
    W, H = views[0].width, views[0].height
    rng = np.random.default_rng(opts.seed)
    rng_held = np.random.default_rng([opts.seed, 1])   # its own stream: the fitted pixels do not depend on it
    rng_cand = np.random.default_rng([opts.seed, 2])
    picks, held, levels, left_out = [], [], [], []
    for k, (im, vc) in enumerate(zip(imgs, views)):
        if im.shape != (H, W):
            raise PhotometricError(f"view {k}: image is {im.shape[1]}x{im.shape[0]}, expected {W}x{H}")
        # Candidates: the board's bounding box only (a real photo is mostly elsewhere), at most
        # MAX_CANDIDATE_PIXELS of its pixels drawn at random, less the saturated ones (glare: their brightness
        # says nothing of the board's), then those whose blur disc lies on the board (`usable_pixels`).
        box = board_box(target, vc)
        if box is None:
            left_out.append((k, "the board is not on the image at the start"))
            continue
        bx0, by0, bx1, by1 = box
        bw, bh = bx1 - bx0 + 1, by1 - by0 + 1
        n_box = bw * bh
        local = np.arange(n_box) if n_box <= MAX_CANDIDATE_PIXELS else \
            np.sort(rng_cand.choice(n_box, MAX_CANDIDATE_PIXELS, replace=False))
        cand = (by0 + local // bw) * W + bx0 + local % bw
        n_drawn = cand.size
        if opts.saturation is not None:
            cand = cand[im.reshape(-1)[cand] < opts.saturation * float(im.max())]
        n_saturated = n_drawn - cand.size
        cand = _informative(cand, vc, target, W, opts, rng_cand)
        uv_all = torch.tensor(np.stack([cand % W, cand // W], -1), dtype=torch.float64)
        ok = usable_pixels(target, vc, uv_all)
        cand, uv_all = cand[ok], uv_all[torch.from_numpy(ok)]
        usable = np.zeros(H * W, dtype=bool)
        usable[cand] = True
        if cand.size < MIN_USABLE_PIXELS:
            left_out.append((k, f"the board covers {cand.size} usable pixels, fewer than {MIN_USABLE_PIXELS} (pixels "
                                f"whose blur disc lies on the board inside its margin; {n_saturated} of the {n_drawn} "
                                "in the board's box saturated)"))
            continue
        if left_out:   # this view is usable, but the fit restarts without the left-out ones
            continue
        white, black = _initial_levels(im.reshape(-1)[cand])
        pred_img = np.full(H * W, np.nan)
        for a in range(0, uv_all.shape[0], 1 << 16):
            dark = predicted_dark_fraction(target, vc, uv_all[a:a + (1 << 16)])
            pred_img[cand[a:a + (1 << 16)]] = (white - (white - black) * dark).numpy()
        picks.append(_select_pixels(pred_img, usable, white, black, opts.max_pixels, rng))
        rest = usable.copy()
        rest[picks[-1]] = False
        held.append(_select_pixels(pred_img, rest, white, black, opts.held_out_pixels, rng_held)
                    if opts.held_out_pixels else picks[-1][:0])
        levels.append((white, black))
        if say:
            say(f"photometric: view {k + 1} of {len(imgs)}: {cand.size} usable pixels of {n_box} in the board's box, "
                f"{picks[-1].size} chosen ({time.perf_counter() - t0:.1f} s)")
    if left_out:
        raise _ViewsLeftOut(left_out)
    # The solver's per-view blocks need the same number of pixels in every view.
    n_rows = min(p.size for p in picks)
    picks = [p if p.size == n_rows else np.sort(rng.choice(p, n_rows, replace=False)) for p in picks]
    hx, hy = image_centre_px(W, H)

    def view_data(im, vc, pick) -> _View:
        uv = torch.tensor(np.stack([pick % W, pick // W], -1), dtype=torch.float64)
        observed = torch.tensor(im.reshape(-1)[pick], dtype=torch.float64)
        blur = pixel_blur_px(vc, uv) if disc_only else None
        if opts.aperture == "closed_form":
            closed = torch.ones(uv.shape[0], dtype=torch.bool)
        elif disc_only:
            closed = blur >= CLOSED_FORM_MIN_BLUR_PX
        else:
            closed = torch.zeros(uv.shape[0], dtype=torch.bool)
        sharp = closed & (blur < SHARP_BLUR_PX) if disc_only else closed & False
        # Closed-form pixels first, the sharp ones (more points a pixel) before the others; then the samples'.
        order = torch.argsort(torch.where(sharp, 0, torch.where(closed, 1, 2)).to(torch.int8), stable=True)
        uv = uv[order]
        rho2 = ((uv[:, 0] - hx) ** 2 + (uv[:, 1] - hy) ** 2) / (hx ** 2 + hy ** 2)
        return _View(uv, observed[order], int(closed.sum()), rho2,
                     torch.stack([(uv[:, 0] - hx) / hx, (uv[:, 1] - hy) / hy], 1), int(sharp.sum()))

    data = [view_data(im, vc, pick) for im, vc, pick in zip(imgs, views, picks)]
    held_data = [view_data(im, vc, pick) for im, vc, pick in zip(imgs, views, held)]
    return data, held_data, levels


def _informative(cand: np.ndarray, vc, target: Target, W: int, opts: PhotometricOptions,
                 rng: np.random.Generator) -> np.ndarray:
    """The candidates worth predicting (flat indices, sorted): pixels carry geometric information only within
    the blur disc of a cell edge. From the chief ray's point on the board, each candidate's distance to the
    nearest cell edge in pixels (the chief-ray map's scale: the 90th percentile over 256 of them); those within half the view's blur disc + 2 px
    are edge candidates, the others flat. Keeps up to 4 x what the selection takes of each, at random."""
    if cand.size == 0:   # nothing of the board's box left (saturated): the view is left out
        return cand
    uv = torch.tensor(np.stack([cand % W, cand // W], -1), dtype=torch.float64)
    probe = uv[torch.from_numpy(rng.choice(cand.size, min(cand.size, 256), replace=False))]
    steps = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]], dtype=torch.float64)
    with torch.no_grad():
        XY = on_board(vc.generate_rays(uv))[:, :2].numpy()
        hit = on_board(vc.generate_rays((probe[:, None, :] + steps).reshape(-1, 2))).reshape(-1, 3, 3)
    J = (hit[:, 1:, :2] - hit[:, :1, :2]).numpy()                    # (n, 2 (du, dv), 2 (X, Y)) mm per px
    with np.errstate(all="ignore"):
        near = np.full(cand.size, np.inf)
        for axis, edges in ((0, np.asarray(target.x_edges)), (1, np.asarray(target.y_edges))):
            dist_mm = np.abs(XY[:, axis, None] - edges[None, :]).min(1)
            per_px = np.nanpercentile(np.hypot(J[:, 0, axis], J[:, 1, axis]), 90)   # mm along this axis per px
            near = np.minimum(near, dist_mm / max(per_px, 1e-300))
    near = np.where(np.isfinite(near), near, np.inf)
    reach = 0.5 * board_blur_px(vc, target) + 2.0
    edge, flat = np.flatnonzero(near <= reach), np.flatnonzero(near > reach)
    want = 4 * (opts.max_pixels + opts.held_out_pixels)
    keep = [rng.choice(edge, min(edge.size, want), replace=False),
            rng.choice(flat, min(flat.size, want // 2), replace=False)]
    return np.sort(cand[np.concatenate(keep)])


def _select_kernel(problem: _Problem, res, iterations: int, blocks: list, view_rows, opts: PhotometricOptions,
                   history: list, say):
    """Kernel `auto`: the Gaussian part freed from the disc's solution on the same pixels and weights, kept where
    the likelihood-ratio test and its width justify it. Returns (LMResult, iterations, scale, selection)."""
    scale = problem.scale
    w0, r0 = res.weights, res.r * scale
    rss0 = float((w0 * r0 * r0).sum())
    x1 = {**res.x, "psf": torch.tensor([PSF_START_PX], dtype=torch.float64)}
    res1, it1 = _solve(problem, x1, blocks + [Block("psf", (1,))], view_rows, opts, history)
    r1 = res1.r * problem.scale
    rss1 = float((w0 * r1 * r1).sum())
    test = nested_test([(int(r0.numel()), rss0, rss1)], 1, opts.alpha)
    psf = abs(float(res1.x["psf"][0]))
    justified = test["justified"] and psf >= PSF_EVIDENCE_PX
    selection = {"kernel": "disc_gaussian" if justified else "disc", "lr_statistic": test["lr_statistic"],
                 "disc_fit": _lens_values(problem.full_lens(res.x["lens"])), "p_value": test["p_value"],
                 "delta_bic": test["delta_bic"], "rss_disc": rss0, "rss_disc_gaussian": rss1,
                 "psf_sigma_px": psf}
    if say:
        say(f"photometric: kernel {selection['kernel']} (Gaussian σ {psf:.3f} px, Λ = {test['lr_statistic']:.3g}, "
            f"p = {test['p_value']:.2g}, ΔBIC = {test['delta_bic']:.3g})")
    if justified:
        res, iterations, scale = res1, iterations + it1, problem.scale
    else:
        problem.scale = scale
    return res, iterations, scale, selection


def _held_out_costs(problem: _Problem, held_data: list, x: dict, x0: dict, opts: PhotometricOptions,
                    scale: float) -> dict:
    """Mean Huber cost (residuals in units of `scale`) of the held-out pixels for the refined state `x` and for
    the start `x0`'s lens and poses with the exposure fitted to the fit's pixels (geometry held: per view the
    levels by robust linear least squares, the vignetting the refinement's)."""
    k = opts.huber_scale
    vig = x["vignetting"] if "vignetting" in x else torch.zeros(1, dtype=torch.float64)
    psf = x0["psf"][0] if "psf" in x0 else torch.tensor(problem.psf_fixed, dtype=torch.float64)
    levels = []
    for v, dv in enumerate(problem.data):
        D = problem._dark(v, torch.cat([problem.full_lens(x0["lens"]), x0["pose"][v]]), psf, False)[0]
        f = 1.0 - vig[0] * dv.rho2
        if "gain" in x:   # the refinement's illumination gradient, as its vignetting
            f = f * (1.0 + dv.xy @ x["gain"][v])
        A = torch.stack([f * (1 - D), f * D], 1)
        sol0 = x0["levels"][v].detach().to(torch.float64)  # the start's levels
        huber = LMOptions(max_iterations=50, rho=lambda s2: robust_rho(s2, "huber", k),
                          weight=lambda s2: robust_weight(s2, "huber", k))
        try:
            sol = least_squares(lambda lv: (A @ lv - dv.observed) / scale, sol0, huber,
                                jacobian_fn=lambda lv: A / scale).x
        except SolverError:  # creeping on (nearly) noise-free pixels: the start's levels
            sol = sol0
        levels.append(sol)
    start = {**x0, "levels": torch.stack(levels), "vignetting": vig, **({"gain": x["gain"]} if "gain" in x else {})}
    check = _Problem(problem.camera, problem.target, held_data, problem.lens_uv)
    check.near, check.scale, check.psf_fixed = problem.near, scale, problem.psf_fixed
    check.free, check.bound, check.lens_start = problem.free, problem.bound, problem.lens_start

    def cost(state):
        with torch.no_grad():
            r = check.evaluate(state, False)[0]
        return robust_rho(r * r, "huber", k)

    c_ref, c_start = cost(x), cost(start)
    diff = c_ref - c_start
    n = int(diff.numel())
    se = float(diff.std() / math.sqrt(n)) if n > 1 else math.inf
    return {"pixels": n, "refined": float(c_ref.mean()), "start": float(c_start.mean()), "difference_se": se}


def _trust_region(cam: LensCamera, sigma: dict):
    """(free indices into LENS_PARAMETERS, (4,) bounds in stored units) from the start's σ: a parameter whose
    σ is missing, 0 or not finite is held (the start held or could not determine it)."""
    w, U, _, _ = lens_values({n: float(getattr(cam, n)) for n in LENS_PARAMETERS})
    by_name = stored_lens_sigma(w, U, sigma)
    stored = [by_name.get(n) for n in LENS_PARAMETERS]
    free = [i for i, sd in enumerate(stored) if sd is not None]
    if not free:
        free = [0]
        stored[0] = math.inf
    bound = torch.tensor([math.inf if sd is None else TRUST_SIGMAS * sd for sd in stored], dtype=torch.float64)
    return free, bound


#: Stored lens parameter -> (its name in CALIB.json, the physical value of a stored one).
_PHYSICAL = {"log_w_mm": ("w_mm", w_from_stored), "inv_U_per_m": ("U_mm", lambda v: U_from_stored(v) if v > 0 else math.inf),
             "d_scaled": ("d_mm", d_from_stored), "theta_F": ("theta_F_deg", math.degrees)}


def _bound_record(problem: "_Problem", z: torch.Tensor, at_bound: list) -> list:
    """Per free lens parameter with a finite trust bound: its start, the bound's two ends and the refined value in
    CALIB.json's units (U's ends swap: it is stored as 1/U), and whether it ended at the bound (`at_bound`)."""
    lens = problem.full_lens(z.detach())
    out = []
    for i in problem.free:
        b = float(problem.bound[i])
        if not math.isfinite(b):
            continue
        stored = LENS_PARAMETERS[i]
        name, to_physical = _PHYSICAL[stored]
        start = float(problem.lens_start[i])
        ends = sorted(to_physical(v) for v in (start - b, start + b))
        out.append({"parameter": name, "start": to_physical(start), "low": ends[0], "high": ends[1],
                    "refined": to_physical(float(lens[i])), "at_bound": stored in at_bound})
    return out


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


def _chi2_quantile(p: float, k: int) -> float:
    """x with P(χ²(k) ≤ x) = p (bisection on `stats.chi2_sf`)."""
    from tiltfit.select.stats import chi2_sf

    lo, hi = 0.0, 10.0 * k + 100.0
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if chi2_sf(mid, k) > 1 - p else (lo, mid)
    return 0.5 * (lo + hi)


def _corner_check(refined: LensCamera, start: LensCamera, corners, start_held_out_px,
                  n_free: int = 4) -> dict:
    """The refinement judged by the corners (held out of the photometric fit): each view's pose refitted to them
    with the refined lens held (`validate.predict_views`), RMS per corner, against the corner fit's held-out
    RMS times 1 + CORNER_TOLERANCE; or, without it, against the start's own RMS with its poses refitted the same way
    (in sample): there the limit lets the corners' cost rise by the χ² quantile (CORNER_CONFIDENCE, `n_free`
    degrees of freedom) times their noise variance (their RSS over its residual degrees of freedom)."""
    from tiltfit.select.held_out import predict_views

    def rss(camera):
        fit = predict_views(camera.copy().double(), corners)
        return float(fit.rss["corners"]), max(int(fit.rss["n_corners"]), 1)

    got_rss, n_res = rss(refined)
    got = math.sqrt(got_rss / max(n_res // 2, 1))
    if start_held_out_px is not None:
        ref = float(start_held_out_px)
        return {"start_px": ref, "refined_px": got, "limit_px": ref * (1 + CORNER_TOLERANCE),
                "start_is_held_out": True, "views": corners.n_views}
    start_rss, _ = rss(start)
    dof = max(n_res - 6 * corners.n_views - n_free, 1)
    limit_rss = start_rss * (1.0 + _chi2_quantile(CORNER_CONFIDENCE, max(n_free, 1)) / dof)
    return {"start_px": math.sqrt(start_rss / max(n_res // 2, 1)), "refined_px": got,
            "limit_px": math.sqrt(limit_rss / max(n_res // 2, 1)), "start_is_held_out": False,
            "views": corners.n_views}


def _camera_of(camera: LensCamera, x: dict, problem: "_Problem") -> LensCamera:
    """`camera` (modified in place) holding the lens and poses of the solver's state `x`."""
    lens = problem.full_lens(x["lens"].detach())
    with torch.no_grad():
        for i, n in enumerate(LENS_PARAMETERS):
            getattr(camera, n).copy_(lens[i].to(getattr(camera, n)))
        camera.rvec.copy_(x["pose"][:, :3].to(camera.rvec))
        camera.T_scaled.copy_(x["pose"][:, 3:6].to(camera.T_scaled))
    return camera


def _lens_values(lens: torch.Tensor) -> dict:
    """w, U, d, θF, θL of a stored lens block (mm, degrees)."""
    record = Lens(*lens_values([float(v) for v in lens])).record()
    return {k: v for k, v in record.items() if k != "tilt_axis_deg"}   # the block has no tilt axis
