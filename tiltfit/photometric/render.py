"""The target renderer of the photometric fit: what a pixel of a thin-lens camera sees of the checkerboard.

Every function takes the renderer's thin-lens camera of one view (`renderer.ThinLensCamera`, as
`LensCamera.view_camera(v)` builds it, tensor parameters with gradients) and returns the dark fraction D(u) ∈
[0, 1] of the board a pixel u sees: the mean, over the pixel's area and the lens's aperture, of the checker's
darkness (1 dark cell, 0 white cell or margin). No general tracer and no random numbers, so D is smooth and
deterministic and its derivatives exact. The photograph's intensity is then the exposure's affine map of D
(`render_target`; `options.Exposure`):

    I(u) = (1 − v ρ(u)²) · (white − (white − black) · D(u))

with v the vignetting and ρ the distance from the image centre, 1 at the corners (`renderer.cameras.sensor.radial_falloff`,
the one sensor model `tiltfit.experiments.synth` and `tiltfit.experiments.reproduce` expose their captures with).

D is integrated over the aperture in one of two ways:
- in closed form (`dark_fraction_disc`): each of n x n points of the pixel (a grid with the box's variance,
  `sub_points`; n = 4, or SUBPIXELS_SHARP below SHARP_BLUR_PX of blur: `closed_form_subpixels`) sees the
  aperture disc through its focus point (`ThinLensCamera.focus_geometry`), on which the board's cell edges are
  straight lines, so D is a sum of disc segments and wedges (`tiltfit.photometric.aperture`). Exact over the aperture for
  the thin lens at any tilt and blur; the pixel's box is the n x n points' quadrature, whose error grows as the
  blur disc shrinks. The fit uses it for every pixel with the disc kernel (`options.CLOSED_FORM_MIN_BLUR_PX`);
- by fixed lens samples (`dark_fraction_samples`): rays for each pixel and sample, intersected with the board
  plane Z = 0, the checker evaluated analytically and antialiased over the pixel's footprint (below). The
  Gaussian kernels need it (the disc convolved with a Gaussian has no closed form here).

Antialiased checker: for a hit (X, Y) on the board with pixel footprint σ (mm), per axis the nearest cell edge
e_j and z = (X − e_j)/σ give A = E[inside] and B = E[inside · s] (s = ±1 the column's parity sign) under a
Gaussian of standard deviation σ; the dark fraction is D = ½ (A_x A_y + p B_x B_y) with p the parity of
`dark_cell`. σ along X and along Y match the variance of the pixel's box footprint on the board (from the
local Jacobian of the chief-ray map), so the pixel's area adds the blur a box filter adds. The lens samples
are a fixed Hammersley set whitened to the disc's second moment (`hammersley_disc_samples`), traced from 2 x 2
sub-pixels. Their number must grow with the blur disc's area (`auto_lens_samples`; at 18 px, 64 samples gave
θL +0.015° and d −0.3 % on average, 192 no bias beyond σ: docs/photometric.md).
"""
from __future__ import annotations

import math

import numpy as np
import torch

from renderer.cameras import ThinLensCamera, concentric_disk, image_centre_px
from renderer.cameras.optics import blur_diameter_first_order, blur_diameter_paper
from renderer.cameras.sensor import radial_falloff

from tiltfit.photometric.aperture import checker_dark_fraction_disc, disc_within
from tiltfit.target.layout import Target

#: Sensor points per pixel side of the closed-form aperture (`dark_fraction_disc`).
SUBPIXELS = 4
#: ... for pixels whose blur disc is narrower than SHARP_BLUR_PX (`closed_form_subpixels`). The n x n points'
#: quadrature of the pixel's box errs by about the same for the same n · blur: against a 40 x 40 grid, the d a
#: fit would take from it is −0.40 % (4 x 4) and −0.06 % (8 x 8) at a 1.5 px disc on a facing board, −0.20 % and
#: −0.02 % at 2 px, +0.02 % and +0.006 % at 3 px (benchmarks/results/photometric_forward_extras.md,
#: "pixel quadrature").
SUBPIXELS_SHARP = 8
SHARP_BLUR_PX = 3.0
#: `lens_samples=0` (auto) takes 64 · (b / 10 px)² samples for the start's largest blur disc b at the board's
#: centre, in multiples of 16, from 64 to this many (`auto_lens_samples`).
AUTO_LENS_SAMPLES_MAX = 256
#: Pixels `usable_mask` takes at once (bounds its memory; 684×456 images stay one chunk).
MASK_CHUNK_PIXELS = 1 << 19


