"""Photometric refinement: fit poses, lens and exposure to the photographs' pixels by rendering the target.

This is the analysis-by-synthesis step. Starting from a corner-and-blur calibration, every photograph is
re-rendered from the current parameters and compared with the photo pixel by pixel; the parameters move to
make the two agree. Corners are only a starting point, so their bias under heavy blur and lens tilt does not
reach the result, and boards too blurred for any corner detector can still be fitted.

The target renderer uses the renderer's own thin-lens camera (`renderer.ThinLensCamera`, tensor parameters)
and no general tracer and no random numbers, so the objective is smooth and deterministic and its gradients
are exact (checked against finite differences in the tests). It integrates each pixel over the lens's
aperture in one of two ways (`PhotometricOptions.aperture`):
- in closed form (`render_target_disc`, the default from 3 px of blur): each of 4 x 4 points of the pixel
  sees the aperture disc through its focus point (`ThinLensCamera.focus_geometry`), on which the board's
  cell edges are straight lines, so the dark fraction is a sum of disc segments and wedges
  (`tiltfit.aperture`). Exact for the thin lens at any tilt and blur, and cheaper per pixel than 192 lens
  samples (`benchmarks/results/photometric.md`). `auto`, the default, takes it for pixels
  whose blur disc is at least 3 px, and the samples below;
- by a fixed set of lens samples (`render_target`): rays for each pixel and sample, intersected with the
  board plane Z = 0, the checker evaluated analytically and antialiased over the pixel's footprint (below).
  Sharp boards need it: there the pixel's box matters more than the disc.

Model of one photograph (linear intensities, image (H, W)):
    I(u) = (1 − v ρ(u)²) · (white_k − (white_k − black_k) · D(u))
where D(u) ∈ [0, 1] is the dark fraction of the board seen by pixel u (average over the lens samples of the
antialiased checker), white_k and black_k the view's radiance of white paper and dark cells, v the lens's
vignetting and ρ the distance from the image centre, 1 at the corners: the fall-off of the one sensor model,
`renderer.sensor` (`radial_falloff`), which `tiltfit.synth` and the simulated camera of `tiltfit.experiments.reproduce`
expose their captures with.

Antialiased checker: for a hit (X, Y) on the board with pixel footprint σ (mm), per axis the nearest cell edge
e_j and z = (X − e_j)/σ give A = E[inside] and B = E[inside · s] (s = ±1 the column's parity sign) under a
Gaussian of standard deviation σ; the dark fraction is D = ½ (A_x A_y + p B_x B_y) with p the parity of
`dark_cell`. σ along X and along Y match the variance of the pixel's box footprint on the board (from the
local Jacobian of the chief-ray map), so the pixel's area adds the blur a box filter adds. The lens samples
are a fixed Hammersley set whitened to the disc's second moment (`hammersley_disc_samples`), traced from 2 x 2
sub-pixels. Their number must grow with the blur disc's area: at 18 px, 64 samples gave θL +0.015° and d −0.3 %
on average on captures of a fine disc, 192 no bias beyond σ (`benchmarks/results/photometric_diagnosis.md`).

Parameters fitted (Levenberg–Marquardt with Huber weights, Jacobians by forward-mode autodiff, one view
block at a time): w, 1/U (so U = ∞ is an ordinary value), d, θF, vignetting v, and per view the pose
(axis-angle, translation) and white/black levels. The principal point and the pixel pitch are held.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from renderer.cameras import Lens, Sensor, ThinLensCamera, concentric_disk
from renderer.optics import blur_diameter_first_order, blur_diameter_paper, theta_L_from_theta_F
from renderer.sensor import radial_falloff

from .aperture import checker_dark_fraction_disc, lines_cut
from .model import axis_angle_to_matrix, matrix_to_axis_angle, robust_weight
from .stats import nested_test
from .target import Target

#: Names of the global parameters in the flat vector, in order (units: mm, 1/m, mm, rad, dimensionless).
GLOBAL_NAMES = ("w_mm", "inv_U_per_m", "d_mm", "theta_F", "vignetting", "psf_sigma_px")
#: Blur kernels: the lens's disc alone, or the disc convolved with a Gaussian (diffraction, aberrations,
#: the sensor's own spread) of std psf_sigma_px in pixels (stored signed, squared in the model, so it has no
#: bound to stall on); `auto` frees the Gaussian where the data justify it (likelihood-ratio test and BIC on
#: the same pixels) and it is at least PSF_EVIDENCE_PX wide.
KERNELS = ("disc", "disc_gaussian", "auto")
AUTO_KERNEL_LENS_SAMPLES = 128
#: `lens_samples=0` (auto) takes 64 · (b / 10 px)² samples for the start's largest blur disc b at the board's
#: centre, in multiples of 16, from 64 to this many (`auto_lens_samples`).
AUTO_LENS_SAMPLES_MAX = 256
PSF_EVIDENCE_PX = 0.5    # narrower Gaussians `auto` rejects: the fixed lens samples' own coarseness
PSF_START_PX = 0.5       # where a freed Gaussian starts (σ = 0 is a stationary point of σ²)
#: Per-view parameters: axis-angle (rad), translation (mm), white and black linear levels.
#: Sensor points per pixel side of the closed-form aperture (`render_target_disc`).
SUBPIXELS = 4
#: `aperture="auto"` integrates the disc in closed form from this blur-disc diameter (px) at the start on;
#: below it the pixel's box matters more than the disc and the fixed lens samples' Gaussian footprints model it.
CLOSED_FORM_MIN_BLUR_PX = 3.0
APERTURES = ("auto", "closed_form", "samples")
#: Pixels per block of the fit's forward-mode Jacobian (bounds its memory; results do not depend on it).
JACOBIAN_BLOCK = 2048
VIEW_NAMES = ("rvec_x", "rvec_y", "rvec_z", "T_x", "T_y", "T_z", "white", "black")


class PhotometricError(RuntimeError):
    """The photometric fit cannot run or did not converge (one-line message)."""


@dataclass(frozen=True)
class PhotometricOptions:
    """How the refinement runs.

    Attributes:
        lens_samples: fixed lens samples per pixel [64] (a whitened Hammersley set), each traced
            from the pixel's 4 sub-pixel centres. Too few for blur discs of 18 px (use about 192 there; the
            number grows with the disc's area; see the module docstring). 0: from the start's blur
            (`auto_lens_samples`).
        max_pixels: pixels used per view [2000], chosen where the image carries information (edges), plus
            a share of flat pixels for the exposure levels.
        iterations: Levenberg–Marquardt iterations at most [30].
        huber_scale: Huber threshold in units of the residuals' robust σ [3].
        fit_vignetting: fit the vignetting coefficient [True].
        kernel: blur kernel, one of KERNELS [disc]. `auto` needs at least AUTO_KERNEL_LENS_SAMPLES lens
            samples and a Gaussian of at least PSF_EVIDENCE_PX: the fixed samples' own coarseness looks like
            a narrow Gaussian to the likelihood-ratio test (in a trial on ray-traced captures without one,
            fewer samples freed a wider one and moved d; see docs/photometric.md).
        alpha: level of the kernel's likelihood-ratio test under `auto` [0.01].
        seed: seed of the pixel selection [0].
        aperture: how each pixel integrates the lens's disc, one of APERTURES [auto]: `closed_form` exactly
            (`render_target_disc`: no lens samples, no sample pattern to bias d or θL; disc kernel only),
            `samples` by the fixed lens samples (`render_target`), `auto` the closed form for the pixels whose
            blur disc at the start is at least CLOSED_FORM_MIN_BLUR_PX (with the disc kernel), the samples for
            the others (their Gaussian footprints model the pixel's box, which a sharp edge needs).
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

    def __post_init__(self):
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


@dataclass
class PhotometricResult:
    """What `refine_photometric` found.

    Attributes:
        values: w_mm, U_mm (inf when 1/U = 0), inv_U_per_m, d_mm, theta_F_deg, theta_L_deg, vignetting,
            psf_sigma_px (σ of the Gaussian part of the kernel, 0 for the disc alone), kernel, lens_samples
            (the fixed lens samples used).
        sigma: one-σ uncertainties of the same keys, from the cluster-robust sandwich covariance
            (`_cluster_sandwich`: errors shared by neighbouring pixels and noise that varies over the image
            are counted).
        sigma_gauss_newton: the textbook σ, (J^T W J)⁻¹ scaled by the residuals' robust σ, which assumes
            independent residuals of one variance (too small on ray-traced captures; kept for comparison).
        views: per view: R (3×3), T_mm, white, black, rms (linear units), n_pixels.
        rms: RMS photometric residual over all views (linear intensity units).
        iterations, runtime_s, history: LM iterations, wall time, cost per iteration.
        kernel_selection: under kernel `auto`, the test that chose the kernel (Λ, p, ΔBIC, costs).
    """

    values: dict
    sigma: dict
    views: list
    rms: float
    iterations: int
    runtime_s: float
    history: list = field(default_factory=list)
    kernel_selection: dict | None = None
    sigma_gauss_newton: dict | None = None


# ---------------------------------------------------------------------------------------------------------
# The target renderer
# ---------------------------------------------------------------------------------------------------------

def _inverse_concentric(xy: np.ndarray) -> np.ndarray:
    """Points on the unit disc (..., 2) -> the [0, 1)² samples that `concentric_disk` maps to them."""
    x, y = xy[..., 0], xy[..., 1]
    r = np.hypot(x, y)
    phi = np.mod(np.arctan2(y, x) + np.pi / 4, 2 * np.pi) - np.pi / 4   # in [−π/4, 7π/4)
    a, b = np.empty_like(r), np.empty_like(r)
    sectors = ((phi < np.pi / 4), (phi >= np.pi / 4) & (phi < 3 * np.pi / 4),
               (phi >= 3 * np.pi / 4) & (phi < 5 * np.pi / 4), phi >= 5 * np.pi / 4)
    s0, s1, s2, s3 = sectors
    a[s0], b[s0] = r[s0], r[s0] * phi[s0] * 4 / np.pi
    b[s1], a[s1] = r[s1], r[s1] * (np.pi / 2 - phi[s1]) * 4 / np.pi
    a[s2], b[s2] = -r[s2], -r[s2] * (phi[s2] - np.pi) * 4 / np.pi
    b[s3], a[s3] = -r[s3], -r[s3] * (np.pi / 2 - (phi[s3] - np.pi)) * 4 / np.pi
    return np.stack([(a + 1) / 2, (b + 1) / 2], -1)


def auto_lens_samples(blur_px: float, minimum: int = 64) -> int:
    """Fixed lens samples for a blur disc of `blur_px` px: 64 · (b / 10 px)², so the samples' spacing on the
    image stays about 1.1 px, in multiples of 16, between `minimum` and AUTO_LENS_SAMPLES_MAX (192 samples
    at 18 px left no bias beyond σ where 64 gave θL +0.015° and d −0.3 %; module docstring)."""
    n = 16 * math.ceil(64.0 * (max(float(blur_px), 0.0) / 10.0) ** 2 / 16)
    return int(min(AUTO_LENS_SAMPLES_MAX, max(minimum, n)))


def hammersley_disc_samples(n: int, dtype=torch.float64) -> torch.Tensor:
    """(n, 2) fixed lens samples in [0, 1)²: a Hammersley set ((i + ½)/n, radical inverse of i) whose
    points on the aperture are whitened to the disc's first and second moments (mean 0, covariance r²/4 · I),
    then mapped back through the inverse of the renderer's concentric map.

    Hammersley keeps n distinct radii and angles, so edge profiles are smooth; the whitening is a small
    linear correction (the plain 64-point set has E xy = 0.026 r² and E r² 2.3 % low: an elliptical,
    tilted aperture, which biased θF on sharp boards and d).
    """
    n = max(int(n), 1)
    if n < 4:
        return torch.full((1, 2), 0.5, dtype=dtype)
    i = np.arange(n)
    inv = np.zeros(n)
    base, k = 0.5, i.copy()
    while k.any():
        inv += (k & 1) * base
        k >>= 1
        base /= 2
    uv = np.stack([(i + 0.5) / n, (inv + 0.5 / n) % 1.0], -1)
    xy = concentric_disk(torch.tensor(uv)).numpy()
    xy = xy - xy.mean(0)
    evals, evecs = np.linalg.eigh(xy.T @ xy / n)
    xy = xy @ (evecs @ np.diag(np.sqrt(0.25 / evals)) @ evecs.T)
    r = np.hypot(xy[:, 0], xy[:, 1])
    xy = xy * np.minimum(1.0, (1 - 1e-12) / np.maximum(r, 1e-300))[:, None]
    return torch.tensor(np.clip(_inverse_concentric(xy), 0.0, np.nextafter(1.0, 0.0)), dtype=dtype)


def _axis_terms(coord: torch.Tensor, edges: torch.Tensor, sigma: torch.Tensor):
    """A = E[inside], B = E[inside · s] along one axis for Gaussian footprints (see the module docstring)."""
    n_cells = edges.shape[0] - 1
    k = torch.searchsorted(edges, coord.detach().contiguous()).clamp(1, n_cells)
    left, right = edges[k - 1], edges[k]
    j = torch.where((coord - left) < (right - coord), k - 1, k)   # nearest edge index, 0..n_cells
    z = (coord - edges[j]) / sigma
    phi = 0.5 * (1 + torch.erf(z / math.sqrt(2)))
    sign_right = 1.0 - 2.0 * (j % 2).to(coord.dtype)              # (−1)^j: parity sign of cell j
    interior = (j > 0) & (j < n_cells)
    a = torch.where(interior, torch.ones_like(z), torch.where(j == 0, phi, 1 - phi))
    b_interior = sign_right * torch.erf(z / math.sqrt(2))
    b_first = phi                                                  # cell 0 has sign +1
    b_last = -sign_right * (1 - phi)                               # cell n−1 has sign −(−1)^n
    b = torch.where(interior, b_interior, torch.where(j == 0, b_first, b_last))
    return a, b


def checker_dark_fraction(X: torch.Tensor, Y: torch.Tensor, sigma: torch.Tensor, target: Target,
                          sigma_y: torch.Tensor | None = None) -> torch.Tensor:
    """Dark fraction of the board seen through a Gaussian footprint of std `sigma` (mm) centred at (X, Y) mm.

    Exact for a footprint whose X and Y are independent (the dark set is a sum of products of an X-only and
    a Y-only indicator), up to the nearest-edge approximation (σ much smaller than a cell).

    Args:
        X, Y, sigma: (...) target-frame coordinates and footprint std along X, mm.
        sigma_y: footprint std along Y [sigma].
    Returns:
        (...) in [0, 1]: 1 inside a dark cell, 0 on white cells and on the margin.
    """
    xe = torch.tensor(target.x_edges, dtype=X.dtype, device=X.device)
    ye = torch.tensor(target.y_edges, dtype=X.dtype, device=X.device)
    ax, bx = _axis_terms(X, xe, sigma)
    ay, by = _axis_terms(Y, ye, sigma if sigma_y is None else sigma_y)
    parity = 1.0 if (target.dark_cell[0] + target.dark_cell[1]) % 2 == 0 else -1.0
    return 0.5 * (ax * ay + parity * bx * by)


@dataclass(frozen=True)
class SensorGeometry:
    """The held part of the camera: image size (W, H) px, pixel pitch mm, principal point (cx, cy) px and
    the lens distortion coefficients (OpenCV's order, None: none)."""

    width_px: int
    height_px: int
    pixel_pitch_mm: float
    principal_point_px: tuple[float, float]
    distortion: tuple | None = None


def lens_camera(sensor: SensorGeometry, w_mm, inv_U_per_m, d_mm, theta_F, rvec, T_mm) -> ThinLensCamera:
    """The renderer's thin-lens camera for one view, all lens and pose values as (differentiable) tensors.

    Args:
        rvec: (3,) axis-angle of R (camera_from_target); T_mm: (3,) translation; X_cam = R X + T.
    The sensor's distortion (held, not fitted) is the renderer's: pixels are traced through their ideal,
    undistorted positions. Built as `renderer.LensCamera.view_camera` builds a view (one construction path).
    """
    lens = Lens(w_mm, 1000.0 / inv_U_per_m, d_mm, theta_F,
                Sensor(sensor.width_px, sensor.height_px, sensor.pixel_pitch_mm), sensor.principal_point_px,
                sensor.distortion)
    return ThinLensCamera.from_calibration(lens, axis_angle_to_matrix(rvec), T_mm)


def render_target(target: Target, sensor: SensorGeometry, uv_px: torch.Tensor, lens_uv: torch.Tensor,
                  w_mm, inv_U_per_m, d_mm, theta_F, rvec, T_mm, white, black, vignetting,
                  psf_var_px2=0.0) -> torch.Tensor:
    """Linear intensity of the target seen by pixels `uv_px`, averaged over the fixed lens samples.

    Args:
        uv_px: (N, 2) pixel positions (x = column, y = row).
        lens_uv: (S, 2) lens samples in [0, 1)², the same for every pixel; their points on the aperture should
            have the disc's moments (`hammersley_disc_samples` does), or d comes out scaled.
        w_mm, inv_U_per_m, d_mm, theta_F, vignetting, white, black: 0-dim tensors; rvec, T_mm: (3,).
        psf_var_px2: variance (px²) of a Gaussian convolved with the lens's disc [0: the disc alone]; it
            widens each sub-pixel's Gaussian footprint on the board.
    Returns:
        (N,) linear intensities (the model of the module docstring). 1/U must be > 0 here (a finite U);
        `refine_photometric` keeps it so.
    """
    cam = lens_camera(sensor, w_mm, inv_U_per_m, d_mm, theta_F, rvec, T_mm)
    n, s = uv_px.shape[0], lens_uv.shape[0]
    # The pixel's area: every lens sample is traced from each of the 2 x 2 sub-pixel centres, and each
    # sub-pixel's remaining box (half a pixel wide) is a Gaussian footprint on the board of the same
    # variance, per board axis, from the chief rays of the pixel and of its right and lower neighbours
    # (J = d(X, Y)/d(u, v)): (J_u² + J_v²) / (4 · 12). A single Gaussian for the whole pixel misses the
    # box's shape, which matters where the blur is a pixel or two (it biased θF by 0.1° on sharp boards).
    sub = torch.tensor([[-0.25, -0.25], [0.25, -0.25], [-0.25, 0.25], [0.25, 0.25]], dtype=uv_px.dtype,
                       device=uv_px.device)
    uv_s = (uv_px[:, None, None, :] + sub[None, :, None, :]).expand(n, 4, s, 2)
    rays = cam.generate_rays(uv_s, lens_uv[None, None].expand(n, 4, s, 2))
    hit = _on_board(rays).reshape(n, 4 * s, 3)
    steps = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]], dtype=uv_px.dtype, device=uv_px.device)
    chief = _on_board(cam.generate_rays(uv_px[:, None, :] + steps, torch.full((n, 3, 2), 0.5, dtype=uv_px.dtype)))
    J = chief[:, 1:, :2] - chief[:, :1, :2]              # (N, 2 (du, dv), 2 (X, Y))
    sigma_xy = torch.sqrt((J**2).sum(1) * (1.0 / 48.0 + psf_var_px2))  # (N, 2)
    dark = checker_dark_fraction(hit[..., 0], hit[..., 1], sigma_xy[:, None, 0], target,
                                 sigma_y=sigma_xy[:, None, 1]).mean(-1)
    falloff = radial_falloff(uv_px[:, 0], uv_px[:, 1], sensor.width_px, sensor.height_px, vignetting)
    return falloff * (white - (white - black) * dark)


