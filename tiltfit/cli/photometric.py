"""`tiltfit calibrate --refine photometric`: the corner fit refitted to the photos' pixels
(`tiltfit.photometric.refine_photometric`), adopted into the calibration where held-out pixels and corners do not
reject it, and the CALIB.json `photometric` block that keeps the corner fit beside the refinement."""
from __future__ import annotations

import sys

from .detect import is_det_file
from .errors import CliError, as_cli_error

#: The lens values the `photometric` block keeps from the corner fit and from the refinement.
LENS_KEYS = ("w_mm", "U_mm", "d_mm", "theta_F_deg", "theta_L_deg")


def refine_calibration(result, obs, target, args, say, photos: dict | None = None,
                       held_out: dict | None = None) -> dict:
    """`--refine photometric`: refit lens and poses to the photos' pixels.

    The refined values are written into `result` (its camera, values, σ and views, so every key CALIB.json
    derives from them, residuals and f included, follows); returns the CALIB.json `photometric` block, which
    keeps the corner fit beside the refinement. `photos`: the photographs already read, by path. The refinement
    moves only what the corner fit determined, within its trust region, and is kept only where held-out pixels
    and the corners (held out of it; against the corner fit's k-fold `held_out` RMS) do not reject it.
    """
    images = _grey_photos(result, args, photos)
    block = {"corner_fit": {k: result.values.get(k) for k in LENS_KEYS},
             "corner_fit_sigma": {k: result.sigma.get(k) for k in LENS_KEYS}}
    res = _refine(images, target, result, obs, args, say, held_out)
    for e in res.left_out:
        if getattr(args, "quiet", False):   # without -q the refinement said so as it happened
            print(f"tiltfit: note: photometric refinement: {result.views[e['view']]['image']} left out of the fit "
                  f"(its pose stays the corner fit's): {e['reason']}", file=sys.stderr, flush=True)
    v, sg = res.values, res.sigma
    block.update(left_out=[{"view": e["view"], "image": result.views[e["view"]]["image"], "reason": e["reason"]}
                           for e in res.left_out])
    block.update(kept=res.kept, held_out=res.held_out, refined={k: v[k] for k in LENS_KEYS},
                 refined_sigma={k: sg[k] for k in LENS_KEYS}, corner_check=res.corner_check, free=res.free,
                 at_bound=res.at_bound, rejected_because=res.rejected_because, sigma_model=res.sigma_model,
                 bounds=res.bounds)
    exposure = _exposure(res)
    if res.kept != "photometric":
        # Not progress: the user asked for a refinement and gets the corner fit, so this line shows even with -q.
        print(f"tiltfit: note: photometric refinement not kept ({res.rejected_because}); CALIB.json keeps the "
              "corner fit", file=sys.stderr, flush=True)
        # The refinement's exposure too: `tiltfit report` draws the residual image through the corner fit with its
        # vignetting and illumination gradient (the levels refitted there, as the held-out check refits them).
        block.update(rms_linear=res.rms, iterations=res.iterations, runtime_s=res.runtime_s, **exposure)
        return block
    _adopt(result, res, obs)
    block.update(rms_linear=res.rms, iterations=res.iterations, runtime_s=res.runtime_s, **exposure,
                 kernel=v["kernel"],
                 psf_sigma_px=v["psf_sigma_px"], psf_sigma_px_sigma=sg["psf_sigma_px"],
                 aperture=v["aperture"], closed_form_pixels=v["closed_form_pixels"],
                 lens_samples=v["lens_samples"])
    if res.kernel_selection is not None:
        block["kernel_selection"] = res.kernel_selection
    say(f"photometric refinement: RMS {res.rms:.4g} (linear), θL {v['theta_L_deg']:+.4f} ± {sg['theta_L_deg']:.4f}°, "
        f"U {v['U_mm']:.2f} mm, d {v['d_mm']:.3f} mm ({res.iterations} iterations, {res.runtime_s:.1f} s)")
    return block


def _grey_photos(result, args, photos: dict | None) -> list:
    """The fitted views' photographs as float64 grey images (H, W) (the channels' mean), in view order: those
    already read (`photos`, by path), the others read now."""
    import numpy as np

    from camio.files import ImageIOError
    from renderer import read_image

    images = []
    for view in result.views:
        path = view["image"]
        if is_det_file(path):
            raise CliError(path, "--refine photometric needs the photographs, not DET files")
        try:
            img = (photos or {}).get(path)
            img = np.asarray(read_image(path, args.encoding) if img is None else img, dtype=np.float64)
        except (ImageIOError, OSError, ValueError) as e:
            raise as_cli_error(path, e) from None
        images.append(img.mean(-1) if img.ndim == 3 else img)
    return images


def _refine(images: list, target, result, obs, args, say, held_out: dict | None):
    """`refine_photometric` from the corner fit, with the command line's kernel (`--psf`)."""
    from tiltfit.photometric import PhotometricError, PhotometricOptions, refine_photometric

    try:
        return refine_photometric(images, target, result.camera,
                                  # 0 lens samples: from the blur; photographs of a megapixel or more fit 1,000
                                  # pixels a view (about 2 s a view on 2 cores; 2,000 doubles it)
                                  PhotometricOptions(kernel=args.psf, lens_samples=0,
                                                     max_pixels=1000 if images[0].size >= 1 << 20 else 2000),
                                  say=say, start_sigma=result.sigma, corners=obs,
                                  corner_held_out_px=(held_out or {}).get("rms_px"),
                                  start_covariance=result.intrinsics_covariance)
    except PhotometricError as e:
        raise CliError(args.inputs[0], f"photometric refinement: {e}") from None


def _exposure(res) -> dict:
    """The refinement's vignetting and each view's levels (None for a view left out of the fit)."""
    return {"vignetting": res.values["vignetting"],
            "levels": [None if "left_out" in x else {k: x[k] for k in ("white", "black", "gain_x", "gain_y") if k in x}
                       for x in res.views]}


def _adopt(result, res, obs) -> None:
    """Write a kept refinement into `result`: the refined lens and poses into its camera, and the values, σ,
    undetermined keys, residuals and views derived from them."""
    import torch

    from tiltfit.calibrate.model import residuals

    cam, sg = result.camera, res.sigma
    with torch.no_grad():
        cam.load_state_dict(res.camera.state_dict())   # the refined lens and poses, in the fit's own module
        r = residuals(cam, obs)
        rms_corners, rms_blur = r.rms_per_view()
    result.values.update({k: x for k, x in cam.summary().items() if k in result.values})
    # σ of the refined keys from the photometric covariance; f and the paper's θL are not propagated.
    result.sigma.update({k: sg[k] for k in LENS_KEYS}, f_mm=None, theta_L_paper_deg=None)
    if "inv_U_per_m" in res.free:
        # U fitted: the pixels determined it and d with it. Where the corners could not tell U the refinement holds
        # it at the start's placeholder and fits d beside it, a blur scale with no focus distance: both stay
        # undetermined (null), not the placeholder U with σ 0.
        result.undetermined = [k for k in result.undetermined if k not in ("U_mm", "d_mm")]
    result.rss = dict(result.rss, corners=float((r.corners_px**2).sum()))
    for k, (view, fitted) in enumerate(zip(result.views, res.views)):
        view.update(R=cam.R[k].tolist(), T_mm=cam.T_mm[k].tolist(), rms_reprojection_px=float(rms_corners[k]),
                    rms_blur_px=float(rms_blur[k]))
        if "rms" in fitted:   # not for a view left out of the fit
            view["rms_photometric"] = fitted["rms"]