def _inverse_concentric(xy: np.ndarray) -> np.ndarray:
    """Points on the unit disc (..., 2) -> the [0, 1)² samples that `concentric_disk` maps to them."""
    x, y = xy[..., 0], xy[..., 1]
    r = np.hypot(x, y)
    phi = np.mod(np.arctan2(y, x) + np.pi / 4, 2 * np.pi) - np.pi / 4   # in [−π/4, 7π/4)
    a, b = np.empty_like(r), np.empty_like(r)
    s0, s1, s2, s3 = ((phi < np.pi / 4), (phi >= np.pi / 4) & (phi < 3 * np.pi / 4),
                      (phi >= 3 * np.pi / 4) & (phi < 5 * np.pi / 4), phi >= 5 * np.pi / 4)
    a[s0], b[s0] = r[s0], r[s0] * phi[s0] * 4 / np.pi
    b[s1], a[s1] = r[s1], r[s1] * (np.pi / 2 - phi[s1]) * 4 / np.pi
    a[s2], b[s2] = -r[s2], -r[s2] * (phi[s2] - np.pi) * 4 / np.pi
    b[s3], a[s3] = -r[s3], -r[s3] * (np.pi / 2 - (phi[s3] - np.pi)) * 4 / np.pi
    return np.stack([(a + 1) / 2, (b + 1) / 2], -1)


def auto_lens_samples(blur_px: float, minimum: int = 64) -> int:
    """Fixed lens samples for a blur disc of `blur_px` px: 64 · (b / 10 px)², so the samples' spacing on the
    image stays about 1.1 px, in multiples of 16, between `minimum` and AUTO_LENS_SAMPLES_MAX."""
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


def closed_form_subpixels(blur_px: float) -> int:
    """Points per pixel side the closed form takes for a pixel whose blur disc is `blur_px` wide: SUBPIXELS, or
    SUBPIXELS_SHARP below SHARP_BLUR_PX."""
    return SUBPIXELS_SHARP if float(blur_px) < SHARP_BLUR_PX else SUBPIXELS


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


def on_board(rays) -> torch.Tensor:
    """(..., 3) points where rays meet the board plane Z = 0 (target frame)."""
    t = -rays.origin[..., 2] / rays.direction[..., 2]
    return rays.origin + t[..., None] * rays.direction


def sub_points(uv_px: torch.Tensor, subpixels: int = SUBPIXELS) -> torch.Tensor:
    """(N, subpixels², 2) points of each pixel of `uv_px` (N, 2): an n x n grid whose spread matches the box
    pixel's.

    The midpoint rule's points ((i + ½)/n − ½) have variance (1 − 1/n²)/12 per axis, less than the box's 1/12:
    the model's edges came out sharper than the pixel makes them, and a fit widened the disc to make up for it
    (against exact tracing, d +0.76 % at a 2 px blur disc and +7 % at 0.7 px with n = 4;
    benchmarks/results/photometric_forward.md). The grid is therefore stretched by √(n² / (n² − 1)), which
    restores the variance (d +0.14 % and −0.4 % there)."""
    n = int(subpixels)
    stretch = math.sqrt(n * n / (n * n - 1.0)) if n > 1 else 1.0
    step = ((torch.arange(n, dtype=uv_px.dtype, device=uv_px.device) + 0.5) / n - 0.5) * stretch
    sub = torch.stack(torch.meshgrid(step, step, indexing="xy"), -1).reshape(-1, 2)
    return uv_px[:, None, :] + sub


#: Sensor points of a pixel the lens samples are traced from, about its centre (px): the 2 x 2 sub-pixel centres.
SAMPLE_SUBPIXELS = ((-0.25, -0.25), (0.25, -0.25), (-0.25, 0.25), (0.25, 0.25))
#: ... and the chief rays of the pixel and of its right and lower neighbours (the footprint's Jacobian).
FOOTPRINT_STEPS = ((0.0, 0.0), (1.0, 0.0), (0.0, 1.0))


def sample_points(uv_px: torch.Tensor) -> torch.Tensor:
    """(N, 7, 2) the sensor points `dark_fraction_samples` needs of each pixel of `uv_px` (N, 2): the 2 x 2
    sub-pixel centres (SAMPLE_SUBPIXELS), then the pixel and its right and lower neighbours (FOOTPRINT_STEPS)."""
    offsets = torch.tensor(SAMPLE_SUBPIXELS + FOOTPRINT_STEPS, dtype=uv_px.dtype, device=uv_px.device)
    return uv_px[:, None, :] + offsets


