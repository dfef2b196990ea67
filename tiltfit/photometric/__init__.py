"""Photometric refinement: fit the calibration's camera to the photographs' pixels by rendering the target.

    render.py   the target seen through a thin lens: dark fraction per pixel (closed-form aperture or fixed
                lens samples), the exposure's shading, the usable pixels of a view, a view's residual image
    refine.py   the fit: `refine_photometric(images, target, camera) -> PhotometricResult` (refined camera,
                exposure, σ), solved by `tiltfit.solve.levenberg_marquardt`
"""
from .refine import (APERTURES, AUTO_KERNEL_LENS_SAMPLES, CLOSED_FORM_MIN_BLUR_PX, KERNELS, MIN_USABLE_PIXELS,
                     MIN_VIEWS, PSF_EVIDENCE_PX, Exposure, PhotometricError, PhotometricOptions, PhotometricResult,
                     refine_photometric)
from .render import (AUTO_LENS_SAMPLES_MAX, SUBPIXELS, auto_lens_samples, checker_dark_fraction,
                     dark_fraction_disc, dark_fraction_samples, hammersley_disc_samples, render_target,
                     render_target_disc, residual_image)

__all__ = ["APERTURES", "AUTO_KERNEL_LENS_SAMPLES", "AUTO_LENS_SAMPLES_MAX", "CLOSED_FORM_MIN_BLUR_PX", "KERNELS",
           "MIN_USABLE_PIXELS", "MIN_VIEWS", "PSF_EVIDENCE_PX", "SUBPIXELS", "Exposure", "PhotometricError",
           "PhotometricOptions", "PhotometricResult",
           "auto_lens_samples", "checker_dark_fraction", "dark_fraction_disc", "dark_fraction_samples",
           "hammersley_disc_samples", "refine_photometric", "render_target", "render_target_disc", "residual_image"]