def render_target_disc(target: Target, sensor: SensorGeometry, uv_px: torch.Tensor, near: int,
                       w_mm, inv_U_per_m, d_mm, theta_F, rvec, T_mm, white, black, vignetting,
                       subpixels: int = SUBPIXELS) -> torch.Tensor:
    """`render_target` with the aperture integrated in closed form (`tiltfit.aperture`): no lens samples.

    Each pixel is the mean of a `subpixels` x `subpixels` grid of sensor points (a box pixel by the midpoint
    rule: fine once the blur disc spans a few pixels, which is where `aperture="auto"` uses it); each point's
    dark fraction is exact over the disc. `near`: lines per family given the two-line term
    (`tiltfit.aperture.lines_cut` counts them). Arguments and result otherwise as in `render_target` (disc kernel only).
    """
    cam = lens_camera(sensor, w_mm, inv_U_per_m, d_mm, theta_F, rvec, T_mm)
    q_h, centre, axes, _ = cam.focus_geometry(_sub_points(uv_px, subpixels))
    dark = checker_dark_fraction_disc(q_h, centre, axes, target, near).mean(-1)
    falloff = radial_falloff(uv_px[:, 0], uv_px[:, 1], sensor.width_px, sensor.height_px, vignetting)
    return falloff * (white - (white - black) * dark)