def _board_hit(q_h: torch.Tensor, lx, ly, lz):
    """(X, Y) where the rays from lens points (lx, ly, lz) through the focus points q_h (homogeneous (x, y, z, s),
    target frame) meet the board plane Z = 0: the central projection X_k = (L_z q_k − q_z L_k) / (L_z s − q_z)
    (`tiltfit.photometric.aperture`'s line equation, solved for the point). Shapes broadcast."""
    qx, qy, qz, s = q_h.unbind(-1)
    den = lz * s - qz
    return (lz * qx - qz * lx) / den, (lz * qy - qz * ly) / den


def dark_fraction_lens_samples(target: Target, q_h: torch.Tensor, centre: torch.Tensor, axes: torch.Tensor,
                               lens_xy: torch.Tensor, psf_var_px2=0.0) -> torch.Tensor:
    """(N,) dark fraction of pixels averaged over fixed points of the lens's disc, from each pixel's focus
    geometry (no rays traced: each sample's ray is the line from its lens point through the sub-pixel's focus
    point, met with the board plane in closed form).

    Args:
        q_h: (N, 7, 4) homogeneous focus points of `sample_points` (`ThinLensCamera.focus_geometry`), target frame.
        centre: (3,) or (N, 3) the lens centre; axes: (2, 3) or (N, 2, 3) the aperture's half-diameter vectors
            (one copy per pixel where the fit differentiates each pixel with respect to its own).
        lens_xy: (S, 2) points of the unit disc (`concentric_disk` of the lens samples).
        psf_var_px2: variance (px²) of a Gaussian convolved with the disc, a number or (N,).
    Returns:
        (N,) the mean over the 2 x 2 sub-pixels and S lens points of the antialiased checker (module docstring).
    """
    if centre.dim() == 1:
        centre, axes = centre.expand(q_h.shape[0], 3), axes.expand(q_h.shape[0], 2, 3)
    a, b = lens_xy[:, 0], lens_xy[:, 1]
    # Lens points (N, 1, S) per component, L = C + a A₁ + b A₂.
    lens = [(centre[:, k, None] + axes[:, 0, k, None] * a + axes[:, 1, k, None] * b)[:, None, :] for k in range(3)]
    X, Y = _board_hit(q_h[:, :4, None, :], *lens)                        # (N, 4, S)
    cx, cy = _board_hit(q_h[:, 4:], *(centre[:, k, None] for k in range(3)))   # chief rays (N, 3)
    # The pixel's area (as the sub-pixels' Gaussian footprints, see `dark_fraction_samples`).
    jx, jy = cx[:, 1:] - cx[:, :1], cy[:, 1:] - cy[:, :1]               # (N, 2 (du, dv))
    var = torch.as_tensor(psf_var_px2, dtype=q_h.dtype, device=q_h.device)
    sigma_x = torch.sqrt((jx * jx).sum(1) * (1.0 / 48.0 + var))
    sigma_y = torch.sqrt((jy * jy).sum(1) * (1.0 / 48.0 + var))
    n = q_h.shape[0]
    return checker_dark_fraction(X.reshape(n, -1), Y.reshape(n, -1), sigma_x[:, None], target,
                                 sigma_y=sigma_y[:, None]).mean(-1)


def dark_fraction_samples(target: Target, cam: ThinLensCamera, uv_px: torch.Tensor, lens_uv: torch.Tensor,
                          psf_var_px2=0.0) -> torch.Tensor:
    """(N,) dark fraction of pixels `uv_px` (N, 2), averaged over the fixed lens samples `lens_uv` (S, 2) in
    [0, 1)² (their points on the aperture should have the disc's moments, as `hammersley_disc_samples`'s do, or
    d comes out scaled). `psf_var_px2`: variance (px²) of a Gaussian convolved with the lens's disc [0]; it
    widens each sub-pixel's Gaussian footprint on the board.

    The pixel's area: every lens sample is traced from each of the 2 x 2 sub-pixel centres, and each sub-pixel's
    remaining box (half a pixel wide) is a Gaussian footprint on the board of the same variance, per board axis,
    from the chief rays of the pixel and of its right and lower neighbours (J = d(X, Y)/d(u, v)):
    (J_u² + J_v²) / (4 · 12). A single Gaussian for the whole pixel misses the box's shape, which matters where
    the blur is a pixel or two (it biased θF by 0.1° on sharp boards). The rays are the thin lens's
    (`ThinLensCamera.generate_rays`: from the sample's lens point through the sensor point's focus point), met
    with the board in closed form from the 7 points' focus geometry (`dark_fraction_lens_samples`), so the
    distortion is inverted 7 times a pixel, not 4 S times."""
    q_h, centre, axes, _ = cam.focus_geometry(sample_points(uv_px))
    return dark_fraction_lens_samples(target, q_h, centre, axes, concentric_disk(lens_uv.to(q_h)), psf_var_px2)


