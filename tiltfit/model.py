"""Tilt-lens camera model for calibration: pinhole geometry plus thin-lens blur (paper eqs 2–4).

A `TiltLensCamera` holds the lens state shared by all views (w, U, d, θF and optionally the principal
point) and one pose per view. It answers two calls, both differentiable in every parameter:

    project(X_world, view) -> uv_px    uv = c + (w / p) · D(x / z, y / z),  (x, y, z) = R X + T
    blur(X_world, view)    -> b_px     blur-disc diameter b = w d |1/z_F − 1/z| / p     (eqs 2 and 4)

Conventions (docs/conventions.md): camera frame x right, y down, z forward; X_cam = R X_world + T;
pixel (0, 0) is the centre of the top-left pixel and the principal point defaults to ((W−1)/2, (H−1)/2);
the plane of focus is z = U + y tan θF in the camera frame; lengths in mm, angles in radians.
D is the lens's Brown–Conrady distortion in OpenCV's order and normalisation
(`renderer.cameras.distortion`, coefficients k1, k2, p1, p2, k3, k4, k5, k6; identity when all are 0), so an
untilted camera equals `cv2.projectPoints` with K = [[w/p, 0, cx], [0, w/p, cy], [0, 0, 1]].

Blur models (`blur_model`; closed forms from `renderer.optics`, all equal to eq (2) when θF = 0):
    "ellipse" (default): equivalent-area diameter 2 sqrt(ab) of the exact blur ellipse of an ideal thin lens
        tilted about its centre by θL (θL from θF, w, U by the exact Scheimpflug relation).
    "first_order": b = w d |1/z_F − 1/z| with z_F = U z / (z − y tan θF), where the chief ray meets the plane
        of focus: the exact width along x to first order in the aperture.
    "paper": b = w d |1/(U + y tan θF) − 1/z|, the paper's eq (4) (focus depth at the point's own height).
A constant `blur_offset_px` (0 unless fitted) is added to every width: the blur detector's bias, not optics.

Parametrisation (for conditioning, so one learning rate suits all parameters): w is stored as its logarithm
(`log_w_mm`), the aperture in centimetres with d = |d_scaled| · 10 mm (`d_scaled`, so d ≥ 0 and a pinhole,
d = 0, is an ordinary value: sharp images leave it near 0 instead of driving a logarithm to −∞), the focus as
its inverse in dioptres (`inv_U_per_m` = 1000 / U_mm, so focus at infinity is the ordinary value 0), the distortion coefficients as themselves (`dist_k1` …),
rotations as axis-angle vectors (`rvec`), translations in units of `length_scale_mm` (`T_scaled`, default
100 mm) and the principal-point offset from the image centre in units of `pixel_scale_px` (`pp_scaled`,
default 100 px). Physical values are properties (`w_mm`, `T_mm`, `R`, `principal_point_px` …).
`free(*names)` / `freeze(*names)` switch parameters on and off by friendly name: w, U, d, theta_F, rvec, T,
principal_point, blur_offset, k1 … k6, p1, p2, or the groups lens (w, U, d), pose (rvec, T), distortion (all
eight coefficients), all.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from renderer import optics
from renderer.cameras.distortion import COEFFICIENT_NAMES, MODEL_TERMS, BrownConrady, distort

BLUR_MODELS = ("ellipse", "first_order", "paper")
APERTURE_SCALE_MM = 10.0  # d_scaled is the aperture diameter in cm
ROBUST_LOSSES = (None, "none", "huber", "cauchy")

_DIST = tuple(f"dist_{k}" for k in COEFFICIENT_NAMES)
_GROUPS = {
    "w": ("log_w_mm",),
    "U": ("inv_U_per_m",),
    "d": ("d_scaled",),
    "theta_F": ("theta_F",),
    "rvec": ("rvec",),
    "R": ("rvec",),
    "T": ("T_scaled",),
    "principal_point": ("pp_scaled",),
    "blur_offset": ("blur_offset_px",),
    "lens": ("log_w_mm", "inv_U_per_m", "d_scaled"),
    "pose": ("rvec", "T_scaled"),
    **{k: (f"dist_{k}",) for k in COEFFICIENT_NAMES},
    "distortion": _DIST,
    "all": ("log_w_mm", "inv_U_per_m", "d_scaled", "theta_F", "rvec", "T_scaled", "pp_scaled", "blur_offset_px")
    + _DIST,
}


def distortion_parameter_names(model: str) -> tuple[str, ...]:
    """Stored names of the coefficients a distortion model frees ("none", "k1", "k1k2", "opencv5", "rational")."""
    if model not in MODEL_TERMS:
        raise ValueError(f"distortion: expected one of {tuple(MODEL_TERMS)}, got {model!r}")
    return tuple(f"dist_{k}" for k in MODEL_TERMS[model])


# ---------------------------------------------------------------------------------------------------------
# Blur models (closed forms from renderer.optics)
# ---------------------------------------------------------------------------------------------------------

def blur_diameter_mm(p_cam: torch.Tensor, w_mm, U_mm, d_mm, theta_F=0.0, blur_model: str = "ellipse"):
    """Blur diameter on the sensor for camera-frame points, by the named model (all equal eq (2) at θF = 0).

    Args:
        p_cam: (..., 3) camera-frame points, mm. Lens parameters: scalars or broadcastable tensors (mm, rad).
        blur_model: "ellipse" (equivalent-area diameter of the exact spot), "first_order" (w d |1/z_F − 1/z|
            with z_F where the chief ray meets the plane of focus) or "paper" (eq (4)).
    Returns:
        (...,) diameter in mm on the sensor.
    """
    if blur_model == "ellipse":
        return optics.blur_diameter_exact(p_cam, w_mm, U_mm, d_mm, theta_F)
    if blur_model == "first_order":
        return optics.blur_diameter_first_order(p_cam, w_mm, U_mm, d_mm, theta_F)
    if blur_model == "paper":
        return optics.blur_diameter_paper(p_cam[..., 1], p_cam[..., 2], w_mm, U_mm, d_mm, theta_F)
    raise ValueError(f"blur_model: expected one of {BLUR_MODELS}, got {blur_model!r}")


# ---------------------------------------------------------------------------------------------------------
# Rotations
# ---------------------------------------------------------------------------------------------------------

def _skew(v: torch.Tensor) -> torch.Tensor:
    o = torch.zeros_like(v[..., 0])
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).reshape(v.shape[:-1] + (3, 3))


def axis_angle_to_matrix(rvec: torch.Tensor) -> torch.Tensor:
    """(..., 3) axis-angle vectors (radians) -> (..., 3, 3) rotation matrices (Rodrigues; smooth at 0)."""
    theta2 = (rvec * rvec).sum(-1)[..., None, None]
    small = theta2 < 1e-8
    safe = torch.where(small, torch.ones_like(theta2), theta2)
    theta = torch.sqrt(safe)
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / safe)
    K = _skew(rvec)
    eye = torch.eye(3, dtype=rvec.dtype, device=rvec.device).expand(K.shape)
    return eye + a * K + b * (K @ K)


def matrix_to_axis_angle(R) -> torch.Tensor:
    """(..., 3, 3) rotation matrices -> (..., 3) axis-angle vectors, radians (via quaternions, kornia)."""
    from kornia.geometry.conversions import rotation_matrix_to_axis_angle

    R = torch.as_tensor(R, dtype=torch.float64).detach()
    flat = R.reshape(-1, 3, 3)
    out = rotation_matrix_to_axis_angle(flat) if len(flat) else torch.zeros(0, 3, dtype=torch.float64)
    return out.reshape(R.shape[:-2] + (3,))


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
# The camera
# ---------------------------------------------------------------------------------------------------------

class TiltLensCamera(torch.nn.Module):
    """Pinhole-plus-thin-lens camera with a tilted plane of focus, V views sharing one lens.

    Args:
        n_views: number of views V (poses).
        image_size_px: (W, H).
        pixel_pitch_mm: sensor pixel pitch p, mm (a constant, not fitted).
        w_mm: lens centre to sensor (effective focal length), mm.
        U_mm: lens centre to the plane of focus on the optical axis, mm (math.inf: focus at infinity).
        d_mm: effective aperture diameter, mm.
        distortion: up to 8 Brown–Conrady coefficients (k1, k2, p1, p2, k3, k4, k5, k6) [zeros]; frozen
            unless freed (`free("k1")`, `free(*distortion_parameter_names("opencv5"))`).
        theta_F: tilt of the plane of focus about the camera x axis, radians [0].
        R: (V, 3, 3) rotations camera_from_world [identity]; or `rvec` (V, 3) axis-angle.
        T_mm: (V, 3) translations, mm [(0, 0, 600)].
        principal_point_px: (cx, cy) [image centre]; frozen unless freed.
        blur_model: "ellipse", "first_order" or "paper" (see the module docstring).
        length_scale_mm, pixel_scale_px: units of the stored translation and principal-point parameters.

    By default every parameter is free except the principal point.
    """

    def __init__(self, n_views: int, image_size_px, pixel_pitch_mm: float, w_mm: float, U_mm: float,
                 d_mm: float, theta_F: float = 0.0, R=None, T_mm=None, rvec=None, principal_point_px=None,
                 blur_model: str = "ellipse", length_scale_mm: float = 100.0, pixel_scale_px: float = 100.0,
                 dtype=torch.float64, distortion=None):
        super().__init__()
        if blur_model not in BLUR_MODELS:
            raise ValueError(f"blur_model: expected one of {BLUR_MODELS}, got {blur_model!r}")
        for name, v in (("pixel_pitch_mm", pixel_pitch_mm), ("w_mm", w_mm), ("d_mm", d_mm)):
            if not (math.isfinite(float(v)) and float(v) > 0):
                raise ValueError(f"{name}: expected a positive length, got {v!r}")
        if not float(U_mm) > 0:
            raise ValueError(f"U_mm: expected a positive length or inf, got {U_mm!r}")
        if not abs(float(theta_F)) < math.pi / 2:
            raise ValueError(f"theta_F: expected |θF| < 90°, got {math.degrees(float(theta_F))}°")
        self.image_size_px = (int(image_size_px[0]), int(image_size_px[1]))
        self.pixel_pitch_mm = float(pixel_pitch_mm)
        self.blur_model = blur_model
        self.length_scale_mm = float(length_scale_mm)
        self.pixel_scale_px = float(pixel_scale_px)
        V = int(n_views)
        if rvec is None:
            rvec = torch.zeros(V, 3) if R is None else matrix_to_axis_angle(R)
        rvec = torch.as_tensor(rvec, dtype=dtype).reshape(V, 3)
        T_mm = torch.tensor([[0.0, 0.0, 600.0]] * V) if T_mm is None else T_mm
        T_mm = torch.as_tensor(T_mm, dtype=dtype).reshape(V, 3)
        P = torch.nn.Parameter
        self.log_w_mm = P(torch.tensor(math.log(float(w_mm)), dtype=dtype))
        self.inv_U_per_m = P(torch.tensor(1000.0 / float(U_mm), dtype=dtype))
        # d = 0 exactly would be a stationary point of |d_scaled| (zero gradient): start a hair above it.
        self.d_scaled = P(torch.tensor(max(float(d_mm), 1e-6) / APERTURE_SCALE_MM, dtype=dtype))
        self.theta_F = P(torch.tensor(float(theta_F), dtype=dtype))
        self.rvec = P(rvec.clone())
        self.T_scaled = P(T_mm / self.length_scale_mm)
        W, H = self.image_size_px
        centre = torch.tensor([(W - 1) / 2.0, (H - 1) / 2.0], dtype=dtype)
        self.register_buffer("image_centre_px", centre)
        pp = centre if principal_point_px is None else torch.as_tensor(principal_point_px, dtype=dtype)
        self.pp_scaled = P((pp - centre) / self.pixel_scale_px)
        k = BrownConrady(() if distortion is None else tuple(distortion)).coefficients  # checked, padded to 8
        for name, v in zip(_DIST, k):
            setattr(self, name, P(torch.tensor(v, dtype=dtype)))
        # A constant added to every measured blur width: a blur detector's bias (e.g. from its edge model),
        # not optics. Frozen at 0 unless freed; the fit frees it so the bias does not leak into d and U.
        self.blur_offset_px = P(torch.tensor(0.0, dtype=dtype))
        self.freeze("principal_point", "distortion", "blur_offset")

    # --- freeing and freezing --------------------------------------------------------------------------
    @staticmethod
    def parameter_names(*names: str) -> list[str]:
        """Stored parameter names for friendly names (w, U, d, theta_F, rvec, T, principal_point, lens,
        pose, all) or stored names themselves."""
        out: list[str] = []
        for n in names:
            if n in _GROUPS:
                out.extend(_GROUPS[n])
            elif n in _GROUPS["all"]:
                out.append(n)
            else:
                raise ValueError(f"unknown parameter {n!r} (expected one of {', '.join(_GROUPS)})")
        return list(dict.fromkeys(out))

    def free(self, *names: str) -> "TiltLensCamera":
        """Let the named parameters be fitted (requires_grad = True); returns self."""
        for n in self.parameter_names(*names):
            getattr(self, n).requires_grad_(True)
        return self

    def freeze(self, *names: str) -> "TiltLensCamera":
        """Hold the named parameters (requires_grad = False); returns self."""
        for n in self.parameter_names(*names):
            getattr(self, n).requires_grad_(False)
        return self

    def free_parameter_names(self) -> list[str]:
        return [n for n, p in self.named_parameters() if p.requires_grad]

    # --- physical values ---------------------------------------------------------------------------------
    @property
    def n_views(self) -> int:
        return self.rvec.shape[0]

    @property
    def w_mm(self) -> torch.Tensor:
        return torch.exp(self.log_w_mm)

    @property
    def U_mm(self) -> torch.Tensor:
        """Focus distance, mm (inf at focus at infinity)."""
        return 1000.0 / self.inv_U_per_m

    @property
    def distortion(self) -> torch.Tensor:
        """(8,) Brown–Conrady coefficients (k1, k2, p1, p2, k3, k4, k5, k6)."""
        return torch.stack([getattr(self, n) for n in _DIST])

    @property
    def d_mm(self) -> torch.Tensor:
        return self.d_scaled.abs() * APERTURE_SCALE_MM

    @property
    def tan_theta_F(self) -> torch.Tensor:
        return torch.tan(self.theta_F)

    @property
    def theta_L(self) -> torch.Tensor:
        """Exact lens tilt, radians (tan θL = w tan θF / (U + w))."""
        return optics.theta_L_from_theta_F(self.theta_F, self.w_mm, self.U_mm)

    @property
    def f_mm(self) -> torch.Tensor:
        """Focal length of the ideal thin lens in this state: f = U w cos θL / (U + w) (hinge rule)."""
        return optics.focal_length(self.w_mm, self.U_mm, self.theta_L)

    @property
    def theta_L_paper(self) -> torch.Tensor:
        """The paper's eq (1), θL = atan(f tan θF / (U + f)), with this state's f; radians."""
        return optics.theta_L_paper(self.theta_F, self.f_mm, self.U_mm)

    @property
    def R(self) -> torch.Tensor:
        """(V, 3, 3) rotations camera_from_world."""
        return axis_angle_to_matrix(self.rvec)

    @property
    def T_mm(self) -> torch.Tensor:
        """(V, 3) translations, mm."""
        return self.T_scaled * self.length_scale_mm

    @property
    def principal_point_px(self) -> torch.Tensor:
        """(2,) principal point (cx, cy), pixels."""
        return self.image_centre_px + self.pp_scaled * self.pixel_scale_px

    @property
    def focal_px(self) -> torch.Tensor:
        return self.w_mm / self.pixel_pitch_mm

    # --- the two calls -----------------------------------------------------------------------------------
    def to_camera(self, X_world: torch.Tensor, view=None) -> torch.Tensor:
        """World points to the camera frame: X_cam = R X_world + T.

        Args:
            X_world: (..., 3) points, mm.
            view: view index (int), or None for all views.
        Returns:
            (..., 3) for one view, (V, ..., 3) for all views; mm.
        """
        X = torch.as_tensor(X_world, dtype=self.rvec.dtype, device=self.rvec.device)
        R, T = self.R, self.T_mm
        if view is not None:
            return X @ R[view].transpose(-1, -2) + T[view]
        extra = X.dim() - 1
        R = R.reshape((R.shape[0],) + (1,) * extra + (3, 3))
        T = T.reshape((T.shape[0],) + (1,) * extra + (3,))
        return (X.unsqueeze(0).unsqueeze(-2) @ R.transpose(-1, -2)).squeeze(-2) + T

    def project_camera(self, p_cam: torch.Tensor, with_distortion: bool = True) -> torch.Tensor:
        """(..., 3) camera-frame points -> (..., 2) pixels: uv = c + (w / p) D(x / z, y / z).

        `with_distortion` False skips D (callers that know all coefficients are held at 0 save its cost)."""
        xy = p_cam[..., :2] / p_cam[..., 2:3]
        if with_distortion:
            xy = distort(xy, self.distortion)
        return self.principal_point_px + self.focal_px * xy

    def blur_camera(self, p_cam: torch.Tensor) -> torch.Tensor:
        """(..., 3) camera-frame points -> (...,) blur diameters in pixels (eq (2)/(4), `blur_model`)."""
        b_mm = blur_diameter_mm(p_cam, self.w_mm, self.U_mm, self.d_mm, self.theta_F, self.blur_model)
        return b_mm / self.pixel_pitch_mm + self.blur_offset_px

    def project(self, X_world: torch.Tensor, view=None) -> torch.Tensor:
        """(..., 3) world points (mm) -> (..., 2) pixels in `view` (or (V, ..., 2) for view=None)."""
        return self.project_camera(self.to_camera(X_world, view))

    def blur(self, X_world: torch.Tensor, view=None) -> torch.Tensor:
        """(..., 3) world points (mm) -> (...,) blur diameters in pixels in `view` (or (V, ...))."""
        return self.blur_camera(self.to_camera(X_world, view))

    def forward(self, X_world: torch.Tensor, with_blur: bool = True, with_distortion: bool = True):
        """All views at once: (N, 3) world points -> ((V, N, 2) uv_px, (V, N) blur_px); the blur is zeros
        when `with_blur` is False (geometric fits skip its cost); see `project_camera` for `with_distortion`."""
        p_cam = self.to_camera(X_world)
        uv = self.project_camera(p_cam, with_distortion)
        return uv, (self.blur_camera(p_cam) if with_blur else torch.zeros_like(p_cam[..., 0]))

    # --- convenience -------------------------------------------------------------------------------------
    def copy(self) -> "TiltLensCamera":
        """An independent copy with the same free/frozen state."""
        import copy

        return copy.deepcopy(self)

    def summary(self) -> dict:
        """Plain floats of the lens state (mm and degrees)."""
        with torch.no_grad():
            return {
                "w_mm": float(self.w_mm), "U_mm": float(self.U_mm), "d_mm": float(self.d_mm),
                "f_mm": float(self.f_mm), "theta_F_deg": math.degrees(float(self.theta_F)),
                "theta_L_deg": math.degrees(float(self.theta_L)),
                "theta_L_paper_deg": math.degrees(float(self.theta_L_paper)),
                "principal_point_px": [float(v) for v in self.principal_point_px],
                "distortion": [float(v) for v in self.distortion],
                "blur_offset_px": float(self.blur_offset_px),
            }

    @staticmethod
    def from_tilted_lens(n_views: int, image_size_px, pixel_pitch_mm: float, w_mm: float, f_mm: float,
                         d_mm: float, theta_L: float, **kwargs) -> "TiltLensCamera":
        """A camera whose thin lens (focal f, sensor at w) is tilted by θL about its centre.

        U and θF follow from the exact relations (hinge rule and Scheimpflug), so U moves with the tilt.
        """
        U = optics.focus_distance_tilted(w_mm, f_mm, theta_L)
        theta_F = optics.theta_F_from_theta_L(theta_L, w_mm, U)
        return TiltLensCamera(n_views, image_size_px, pixel_pitch_mm, w_mm, float(U), d_mm, float(theta_F),
                              **kwargs)


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
        """((V,) reprojection RMS over both coordinates, (V,) blur RMS), pixels; NaN for empty views."""
        nc = self.corner_mask.sum(-1)
        nb = self.blur_mask.sum(-1)
        rc = torch.sqrt((self.corners_px ** 2).sum((-1, -2)) / (2 * nc))
        rb = torch.sqrt((self.blur_px ** 2).sum(-1) / nb)
        return rc, rb


def residuals(camera: TiltLensCamera, obs: Observations) -> Residuals:
    """Residuals of the model against the observations (model − observed), all views at once."""
    uv, b = camera(obs.points_mm)
    cm, bm = obs.corner_mask.to(uv.device), obs.blur_mask.to(uv.device)
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


def normalized_residual_vector(camera: TiltLensCamera, obs: Observations, sigma_corner_px: float = 1.0,
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


def loss(camera: TiltLensCamera, obs: Observations, sigma_corner_px: float = 1.0, sigma_blur_px: float = 1.0,
         robust: str | None = None, robust_scale: float = 3.0, use_corners: bool = True,
         use_blur: bool = True) -> torch.Tensor:
    """Scalar ½ Σ ρ((r / σ)²) over corners and blur: minimise it with any torch optimizer."""
    r = normalized_residual_vector(camera, obs, sigma_corner_px, sigma_blur_px, use_corners, use_blur)
    return 0.5 * robust_rho(r * r, robust, robust_scale).sum()


# ---------------------------------------------------------------------------------------------------------
# Synthetic observations
# ---------------------------------------------------------------------------------------------------------

def synthesize_observations(camera: TiltLensCamera, points_mm, noise_px: float = 0.0, noise_blur_px: float = 0.0,
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


# The paper's camera (Canon EOS 6D, TS-E 45 mm at f/2.8; stage-1 values of the paper's experiment).
PAPER_SENSOR = {"image_size_px": (5472, 3648), "pixel_pitch_mm": 0.00654}
PAPER_LENS = {"w_mm": 55.39, "U_mm": 618.4, "d_mm": 18.81}


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
