"""Calibration model: observations, residuals and losses for the one camera model, plus synthetic observations.

The camera is the renderer's `LensCamera` (renderer/cameras/lens_model.py; its docstring gives the projection,
the blur models and the parametrisation), under that one name here too. The names this module
re-exports (BLUR_MODELS, APERTURE_SCALE_MM, blur_diameter_mm, axis_angle_to_matrix, matrix_to_axis_angle,
distortion_parameter_names) are the renderer's too. Lengths in mm, angles in radians.

    project(X_world, view) -> uv_px    uv = c + (w / p) · D(x / z, y / z),  (x, y, z) = R X + T
    blur(X_world, view)    -> b_px     blur-disc diameter b = w d |1/z_F − 1/z| / p     (eqs 2 and 4)
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from renderer import Lens, axis_angle_to_matrix, matrix_to_axis_angle  # noqa: F401  (re-exported)
from renderer.cameras import APERTURE_SCALE_MM, LensCamera, distortion_parameter_names  # noqa: F401  (re-exported)
from renderer.cameras.optics import BLUR_MODELS  # noqa: F401  (re-exported)
from renderer.cameras.optics import blur_diameter as blur_diameter_mm  # noqa: F401  (re-exported)

from tiltfit.files.det import MIN_CORNERS  # noqa: F401 - the fewest corners a view must have (owned there: no torch)

ROBUST_LOSSES = (None, "none", "huber", "cauchy")


# ---------------------------------------------------------------------------------------------------------
# Observations
# ---------------------------------------------------------------------------------------------------------

@dataclass
class Observations:
    """Detected feature points and blur widths of one target seen in several views.

    Attributes:
        points_mm: (N, 3) target feature points in the world (target) frame, mm.
        corners_px: (V, N, 2) detected image positions, pixels; NaN where not detected.
        blur_px: (V, N) detected blur-disc diameters, pixels; NaN where not measured.
        image_size_px: (W, H).
        pixel_pitch_mm: sensor pixel pitch, mm.
        names: optional per-view labels (image files).
    """

    points_mm: torch.Tensor
    corners_px: torch.Tensor
    blur_px: torch.Tensor
    image_size_px: tuple[int, int]
    pixel_pitch_mm: float
    names: list[str] | None = None

    def __post_init__(self):
        self.points_mm = torch.as_tensor(self.points_mm, dtype=torch.float64)
        self.corners_px = torch.as_tensor(self.corners_px, dtype=torch.float64)
        self.blur_px = torch.as_tensor(self.blur_px, dtype=torch.float64)
        N = self.points_mm.shape[0]
        if self.points_mm.shape != (N, 3):
            raise ValueError(f"points_mm: expected shape (N, 3), got {tuple(self.points_mm.shape)}")
        V = self.corners_px.shape[0] if self.corners_px.ndim == 3 else -1
        if self.corners_px.shape != (V, N, 2):
            raise ValueError(f"corners_px: expected shape (V, {N}, 2), got {tuple(self.corners_px.shape)}")
        if self.blur_px.shape != (V, N):
            raise ValueError(f"blur_px: expected shape ({V}, {N}), got {tuple(self.blur_px.shape)}")
        self.image_size_px = (int(self.image_size_px[0]), int(self.image_size_px[1]))
        self.pixel_pitch_mm = float(self.pixel_pitch_mm)
        if self.names is None:
            self.names = [f"view{v}" for v in range(V)]
        if len(self.names) != V:
            raise ValueError(f"names: expected {V} names, got {len(self.names)}")

    @property
    def n_views(self) -> int:
        return self.corners_px.shape[0]

    @property
    def corner_mask(self) -> torch.Tensor:
        """(V, N) bool: where a corner was detected."""
        return torch.isfinite(self.corners_px).all(-1)

    @property
    def blur_mask(self) -> torch.Tensor:
        """(V, N) bool: where a blur width was measured."""
        return torch.isfinite(self.blur_px)

    def subset(self, views) -> "Observations":
        """The observations of the listed views only."""
        idx = list(views)
        return Observations(self.points_mm, self.corners_px[idx], self.blur_px[idx], self.image_size_px,
                            self.pixel_pitch_mm, [self.names[i] for i in idx])


# ---------------------------------------------------------------------------------------------------------
# Residuals and loss
# ---------------------------------------------------------------------------------------------------------

@dataclass
class Residuals:
    """Model minus observation, zero where nothing was observed.

    Attributes:
        corners_px: (V, N, 2) reprojection residuals, pixels.
        blur_px: (V, N) blur residuals, pixels.
        corner_mask, blur_mask: (V, N) bool, where an observation exists.
    """

    corners_px: torch.Tensor
    blur_px: torch.Tensor
    corner_mask: torch.Tensor
    blur_mask: torch.Tensor

    def rms_per_view(self) -> tuple[torch.Tensor, torch.Tensor]:
        """((V,) reprojection RMS per corner, (V,) blur RMS), pixels; NaN for empty views.

        The reprojection RMS is OpenCV's (`cv2.calibrateCamera`'s return value): sqrt(mean over corners of
        dx² + dy²), √2 times the RMS per coordinate."""
        nc = self.corner_mask.sum(-1)
        nb = self.blur_mask.sum(-1)
        rc = torch.sqrt((self.corners_px ** 2).sum((-1, -2)) / nc)
        rb = torch.sqrt((self.blur_px ** 2).sum(-1) / nb)
        return rc, rb


def residuals(camera: LensCamera, obs: Observations) -> Residuals:
    """Residuals of the model against the observations (model − observed), all views at once (the blur widths'
    not modelled where none was measured: their residuals are 0 then)."""
    bm = obs.blur_mask
    uv, b = camera(obs.points_mm, with_blur=bool(bm.any()))
    cm, bm = obs.corner_mask.to(uv.device), bm.to(uv.device)
    rc = torch.where(cm[..., None], uv - torch.nan_to_num(obs.corners_px.to(uv)), torch.zeros_like(uv))
    rb = torch.where(bm, b - torch.nan_to_num(obs.blur_px.to(b)), torch.zeros_like(b))
    return Residuals(rc, rb, cm, bm)


def robust_rho(s2: torch.Tensor, robust: str | None = None, scale: float = 3.0) -> torch.Tensor:
    """Robust cost ρ of squared normalised residuals s² (ρ(s²) = s² when robust is None).

    huber: s² inside |s| ≤ k, 2k|s| − k² outside;  cauchy: k² log(1 + s²/k²);  k = scale.
    """
    if robust in (None, "none"):
        return s2
    k2 = scale * scale
    if robust == "huber":
        inside = s2 <= k2
        s_safe = torch.sqrt(torch.where(inside, torch.full_like(s2, k2), s2))
        return torch.where(inside, s2, 2.0 * scale * s_safe - k2)
    if robust == "cauchy":
        return k2 * torch.log1p(s2 / k2)
    raise ValueError(f"robust: expected one of {ROBUST_LOSSES}, got {robust!r}")


def robust_weight(s2: torch.Tensor, robust: str | None = None, scale: float = 3.0) -> torch.Tensor:
    """dρ/d(s²): the IRLS weight of each residual (1 without a robust loss)."""
    if robust in (None, "none"):
        return torch.ones_like(s2)
    k2 = scale * scale
    if robust == "huber":
        return torch.where(s2 <= k2, torch.ones_like(s2), scale / torch.sqrt(torch.clamp(s2, min=k2)))
    if robust == "cauchy":
        return 1.0 / (1.0 + s2 / k2)
    raise ValueError(f"robust: expected one of {ROBUST_LOSSES}, got {robust!r}")


def normalized_residual_vector(camera: LensCamera, obs: Observations, sigma_corner_px: float = 1.0,
                               sigma_blur_px: float = 1.0, use_corners: bool = True,
                               use_blur: bool = True) -> torch.Tensor:
    """Flat residual vector (V·N·2 corner entries, then V·N blur entries), each divided by its σ.

    Unobserved entries (and switched-off groups) are zero, so the length is fixed by (V, N).
    """
    r = residuals(camera, obs)
    rc = r.corners_px.reshape(-1) / sigma_corner_px
    rb = r.blur_px.reshape(-1) / sigma_blur_px
    if not use_corners:
        rc = torch.zeros_like(rc)
    if not use_blur:
        rb = torch.zeros_like(rb)
    return torch.cat([rc, rb])


def loss(camera: LensCamera, obs: Observations, sigma_corner_px: float = 1.0, sigma_blur_px: float = 1.0,
         robust: str | None = None, robust_scale: float = 3.0, use_corners: bool = True,
         use_blur: bool = True) -> torch.Tensor:
    """Scalar ½ Σ ρ((r / σ)²) over corners and blur: minimise it with any torch optimizer."""
    r = normalized_residual_vector(camera, obs, sigma_corner_px, sigma_blur_px, use_corners, use_blur)
    return 0.5 * robust_rho(r * r, robust, robust_scale).sum()


# ---------------------------------------------------------------------------------------------------------
# Synthetic observations
# ---------------------------------------------------------------------------------------------------------

def synthesize_observations(camera: LensCamera, points_mm, noise_px: float = 0.0, noise_blur_px: float = 0.0,
                            seed: int = 0, noise_blur_rel: float = 0.0, names=None,
                            margin_px: float = 0.0) -> Observations:
    """Noisy observations of target points seen by `camera` in each of its views.

    Corners get isotropic Gaussian noise of `noise_px` per coordinate; blur widths get Gaussian noise of
    standard deviation sqrt(noise_blur_px² + (noise_blur_rel · b)²) and are clipped at 0. Points behind the
    camera or outside the image (less `margin_px`) are marked unobserved (NaN).

    Args:
        camera: the true camera (its views define the observations).
        points_mm: (N, 3) target points in the world frame, mm.
        seed: seeds a private torch.Generator (the global RNG is untouched).
    """
    pts = torch.as_tensor(points_mm, dtype=torch.float64)
    gen = torch.Generator().manual_seed(int(seed))
    with torch.no_grad():
        cam = camera if camera.rvec.dtype == torch.float64 else camera.copy().double()
        p_cam = cam.to_camera(pts)
        uv = cam.project_camera(p_cam)
        b = cam.blur_camera(p_cam)
        V, N = b.shape
        uv = uv + noise_px * torch.randn(V, N, 2, generator=gen, dtype=torch.float64)
        sb = torch.sqrt(noise_blur_px ** 2 + (noise_blur_rel * b) ** 2)
        b = torch.clamp(b + sb * torch.randn(V, N, generator=gen, dtype=torch.float64), min=0.0)
        W, H = cam.image_size_px
        inside = ((p_cam[..., 2] > 0) & (uv[..., 0] >= -0.5 + margin_px) & (uv[..., 0] <= W - 0.5 - margin_px)
                  & (uv[..., 1] >= -0.5 + margin_px) & (uv[..., 1] <= H - 0.5 - margin_px))
        uv = torch.where(inside[..., None], uv, torch.full_like(uv, float("nan")))
        b = torch.where(inside, b, torch.full_like(b, float("nan")))
    return Observations(pts, uv, b, cam.image_size_px, cam.pixel_pitch_mm, names)


def board_points_mm(nx: int = 8, ny: int = 5, pitch_mm: float = 25.0, centred: bool = True) -> torch.Tensor:
    """(ny·nx, 3) interior corners of a planar board on Z = 0, row by row (Y outer, X inner), mm."""
    x = torch.arange(nx, dtype=torch.float64) * pitch_mm
    y = torch.arange(ny, dtype=torch.float64) * pitch_mm
    if centred:
        x, y = x - x.mean(), y - y.mean()
    Y, X = torch.meshgrid(y, x, indexing="ij")
    return torch.stack([X.reshape(-1), Y.reshape(-1), torch.zeros(nx * ny, dtype=torch.float64)], -1)


# The paper's camera (`renderer.Lens.paper()`: Canon EOS 6D, TS-E 45 mm at f/2.8; stage-1 values of the paper's
# experiment) as `LensCamera`'s keyword arguments.
PAPER_SENSOR = {"image_size_px": Lens.paper().sensor.size_px, "pixel_pitch_mm": Lens.paper().sensor.pixel_pitch}
PAPER_LENS = {"w_mm": Lens.paper().w, "U_mm": Lens.paper().U, "d_mm": Lens.paper().d}


def random_poses(n_views: int, seed: int = 0, distance_mm=(520.0, 720.0), max_angle_deg: float = 17.0,
                 max_roll_deg: float = 6.0, shift_mm=(30.0, 20.0), board_centre_mm=(0.0, 0.0)):
    """Random board poses for synthetic calibrations: the board centre at a random depth and offset.

    Args:
        n_views: V.
        seed: seeds a private generator.
        distance_mm: (min, max) depth of the board centre in the camera frame.
        max_angle_deg: largest rotation about the camera x and y axes; max_roll_deg: about z.
        shift_mm: largest |x|, |y| offset of the board centre from the optical axis.
        board_centre_mm: the board point placed at that centre, target frame (X, Y).
    Returns:
        (rvec (V, 3) radians, T (V, 3) mm), X_cam = R(rvec) X_target + T.
    """
    gen = torch.Generator().manual_seed(int(seed))
    u = lambda *s: 2.0 * torch.rand(*s, generator=gen, dtype=torch.float64) - 1.0  # noqa: E731
    lim = torch.tensor([max_angle_deg, max_angle_deg, max_roll_deg], dtype=torch.float64) * math.pi / 180
    rvec = u(n_views, 3) * lim
    z0, z1 = distance_mm
    centre_cam = torch.stack([u(n_views) * shift_mm[0], u(n_views) * shift_mm[1],
                              z0 + (z1 - z0) * torch.rand(n_views, generator=gen, dtype=torch.float64)], -1)
    c = torch.tensor([board_centre_mm[0], board_centre_mm[1], 0.0], dtype=torch.float64)
    T = centre_cam - axis_angle_to_matrix(rvec) @ c
    return rvec, T