def dark_fraction_disc(target: Target, cam: ThinLensCamera, uv_px: torch.Tensor, near: int,
                       subpixels: int = SUBPIXELS) -> torch.Tensor:
    """(N,) dark fraction of pixels `uv_px` with the aperture integrated in closed form (`tiltfit.photometric.aperture`).

    Each pixel is the mean of a `subpixels` x `subpixels` grid of sensor points (`sub_points`: the box pixel's
    variance, exact for the mean and spread of an edge's profile); each point's dark fraction is exact over the disc.
    `near`: lines per family given the two-line term (`tiltfit.photometric.aperture.lines_cut` counts them)."""
    q_h, centre, axes, _ = cam.focus_geometry(sub_points(uv_px, subpixels))
    return checker_dark_fraction_disc(q_h, centre, axes, target, near).mean(-1)


def shade(dark: torch.Tensor, uv_px: torch.Tensor, image_size_px, white, black, vignetting) -> torch.Tensor:
    """The exposure of a dark fraction: (1 − v ρ²) · (white − (white − black) · D) (module docstring)."""
    falloff = radial_falloff(uv_px[:, 0], uv_px[:, 1], image_size_px[0], image_size_px[1], vignetting)
    return falloff * (white - (white - black) * dark)


def render_target(target: Target, cam: ThinLensCamera, uv_px: torch.Tensor, lens_uv: torch.Tensor, white, black,
                  vignetting, psf_var_px2=0.0) -> torch.Tensor:
    """(N,) linear intensities of pixels `uv_px` by the fixed lens samples (`dark_fraction_samples`, `shade`)."""
    return shade(dark_fraction_samples(target, cam, uv_px, lens_uv, psf_var_px2), uv_px,
                 (cam.width, cam.height), white, black, vignetting)


def render_target_disc(target: Target, cam: ThinLensCamera, uv_px: torch.Tensor, near: int, white, black,
                       vignetting, subpixels: int = SUBPIXELS) -> torch.Tensor:
    """(N,) linear intensities of pixels `uv_px` with the aperture in closed form (`dark_fraction_disc`)."""
    return shade(dark_fraction_disc(target, cam, uv_px, near, subpixels), uv_px, (cam.width, cam.height),
                 white, black, vignetting)


def predicted_dark_fraction(target: Target, cam: ThinLensCamera, uv_px: torch.Tensor) -> torch.Tensor:
    """(N,) a cheap prediction of the dark fraction, for choosing pixels: the aperture in closed form from 2 x 2
    points of each pixel (every line a disc cuts gets its exact term)."""
    with torch.no_grad():
        return dark_fraction_disc(target, cam, uv_px, max(len(target.x_edges), len(target.y_edges)), subpixels=2)


def pixel_blur_px(cam: ThinLensCamera, uv: torch.Tensor) -> torch.Tensor:
    """(N,) blur-disc diameter (px) of each pixel at the board point its chief ray meets: w d |1/z_f − 1/z| with
    z_f where that ray meets the plane of focus (`optics.blur_diameter_first_order`)."""
    with torch.no_grad():
        lens = cam.lens
        p_cam = lens.to_tilt_frame(cam.transform.points_to_camera(on_board(cam.generate_rays(uv))))
        return blur_diameter_first_order(p_cam, lens.w, lens.U, lens.d, lens.theta_F) / cam.screen.pitch[0]


def board_blur_px(cam: ThinLensCamera, target: Target) -> float:
    """Blur-disc diameter (px) at the board's centre, paper (4) (`optics.blur_diameter_paper`)."""
    x0, y0, x1, y1 = target.extent_mm
    with torch.no_grad():
        lens = cam.lens
        p = cam.transform.points_to_camera(torch.tensor([(x0 + x1) / 2, (y0 + y1) / 2, 0.0], dtype=torch.float64))
        p = lens.to_tilt_frame(p)
        return float(blur_diameter_paper(p[1], p[2], float(lens.w), float(lens.U), float(lens.d),
                                         float(lens.theta_F))) / float(cam.screen.pitch[0])