def _sub_points(uv_px: torch.Tensor, subpixels: int = SUBPIXELS) -> torch.Tensor:
    """(N, subpixels², 2) the midpoint-rule points of each pixel of `uv_px` (N, 2)."""
    step = (torch.arange(subpixels, dtype=uv_px.dtype, device=uv_px.device) + 0.5) / subpixels - 0.5
    sub = torch.stack(torch.meshgrid(step, step, indexing="xy"), -1).reshape(-1, 2)
    return uv_px[:, None, :] + sub


def _on_board(rays) -> torch.Tensor:
    """(..., 3) points where rays meet the board plane Z = 0 (target frame)."""
    t = -rays.origin[..., 2] / rays.direction[..., 2]
    return rays.origin + t[..., None] * rays.direction


# ---------------------------------------------------------------------------------------------------------
# The fit
# ---------------------------------------------------------------------------------------------------------

@dataclass
class _View:
    uv: torch.Tensor          # (N, 2) pixels used
    observed: torch.Tensor    # (N,) linear intensities
    n_closed_form: int = 0    # the first n_closed_form pixels integrate the aperture in closed form


def _select_pixels(image: np.ndarray, predicted: np.ndarray, usable: np.ndarray, white: float, black: float,
                   max_pixels: int, rng: np.random.Generator) -> np.ndarray:
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


