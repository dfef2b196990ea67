"""The photometric refinement's settings (`PhotometricOptions`, the kernels, apertures and limits), its
exposure model (`Exposure`), its result (`PhotometricResult`) and its errors."""
from __future__ import annotations

from dataclasses import dataclass, field

import torch

from renderer.cameras import LENS_PARAMETERS

from tiltfit.calibrate.model import LensCamera


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


#: Illumination models of `PhotometricOptions.illumination`.
ILLUMINATIONS = ("flat", "gradient")


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