def usable_pixels(target: Target, cam: ThinLensCamera, uv_px: torch.Tensor, t_max: float | None = None) -> np.ndarray:
    """(N,) bool: pixels `uv_px` (N, 2) whose whole blur disc lands on the board, margin included, at least two
    pixels' footprint (at the chief ray's length `t_max`, by default the longest of these pixels') inside its
    outer edge: exact for the thin lens's disc (`aperture.disc_within`), one focus point per pixel, in chunks of
    MASK_CHUNK_PIXELS pixels. Whatever lies beyond the margin (background, the board's edge) is never fitted.

    `t_max` by default comes from the pixels whose chief ray meets the board's plane in front of the camera and
    within one board size of its outline: a pixel of the board's box whose ray grazes the plane (on a real GoPro
    view one met it 742 m away) would widen the guard past the whole board and leave no pixel usable."""
    x0, y0, x1, y1 = target.extent_mm
    bx, by = x1 - x0, y1 - y0
    chunks = range(0, uv_px.shape[0], MASK_CHUNK_PIXELS)
    with torch.no_grad():
        t_chief, t_near = [], []
        for a in chunks:
            rays = cam.generate_rays(uv_px[a:a + MASK_CHUNK_PIXELS])
            t = -rays.origin[..., 2] / rays.direction[..., 2]
            hit = rays.origin + t[..., None] * rays.direction
            near = (t > 0) & (hit[..., 0] >= x0 - bx) & (hit[..., 0] <= x1 + bx) & (hit[..., 1] >= y0 - by) & \
                (hit[..., 1] <= y1 + by)
            t_chief.append(t)
            t_near.append(t[near])
        if t_max is None:
            t_near = torch.cat(t_near) if t_near else torch.zeros(0)
            t_max = float(t_near.max()) if t_near.numel() else 1.0   # none near the board: none usable anyway
        guard = 2.0 * float(cam.screen.pitch[0]) * t_max / float(cam.lens.w)
        ok = np.empty(uv_px.shape[0], dtype=bool)
        for a, t in zip(chunks, t_chief):
            q_h, centre, axes, valid = cam.focus_geometry(uv_px[a:a + MASK_CHUNK_PIXELS])
            inside = disc_within(q_h, centre, axes, (x0 + guard, x1 - guard), (y0 + guard, y1 - guard))
            ok[a:a + t.shape[0]] = (inside & valid & (t > 0)).numpy()
    return ok


