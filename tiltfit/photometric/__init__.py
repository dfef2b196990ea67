"""Photometric refinement: fit the calibration's camera to the photographs' pixels by rendering the target.

Modules:
    render    the target seen through a thin lens: dark fraction per pixel (closed-form aperture or fixed lens
              samples), the exposure's shading, the usable pixels of a view, a view's residual image
    aperture  the checker integrated over the lens's disc in closed form
    refine    the fit: `refine_photometric(images, target, camera) -> PhotometricResult` (refined camera, exposure,
              σ) in named stages: the start, the pixels, the solve, the σ, the verdict
    options   its settings (`PhotometricOptions`), exposure model (`Exposure`), result and errors
    pixels    which pixels it fits and which it holds out
    problem   the least-squares problem: residuals and Jacobian of the fitted pixels
    fit       the solve (`tiltfit.solve.levenberg_marquardt`, Huber weights, the robust scale) and the kernel choice
    sigma     σ: per-view cluster-robust covariance, the tiles' sandwich, what the held intrinsics add
    bounds    the trust region about the corner fit
    checks    the held-out pixels' cost and the held-out corners the refinement is judged by
    profiles  brightness profiles of photographs against renderings (the reproduction's figures)
"""
from .options import (APERTURES, AUTO_KERNEL_LENS_SAMPLES, CLOSED_FORM_MIN_BLUR_PX, KERNELS, MIN_USABLE_PIXELS,
                      MIN_VIEWS, PSF_EVIDENCE_PX, Exposure, PhotometricError, PhotometricOptions, PhotometricResult)
from .refine import refine_photometric
from .render import (AUTO_LENS_SAMPLES_MAX, SUBPIXELS, auto_lens_samples, checker_dark_fraction,
                     dark_fraction_disc, dark_fraction_samples, hammersley_disc_samples, render_target,
                     render_target_disc, residual_image)

__all__ = ["APERTURES", "AUTO_KERNEL_LENS_SAMPLES", "AUTO_LENS_SAMPLES_MAX", "CLOSED_FORM_MIN_BLUR_PX", "KERNELS",
           "MIN_USABLE_PIXELS", "MIN_VIEWS", "PSF_EVIDENCE_PX", "SUBPIXELS", "Exposure", "PhotometricError",
           "PhotometricOptions", "PhotometricResult",
           "auto_lens_samples", "checker_dark_fraction", "dark_fraction_disc", "dark_fraction_samples",
           "hammersley_disc_samples", "refine_photometric", "render_target", "render_target_disc", "residual_image"]