# Pixels whose rays `_usable_mask` generates at once (about 2 KB each with its ring of lens samples and the
# intermediates): at 5472×3648 all pixels at once took more than 17 GB (`tiltfit reproduce --target-scale 1`
# was killed); 684×456 images stay one chunk.
MASK_CHUNK_PIXELS = 1 << 19
# Candidate pixels whose brightness is predicted before picking the pixels to fit (`_select_pixels`): above it
# a regular subset of the usable pixels (every k-th); images up to 2^19 pixels keep them all.
MAX_CANDIDATE_PIXELS = 1 << 19


def _usable_mask(target: Target, sensor: SensorGeometry, glob: torch.Tensor, view: torch.Tensor,
                 lens_uv: torch.Tensor) -> np.ndarray:
    """(H, W) pixels whose every lens sample lands on the board, margin included, away from its outer edge.
    Two passes over chunks of MASK_CHUNK_PIXELS pixels: the margin (two pixels, mm) needs the largest ray
    length over the whole image first."""
    W, H = sensor.width_px, sensor.height_px
    x0, y0, x1, y1 = target.extent_mm
    with torch.no_grad():
        cam = lens_camera(sensor, glob[0], glob[1], glob[2], glob[3], view[0:3], view[3:6])
        ring = lens_uv[:: max(1, lens_uv.shape[0] // 16)]
        ring = torch.cat([ring, torch.tensor([[0.0, 0.5], [1.0, 0.5], [0.5, 0.0], [0.5, 1.0]], dtype=ring.dtype)])

        def hits(a: int):
            flat = torch.arange(a, min(a + MASK_CHUNK_PIXELS, H * W))
            uv = torch.stack([(flat % W).to(torch.float64), (flat // W).to(torch.float64)], -1)
            n, s = uv.shape[0], ring.shape[0]
            rays = cam.generate_rays(uv[:, None, :].expand(n, s, 2), ring[None].expand(n, s, 2))
            t = -rays.origin[..., 2] / rays.direction[..., 2]
            return t, rays.origin + t[..., None] * rays.direction

        starts = range(0, H * W, MASK_CHUNK_PIXELS)
        first = hits(0)  # kept for the second pass where it is the only chunk (images up to 2^19 pixels)
        t_max = max([float(first[0].abs().max())] + [float(hits(a)[0].abs().max()) for a in starts[1:]])
        guard = 2.0 * float(cam.screen.pitch[0]) * t_max / float(glob[0])
        ok = np.empty(H * W, dtype=bool)
        for a in starts:
            t, hit = first if a == 0 and len(starts) == 1 else hits(a)
            inside = (t > 0) & (hit[..., 0] > x0 + guard) & (hit[..., 0] < x1 - guard) & \
                     (hit[..., 1] > y0 + guard) & (hit[..., 1] < y1 - guard)
            ok[a:a + t.shape[0]] = inside.all(-1).numpy()
    return ok.reshape(H, W)


def _initial_levels(image: np.ndarray, usable: np.ndarray) -> tuple[float, float]:
    vals = image[usable]
    if vals.size < 100:
        raise PhotometricError("the board covers fewer than 100 usable pixels in a view")
    return float(np.percentile(vals, 97)), float(np.percentile(vals, 3))


def refine_photometric(images, target: Target, init: dict, pixel_pitch_mm: float,
                       options: PhotometricOptions | None = None, say=None) -> PhotometricResult:
    """Fit lens, poses and exposure to the photographs by rendering the target (analysis by synthesis).

    Args:
        images: list of (H, W) or (H, W, 3) linear images (decode sRGB first), one per view.
        target: the board.
        init: a calibration in CALIB.json's shape: w_mm, U_mm (None: at infinity), d_mm (None: 1 mm),
            theta_F_deg [0], principal_point_px [image centre], distortion [none; held],
            views: [{R, T_mm}, ...] one per image.
        pixel_pitch_mm: sensor pixel pitch.
        options: PhotometricOptions.
        say: optional progress callback taking one line.
    Returns:
        PhotometricResult.
    """
    opts = options or PhotometricOptions()
    t0 = time.perf_counter()
    imgs = [np.asarray(im, dtype=np.float64) for im in images]
    imgs = [im.mean(-1) if im.ndim == 3 else im for im in imgs]
    if not imgs:
        raise PhotometricError("no images to refine")
    if len(init.get("views", [])) != len(imgs):
        raise PhotometricError(f"init has {len(init.get('views', []))} views for {len(imgs)} images")
    H, W = imgs[0].shape
    pp = init.get("principal_point_px") or ((W - 1) / 2.0, (H - 1) / 2.0)
    dist = (init.get("distortion") or {}).get("coefficients")
    dist = tuple(float(c) for c in dist) if dist and any(dist) else None
    sensor = SensorGeometry(W, H, float(pixel_pitch_mm), (float(pp[0]), float(pp[1])), dist)
    U0 = init.get("U_mm")
    inv_U0 = 1000.0 / U0 if U0 not in (None, 0) and math.isfinite(U0) else 1e-3
    d0 = init.get("d_mm") if init.get("d_mm") is not None else 1.0
    psf0 = PSF_START_PX if opts.kernel == "disc_gaussian" else 0.0
    glob = torch.tensor([init["w_mm"], inv_U0, max(d0, 1e-3), math.radians(init.get("theta_F_deg") or 0.0), 0.0,
                         psf0], dtype=torch.float64)
    starts = [torch.tensor([*matrix_to_axis_angle(v["R"]).reshape(3).tolist(), *np.asarray(v["T_mm"], dtype=float),
                            0.0, 0.0], dtype=torch.float64) for v in init["views"]]
    blur = max(_view_blur_px(glob, vp, sensor, target) for vp in starts)
    # Which pixels integrate the aperture in closed form: all (closed_form), none (samples, or a kernel with
    # a Gaussian part), or under auto those whose blur disc at the start is at least CLOSED_FORM_MIN_BLUR_PX.
    disc_only = opts.kernel == "disc" and opts.aperture != "samples"
    n_edges = max(len(target.x_edges), len(target.y_edges))
    near = 1
    n_samples = opts.lens_samples
    if not disc_only and n_samples == 0:
        n_samples = auto_lens_samples(blur, AUTO_KERNEL_LENS_SAMPLES if opts.kernel == "auto" else 64)
    elif n_samples == 0:
        n_samples = auto_lens_samples(CLOSED_FORM_MIN_BLUR_PX)   # for the sharper pixels only
    lens_uv = hammersley_disc_samples(n_samples)
    rng = np.random.default_rng(opts.seed)
    views_p, data = [], []
    for k, (im, v) in enumerate(zip(imgs, init["views"])):
        if im.shape != (H, W):
            raise PhotometricError(f"view {k}: image is {im.shape[1]}x{im.shape[0]}, expected {W}x{H}")
        rvec = matrix_to_axis_angle(v["R"]).tolist()
        vp = torch.tensor([*rvec, *np.asarray(v["T_mm"], dtype=np.float64), 0.0, 0.0], dtype=torch.float64)
        usable = _usable_mask(target, sensor, glob, vp, lens_uv)
        white, black = _initial_levels(im, usable)
        vp[6], vp[7] = white, black
        if usable.sum() > MAX_CANDIDATE_PIXELS:  # a regular subset: predicting all of a 20 MP photo is slow
            keep = np.flatnonzero(usable)
            usable = np.zeros_like(usable)
            usable.reshape(-1)[keep[::-(-keep.size // MAX_CANDIDATE_PIXELS)]] = True
        yy, xx = np.nonzero(usable)
        uv_all = torch.tensor(np.stack([xx, yy], -1), dtype=torch.float64)
        with torch.no_grad():
            pred = np.empty(uv_all.shape[0])
            for a in range(0, uv_all.shape[0], 8192):
                pred[a:a + 8192] = render_target(target, sensor, uv_all[a:a + 8192], lens_uv[::4], *glob[:4],
                                                 vp[0:3], vp[3:6], vp[6], vp[7], glob[4], glob[5]**2).numpy()
        pred_img = np.full((H, W), np.nan)
        pred_img[yy, xx] = pred
        pick = _select_pixels(im, pred_img.reshape(-1), usable.reshape(-1), white, black, opts.max_pixels, rng)
        uv = torch.tensor(np.stack([pick % W, pick // W], -1), dtype=torch.float64)
        observed = torch.tensor(im.reshape(-1)[pick], dtype=torch.float64)
        cam = lens_camera(sensor, *glob[:4], vp[0:3], vp[3:6])
        if opts.aperture == "closed_form":
            closed = torch.ones(uv.shape[0], dtype=torch.bool)
        elif disc_only:
            closed = _pixel_blur_px(cam, uv, sensor) >= CLOSED_FORM_MIN_BLUR_PX
        else:
            closed = torch.zeros(uv.shape[0], dtype=torch.bool)
        order = torch.argsort((~closed).to(torch.int8), stable=True)     # closed-form pixels first
        n_closed = int(closed.sum())
        data.append(_View(uv[order], observed[order], n_closed))
        views_p.append(vp)
    n_closed = sum(d.n_closed_form for d in data)
    n_pixels = sum(int(d.uv.shape[0]) for d in data)
    aperture = "closed_form" if n_closed == n_pixels else "samples" if n_closed == 0 else "mixed"
    if say:
        say(f"photometric: {len(imgs)} views, {n_pixels} pixels, aperture "
            + {"closed_form": f"in closed form ({SUBPIXELS}x{SUBPIXELS} points per pixel)",
               "samples": f"by {n_samples} lens samples per pixel",
               "mixed": f"in closed form for {n_closed} pixels (blur from {CLOSED_FORM_MIN_BLUR_PX:g} px), "
                        f"by {n_samples} lens samples for the other {n_pixels - n_closed}"}[aperture])

    n_g, n_v = len(GLOBAL_NAMES), len(VIEW_NAMES)
    free_g = torch.tensor([True, True, True, True, opts.fit_vignetting, opts.kernel == "disc_gaussian"])

    def residual(g, vp, view: _View):
        n = view.n_closed_form
        parts = []
        if n:
            parts.append(render_target_disc(target, sensor, view.uv[:n], near, g[0], g[1], g[2], g[3], vp[0:3],
                                            vp[3:6], vp[6], vp[7], g[4]))
        if n < view.uv.shape[0]:
            parts.append(render_target(target, sensor, view.uv[n:], lens_uv, g[0], g[1], g[2], g[3], vp[0:3],
                                       vp[3:6], vp[6], vp[7], g[4], g[5] ** 2))
        return (torch.cat(parts) if parts else view.observed[:0]) - view.observed

    def grow_near(g, vp, view: _View):
        """`near` covers every line the closed-form points' discs cut now, plus one (the blur may grow before
        the next check, which comes with the next Jacobian)."""
        nonlocal near
        if view.n_closed_form:
            with torch.no_grad():
                cam = lens_camera(sensor, *g[:4], vp[0:3], vp[3:6])
                cut = lines_cut(*cam.focus_geometry(_sub_points(view.uv[:view.n_closed_form]))[:3], target)
            near = min(n_edges, max(near, cut + 1))

    for vp, dv in zip(views_p, data):
        grow_near(glob, vp, dv)

    def jac(g, vp, view):
        grow_near(g, vp, view)
        # In blocks of JACOBIAN_BLOCK pixels: forward mode carries every parameter's tangent through each
        # intermediate, so a whole view at once would hold (pixels x sub-points x lines x parameters) arrays.
        blocks = []
        for a in range(0, view.uv.shape[0], JACOBIAN_BLOCK):
            b = min(a + JACOBIAN_BLOCK, view.uv.shape[0])
            part = _View(view.uv[a:b], view.observed[a:b], min(max(view.n_closed_form - a, 0), b - a))
            blocks.append(torch.func.jacfwd(lambda gg, vv: residual(gg, vv, part), argnums=(0, 1))(g, vp))
        return torch.cat([j[0] for j in blocks]), torch.cat([j[1] for j in blocks])

    def all_residuals(g, vps):
        return torch.cat([residual(g, vp, dv) for vp, dv in zip(vps, data)])

    def robust_weights(r):
        s = 1.4826 * float(torch.median(r.abs())) + 1e-12
        return robust_weight((r / s) ** 2, "huber", opts.huber_scale), s

    n_par = n_g + n_v * len(imgs)
    history = []
    glob, views_p, r, wts, scale, JTJ, it = _levenberg_marquardt(
        glob, views_p, free_g, all_residuals, jac, robust_weights, data, n_par, opts.iterations, history, say)
    selection = None
    if opts.kernel == "auto":
        # The Gaussian part, freed from the disc's solution on the same pixels and weights.
        w0 = wts
        rss0 = float((w0 * r * r).sum())
        free_k = free_g.clone()
        free_k[5] = True
        start_k = glob.clone()
        start_k[5] = PSF_START_PX
        out = _levenberg_marquardt(start_k, views_p, free_k, all_residuals, jac, robust_weights, data, n_par,
                                   opts.iterations, history, say)
        rss1 = float((w0 * out[2] * out[2]).sum())
        test = nested_test([(int(r.numel()), rss0, rss1)], 1, opts.alpha)
        lam_stat, p_value, delta_bic = test["lr_statistic"], test["p_value"], test["delta_bic"]
        psf = abs(float(out[0][5]))
        justified = test["justified"] and psf >= PSF_EVIDENCE_PX
        disc_values = _lens_values(glob)
        selection = {"kernel": "disc_gaussian" if justified else "disc", "lr_statistic": lam_stat,
                     "disc_fit": disc_values,
                     "p_value": p_value, "delta_bic": delta_bic, "rss_disc": rss0, "rss_disc_gaussian": rss1,
                     "psf_sigma_px": psf}
        if say:
            say(f"photometric: kernel {selection['kernel']} (Gaussian σ {selection['psf_sigma_px']:.3f} px, "
                f"Λ = {lam_stat:.3g}, p = {p_value:.2g}, ΔBIC = {delta_bic:.3g})")
        if justified:
            glob, views_p, r, wts, scale, JTJ, it2 = out
            free_g, it = free_k, it + it2
    kernel = "disc_gaussian" if bool(free_g[5]) else "disc"
    if kernel == "disc":
        glob = glob.clone()
        glob[5] = 0.0
    cov_sandwich = _cluster_sandwich(glob, views_p, free_g, jac, r, wts, JTJ, data, sensor, target)
    result = _photometric_result(glob, views_p, r, scale, JTJ, free_g, data, n_g, n_v, n_par, it, t0, history,
                                 kernel, selection, cov_sandwich)
    result.values["lens_samples"] = n_samples if aperture != "closed_form" else 0
    result.values["aperture"] = aperture
    result.values["closed_form_pixels"] = n_closed
    return result


def _lens_values(glob) -> dict:
    """w, U, d, θF, θL of a global parameter vector (mm, degrees)."""
    w, invU, d, thF = (float(x) for x in glob[:4])
    U = 1000.0 / invU
    return {"w_mm": w, "U_mm": U, "d_mm": d, "theta_F_deg": math.degrees(thF),
            "theta_L_deg": math.degrees(float(theta_L_from_theta_F(thF, w, U)))}


def _levenberg_marquardt(glob, views_p, free_g, all_residuals, jac, robust_weights, data, n_par, iterations,
                         history, say):
    """The photometric fit's LM loop (view-blocked normal equations, IRLS Huber weights, Marquardt scaling)
    over the free global parameters `free_g` and every view's parameters. Returns (glob, views_p, r, wts,
    scale, JTJ, iterations)."""
    n_g, n_v = len(GLOBAL_NAMES), len(VIEW_NAMES)
    with torch.no_grad():
        r = all_residuals(glob, views_p)
    wts, scale = robust_weights(r)
    cost = float((wts * r * r).sum())
    lam, it, rel = 1e-3, 0, 0.0
    history.append(cost)
    JTJ = torch.zeros(n_par, n_par, dtype=torch.float64)
    for it in range(1, iterations + 1):
        JTJ = torch.zeros(n_par, n_par, dtype=torch.float64)
        JTr = torch.zeros(n_par, dtype=torch.float64)
        offset = 0
        for k, (vp, dv) in enumerate(zip(views_p, data)):
            jg, jv = jac(glob, vp, dv)
            jg = jg * free_g.to(jg.dtype)
            rk = r[offset:offset + dv.uv.shape[0]]
            wk = wts[offset:offset + dv.uv.shape[0]]
            offset += dv.uv.shape[0]
            J = torch.cat([jg, jv], 1)
            sl = [*range(n_g), *range(n_g + n_v * k, n_g + n_v * (k + 1))]
            sl = torch.tensor(sl)
            JTJ[sl[:, None], sl[None, :]] += J.T @ (wk[:, None] * J)
            JTr[sl] += J.T @ (wk * rk)
        # Marquardt's scaling by the diagonal; a held parameter (zero column) gets 1 so the system stays regular.
        diag = torch.diagonal(JTJ).clone()
        held = diag == 0
        diag[held] = 1.0
        JTJ_reg = JTJ + torch.diag(held.to(JTJ.dtype))
        improved = False
        for _ in range(10):
            A = JTJ_reg + lam * torch.diag(diag)
            step = torch.linalg.solve(A, -JTr)
            g_new = glob + step[:n_g]
            vps_new = [vp + step[n_g + n_v * k: n_g + n_v * (k + 1)] for k, vp in enumerate(views_p)]
            if not (float(g_new[0]) > 0 and float(g_new[1]) > 0 and float(g_new[2]) >= 0
                    and abs(float(g_new[3])) < 1.5):
                lam *= 10
                continue
            with torch.no_grad():
                r_new = all_residuals(g_new, vps_new)
            new_cost = float((wts * r_new * r_new).sum())
            if math.isfinite(new_cost) and new_cost < cost:
                glob, views_p, r = g_new, vps_new, r_new
                rel = (cost - new_cost) / max(cost, 1e-300)
                cost, lam, improved = new_cost, max(lam / 10, 1e-9), True
                break
            lam *= 10
        wts, scale = robust_weights(r)
        cost = float((wts * r * r).sum())
        history.append(cost)
        if say:
            say(f"photometric: iteration {it}, cost {cost:.6g}, θF {math.degrees(float(glob[3])):+.4f}°, "
                f"U {1000.0 / float(glob[1]):.2f} mm, d {float(glob[2]):.4f} mm")
        if not improved or rel < 1e-7:
            break
    return glob, views_p, r, wts, scale, JTJ, it


def _view_blur_px(glob, view, sensor: SensorGeometry, target: Target) -> float:
    """Blur-disc diameter (px) at the board's centre in one view, paper (4) (`optics.blur_diameter_paper`)."""
    x0, y0, x1, y1 = target.extent_mm
    R = axis_angle_to_matrix(view[0:3]).detach()
    p = R @ torch.tensor([(x0 + x1) / 2, (y0 + y1) / 2, 0.0], dtype=R.dtype) + view[3:6].detach()
    w, inv_U, d, theta_F = (float(x) for x in glob[:4])
    return float(blur_diameter_paper(p[1], p[2], w, 1000.0 / inv_U, d, theta_F)) / sensor.pixel_pitch_mm


def _pixel_blur_px(cam: ThinLensCamera, uv: torch.Tensor, sensor: SensorGeometry) -> torch.Tensor:
    """(N,) blur-disc diameter (px) of each pixel at the board point its chief ray meets: w d |1/z_f − 1/z| with
    z_f where that ray meets the plane of focus (`optics.blur_diameter_first_order`)."""
    with torch.no_grad():
        p_cam = cam.transform.points_to_camera(_on_board(cam.generate_rays(uv)))
        lens = cam.lens
        return blur_diameter_first_order(p_cam, lens.w, lens.U, lens.d, lens.theta_F) / sensor.pixel_pitch_mm


def _cluster_sandwich(glob, views_p, free_g, jac, r, wts, JTJ, data, sensor: SensorGeometry,
                      target: Target) -> torch.Tensor:
    """Covariance (n_par, n_par) of all parameters by the cluster-robust sandwich A⁻¹ B A⁻¹ of the Huber fit.

    A = Σ w J J^T is the fit's own normal matrix; B = Σ_c g_c g_c^T sums the score g_c = Σ_{i ∈ c} w_i r_i J_i
    of each cluster c: the pixels of one square tile of a view, as wide as that view's blur disc (at least
    8 px). Residuals of neighbouring pixels share their errors — the same blurred edge mis-modelled, the
    capture's noise varying with the local contrast (Monte Carlo render noise and shot noise are largest on
    edges, where the information is) — so the textbook (J^T W J)⁻¹ s², which assumes independent residuals of
    one variance s², comes out too small. The sandwich needs no noise model, only clusters that are roughly
    independent of each other and many more of them than parameters; it is scaled by C / (C − 1) for C clusters.
    Held parameters get zero rows and columns.
    """
    n_g, n_v = len(GLOBAL_NAMES), len(VIEW_NAMES)
    n_par = n_g + n_v * len(views_p)
    free = torch.cat([free_g, torch.ones(n_v * len(views_p), dtype=torch.bool)])
    idx = torch.nonzero(free).squeeze(1)
    scores, offset = [], 0
    for k, (vp, dv) in enumerate(zip(views_p, data)):
        n = dv.uv.shape[0]
        with torch.no_grad():
            jg, jv = jac(glob, vp, dv)
        J = torch.zeros(n, n_par, dtype=torch.float64)
        J[:, :n_g] = jg * free_g.to(jg.dtype)
        J[:, n_g + n_v * k: n_g + n_v * (k + 1)] = jv
        psi = (wts[offset:offset + n] * r[offset:offset + n])[:, None] * J      # (n, n_par) per-pixel scores
        offset += n
        side = max(8.0, _view_blur_px(glob, vp, sensor, target))
        tile = torch.floor(dv.uv / side).to(torch.int64)
        key = tile[:, 0] * 100003 + tile[:, 1]
        _, cluster = torch.unique(key, return_inverse=True)
        g = torch.zeros(int(cluster.max()) + 1, n_par, dtype=torch.float64).index_add_(0, cluster, psi)
        scores.append(g)
    G = torch.cat(scores)
    C = G.shape[0]
    B = G.T @ G * (C / max(C - 1, 1))
    cov = torch.full((n_par, n_par), float("nan"), dtype=torch.float64)
    try:
        A_inv = torch.linalg.inv(JTJ[idx[:, None], idx[None, :]])
    except RuntimeError:
        return cov
    cov.zero_()
    cov[idx[:, None], idx[None, :]] = A_inv @ B[idx[:, None], idx[None, :]] @ A_inv
    return cov


def _sigma_dict(glob, cov, n_g) -> dict:
    """One-σ of the global parameters (and U, θL by the chain rule) from a covariance of the flat vector."""
    sd = torch.sqrt(torch.diagonal(cov).clamp_min(0))
    U = 1000.0 / float(glob[1])
    # θL's σ by the chain rule through tan θL = w tan θF / (U + w).
    gL = torch.func.jacrev(lambda g: theta_L_from_theta_F(g[3], g[0], 1000.0 / g[1]))(glob)
    var_L = float(gL @ cov[:n_g, :n_g] @ gL)
    return {"w_mm": float(sd[0]), "inv_U_per_m": float(sd[1]), "U_mm": float(sd[1]) * U * U / 1000.0,
            "d_mm": float(sd[2]), "theta_F_deg": math.degrees(float(sd[3])),
            "theta_L_deg": math.degrees(math.sqrt(max(var_L, 0.0))) if math.isfinite(var_L) else float("nan"),
            "vignetting": float(sd[4]), "psf_sigma_px": float(sd[5])}


def _photometric_result(glob, views_p, r, scale, JTJ, free_g, data, n_g, n_v, n_par, it, t0, history, kernel,
                        selection, cov_sandwich) -> PhotometricResult:
    """The result: values, σ from the cluster-robust sandwich (and the textbook Gauss–Newton σ beside it),
    per-view poses."""
    n_views = len(views_p)
    # The textbook covariance (Gauss–Newton, robust σ of the residuals), kept for comparison.
    free = torch.cat([free_g, torch.ones(n_v * n_views, dtype=torch.bool)])
    idx = torch.nonzero(free).squeeze(1)
    cov = torch.zeros(n_par, n_par, dtype=torch.float64)
    try:
        cov_free = torch.linalg.inv(JTJ[idx[:, None], idx[None, :]]) * scale**2
        cov[idx[:, None], idx[None, :]] = cov_free
    except RuntimeError:
        cov = torch.full((n_par, n_par), float("nan"), dtype=torch.float64)
    lens = _lens_values(glob)
    vig, psf = float(glob[4]), float(glob[5])
    invU = float(glob[1])
    values = {**lens, "inv_U_per_m": invU, "vignetting": vig, "psf_sigma_px": abs(psf), "kernel": kernel}
    sigma = _sigma_dict(glob, cov_sandwich, n_g)
    sigma_gn = _sigma_dict(glob, cov, n_g)
    views, offset = [], 0
    for k, (vp, dv) in enumerate(zip(views_p, data)):
        n = dv.uv.shape[0]
        rk = r[offset:offset + n]
        offset += n
        views.append({"R": axis_angle_to_matrix(vp[0:3]).numpy(), "T_mm": vp[3:6].numpy().copy(), "white": float(vp[6]),
                      "black": float(vp[7]), "rms": float(torch.sqrt((rk * rk).mean())), "n_pixels": n})
    rms = float(torch.sqrt((r * r).mean()))
    return PhotometricResult(values, sigma, views, rms, it, time.perf_counter() - t0, history, selection, sigma_gn)