def usable_mask(target: Target, cam: ThinLensCamera) -> np.ndarray:
    """(H, W) `usable_pixels` of the whole image."""
    W, H = cam.width, cam.height
    flat = torch.arange(H * W)
    uv = torch.stack([(flat % W).to(torch.float64), (flat // W).to(torch.float64)], -1)
    return usable_pixels(target, cam, uv).reshape(H, W)


def board_box(target: Target, cam: ThinLensCamera, pad_px: float = 2.0) -> tuple[int, int, int, int] | None:
    """(x0, y0, x1, y1) inclusive pixel bounds of the board (margin included) on the image, by the chief rays
    of 64 points along each side of its outline (distortion included), widened by `pad_px` and the blur disc at
    the board's centre; None where no part of it is in front of the camera and on the image."""
    ex0, ey0, ex1, ey1 = target.extent_mm
    s = torch.linspace(0.0, 1.0, 64, dtype=torch.float64)
    X = torch.cat([ex0 + (ex1 - ex0) * s, torch.full_like(s, ex1), ex1 - (ex1 - ex0) * s, torch.full_like(s, ex0)])
    Y = torch.cat([torch.full_like(s, ey0), ey0 + (ey1 - ey0) * s, torch.full_like(s, ey1), ey1 - (ey1 - ey0) * s])
    with torch.no_grad():
        pts = torch.stack([X, Y, torch.zeros_like(X)], -1)
        in_front = cam.transform.points_to_camera(pts)[:, 2] > 0
        uv = cam.project(pts)
    ok = in_front & torch.isfinite(uv).all(-1)
    if not bool(ok.any()):
        return None
    uv = uv[ok]
    pad = pad_px + board_blur_px(cam, target)
    W, H = cam.width, cam.height
    x0, y0 = max(0, int(math.floor(float(uv[:, 0].min()) - pad))), max(0, int(math.floor(float(uv[:, 1].min()) - pad)))
    x1 = min(W - 1, int(math.ceil(float(uv[:, 0].max()) + pad)))
    y1 = min(H - 1, int(math.ceil(float(uv[:, 1].max()) + pad)))
    return None if x1 < x0 or y1 < y0 else (x0, y0, x1, y1)


def dark_fraction_image(target: Target, cam: ThinLensCamera, subpixels: int = 2, stride: int = 1,
                        chunk: int = 1 << 15) -> np.ndarray:
    """(H, W) dark fraction D of one view's pixels (`dark_fraction_disc`), NaN outside the pixels the fit may use
    (`usable_pixels` of the board's box) and off the grid of every `stride`-th column and row (x and y multiples
    of `stride`: `image[::stride, ::stride]` is the evaluated grid). Each evaluated pixel is the full-resolution
    pixel, so a stride thins the picture without changing the model.

    Args:
        cam: the view's camera (`LensCamera.view_camera(v)`, or `tiltfit.files.calibrated.Calibration.camera(v)`).
        subpixels: points per pixel side of the closed-form aperture [2: a picture, not a fit].
    """
    W, H = cam.width, cam.height
    out = np.full((H, W), np.nan)
    box = board_box(target, cam)
    if box is None:
        return out
    x0, y0, x1, y1 = box
    k = max(int(stride), 1)
    ys, xs = np.mgrid[-(-y0 // k) * k:y1 + 1:k, -(-x0 // k) * k:x1 + 1:k]
    uv = torch.tensor(np.stack([xs.ravel(), ys.ravel()], -1), dtype=torch.float64)
    if not uv.shape[0]:
        return out
    uv = uv[torch.from_numpy(usable_pixels(target, cam, uv))]
    near = max(len(target.x_edges), len(target.y_edges))
    with torch.no_grad():
        for a in range(0, uv.shape[0], chunk):
            u = uv[a:a + chunk]
            out[u[:, 1].long().numpy(), u[:, 0].long().numpy()] = dark_fraction_disc(target, cam, u, near,
                                                                                      subpixels).numpy()
    return out


def shade_image(dark: np.ndarray, white: float, black: float, vignetting: float = 0.0, gain=(0.0, 0.0)) -> np.ndarray:
    """(H, W) linear intensity the exposure makes of a dark-fraction image (`dark_fraction_image`; NaN stays NaN):
    `shade`'s vignetting and levels times the view's illumination gradient 1 + g_x x + g_y y (x, y about the image
    centre, ±1 at the edges; `options.Exposure`)."""
    H, W = dark.shape
    ys, xs = np.mgrid[0:H, 0:W]
    uv = torch.tensor(np.stack([xs.ravel(), ys.ravel()], -1), dtype=torch.float64)
    hx, hy = image_centre_px(W, H)
    with torch.no_grad():
        pred = shade(torch.from_numpy(np.ascontiguousarray(dark, dtype=np.float64).ravel()), uv, (W, H), white, black,
                     vignetting)
        pred = pred * (1.0 + gain[0] * (uv[:, 0] - hx) / hx + gain[1] * (uv[:, 1] - hy) / hy)
    return pred.numpy().reshape(H, W)


def residual_image(image: np.ndarray, target: Target, cam: ThinLensCamera, white: float, black: float,
                   vignetting: float = 0.0, gain=(0.0, 0.0), subpixels: int = 2,
                   chunk: int = 1 << 15, stride: int = 1) -> np.ndarray:
    """(H, W) photo − rendered board of one view (linear units), NaN outside the pixels the fit may use
    (`usable_pixels` of the board's box; with `stride`, off its grid: `dark_fraction_image`): what the refinement
    could not explain, for `tiltfit.report.photometric.plot_residual_image`.

    Args:
        image: (H, W) linear photo of the view (decode sRGB first).
        cam: the view's camera (`LensCamera.view_camera(v)` of the calibration).
        white, black, vignetting, gain: the view's exposure (CALIB.json's photometric `levels` and `vignetting`;
            gain (g_x, g_y) the illumination gradient, `render.shade` and `options.Exposure`).
        subpixels: points per pixel side of the closed-form aperture [2: a picture, not a fit].
    """
    dark = dark_fraction_image(target, cam, subpixels, stride, chunk)
    return np.asarray(image, dtype=np.float64) - shade_image(dark, white, black, vignetting, gain)
