"""The one camera model: pose, lens and sensor mapping as a torch module with tensor parameters, V views sharing
one lens. It renders (`view_camera(v)` is the renderer's `ThinLensCamera` of view v, built from the module's own
tensors, so gradients of a rendered image reach every parameter) and it is fitted (tiltfit's calibration uses it
as `tiltfit.calibrate.model.LensCamera`: pinhole geometry plus thin-lens blur, paper eqs 2–4). Its two closed-form
calls, both differentiable in every parameter:

    project(X_world, view) -> uv_px    uv = c + (w / p) · D(x / z, y / z),  (x, y, z) = R X + T
    blur(X_world, view)    -> b_px     blur-disc diameter b = w d |1/z_F − 1/z| / p     (eqs 2 and 4)

The projection is `renderer.cameras.projection.project_pinhole` (the same function as every renderer camera's
chief-ray projection), the blur `renderer.cameras.optics.blur_diameter`, rotations `renderer.core.transforms`.

Conventions (docs/conventions.md): camera frame x right, y down, z forward; X_cam = R X_world + T;
pixel (0, 0) is the centre of the top-left pixel and the principal point defaults to ((W−1)/2, (H−1)/2);
the plane of focus is z = U + y_φ tan θF in the camera frame, y_φ = y cos φ − x sin φ (φ: the tilt axis's
direction, 0 unless freed: the camera x axis); lengths in mm (the scene unit of a real camera),
angles in radians.
D is the lens's Brown–Conrady distortion in OpenCV's order and normalisation
(`renderer.cameras.distortion`, coefficients k1, k2, p1, p2, k3, k4, k5, k6; identity when all are 0), so an
untilted camera equals `cv2.projectPoints` with K = [[w/p, 0, cx], [0, w/p, cy], [0, 0, 1]]. With
`distortion_centre="lens_axis"` D acts in the lens's own frame, about its axis (`renderer.Lens.distortion_frame`,
`distortion.distort_about_axis`): a tilted camera then equals OpenCV's tilted model (τx, τy; see
tiltfit/files/export.py); for θL = 0 it is the same model.

Blur models (`blur_model`; closed forms from `renderer.cameras.optics`, all equal to eq (2) when θF = 0):
    "ellipse" (default): equivalent-area diameter 2 sqrt(ab) of the exact blur ellipse of an ideal thin lens
        tilted about its centre by θL (θL from θF, w, U by the exact Scheimpflug relation).
    "first_order": b = w d |1/z_F − 1/z| with z_F = U z / (z − y tan θF), where the chief ray meets the plane
        of focus: the exact width along x to first order in the aperture.
    "paper": b = w d |1/(U + y tan θF) − 1/z|, the paper's eq (4) (focus depth at the point's own height).
A constant `blur_offset_px` (0 unless fitted) is added to every width: the blur detector's bias, not optics.

Parametrisation (for conditioning, so one learning rate suits all parameters): w is stored as its logarithm
(`log_w_mm`), the aperture in centimetres with d = |d_scaled| · 10 mm (`d_scaled`, so d ≥ 0 and a pinhole,
d = 0, is an ordinary value: sharp images leave it near 0 instead of driving a logarithm to −∞), the focus as
its inverse in dioptres (`inv_U_per_m` = 1000 / U_mm, so focus at infinity is the ordinary value 0), the
distortion coefficients as themselves (`dist_k1` …), rotations as axis-angle vectors (`rvec`), translations
in units of `length_scale_mm` (`T_scaled`, default 100 mm) and the principal-point offset from the image
centre in units of `pixel_scale_px` (`pp_scaled`, default 100 px). Physical values are properties (`w_mm`, `T_mm`, `R`, `principal_point_px` …).
`free(*names)` / `freeze(*names)` switch parameters on and off by friendly name: w, U, d, theta_F, rvec, T,
principal_point, blur_offset, k1 … k6, p1, p2, or the groups lens (w, U, d), pose (rvec, T), distortion (all
eight coefficients), all.
"""
from __future__ import annotations

import copy
import math
from typing import NamedTuple

import torch

from . import optics
from renderer.cameras.optics import BLUR_MODELS
from renderer.core.transforms import axis_angle_to_matrix, matrix_to_axis_angle, rotated_point_jacobian
from .distortion import COEFFICIENT_NAMES, MODEL_TERMS, BrownConrady, distort_with_jacobians
from .distortion import distort_about_axis_jacobians
from .lens import DISTORTION_CENTRES, Lens, Sensor, opencv_tilt, tilt_frame, tilt_rotation
from .projection import image_centre_px, project_pinhole
from .thin_lens import ThinLensCamera
from .lens_vector import U_from_stored, d_from_stored, lens_from_stored_jacobian, stored_from_lens, w_from_stored

_DIST = tuple(f"dist_{k}" for k in COEFFICIENT_NAMES)
_GROUPS = {
    "w": ("log_w_mm",),
    "U": ("inv_U_per_m",),
    "d": ("d_scaled",),
    "theta_F": ("theta_F",),
    "phi": ("phi",),
    "rvec": ("rvec",),
    "R": ("rvec",),
    "T": ("T_scaled",),
    "principal_point": ("pp_scaled",),
    "blur_offset": ("blur_offset_px",),
    "lens": ("log_w_mm", "inv_U_per_m", "d_scaled"),
    "pose": ("rvec", "T_scaled"),
    **{k: (f"dist_{k}",) for k in COEFFICIENT_NAMES},
    "distortion": _DIST,
    "all": ("log_w_mm", "inv_U_per_m", "d_scaled", "theta_F", "phi", "rvec", "T_scaled", "pp_scaled",
            "blur_offset_px")
    + _DIST,
}


def distortion_parameter_names(model: str) -> tuple[str, ...]:
    """Stored names of the coefficients a distortion model frees ("none", "k1", "k1k2", "opencv5", "rational5", "rational")."""
    if model not in MODEL_TERMS:
        raise ValueError(f"distortion: expected one of {tuple(MODEL_TERMS)}, got {model!r}")
    return tuple(f"dist_{k}" for k in MODEL_TERMS[model])


def _through_perspective(J_xy: torch.Tensor, xn: torch.Tensor, iz: torch.Tensor) -> torch.Tensor:
    """(..., 2, 2) ∂f/∂xn times ∂xn/∂p_cam = [[1/z, 0, −x/z²], [0, 1/z, −y/z²]] -> (..., 2, 3) ∂f/∂p_cam,
    written out (the product's zeros skipped; a batched 2 × 2 by 2 × 3 matmul per point costs more)."""
    Jz = J_xy * iz[..., None, None]
    return torch.cat([Jz, -(Jz[..., 0:1] * xn[..., None, 0:1] + Jz[..., 1:2] * xn[..., None, 1:2])], -1)


class _ProjectionTerms(NamedTuple):
    """The terms of `LensCamera.jacobian`'s projection that its columns share (V views, N points)."""
    rvec: torch.Tensor      # (V, 3) axis-angle rotations
    p_rot: torch.Tensor     # (V, N, 3) R X, mm
    p_cam: torch.Tensor     # (V, N, 3) camera frame, mm
    xn: torch.Tensor        # (V, N, 2) ideal normalised coordinates x / z, y / z
    k: torch.Tensor         # (8,) distortion coefficients
    xd: torch.Tensor        # (V, N, 2) distorted normalised coordinates
    dxd_dp: torch.Tensor    # (V, N, 2, 3) ∂x_d/∂p_cam
    uv: torch.Tensor        # (V, N, 2) pixels
    F: float                # focal length, pixels
    with_distortion: bool
    axis: bool              # D about the lens axis (its frame turns with θL and φ)
    J_k: torch.Tensor | None        # ∂x_d/∂k: about the lens axis all 8 columns; else those of `dist_names`
    dist_names: tuple               # the distortion coefficients (stored names) whose columns are asked for
    J_angles: list | None           # axis only: [∂x_d/∂θL, ∂x_d/∂φ]
    dthL: list | None               # axis only: ∂θL/∂(log w, 1/U in dioptres, θF)


class _BlurTerms(NamedTuple):
    """The terms of `LensCamera.jacobian`'s blur (zeros and None without blur)."""
    with_blur: bool
    b: torch.Tensor                 # (V, N) blur diameters, pixels
    db_dlens: torch.Tensor | None   # (V, N, 4) ∂b_mm/∂(w, U, d, θF)
    db_dphi: torch.Tensor | None    # (V, N) ∂b_mm/∂φ
    rows: torch.Tensor              # (V, N, 3, 3) ∂(u, v, b)/∂p_cam


class LensCamera(torch.nn.Module):
    """Thin-lens camera with a tilted plane of focus and lens distortion, V views sharing one lens (tiltfit's
    calibration camera).

    Args:
        n_views: number of views V (poses).
        image_size_px: (W, H).
        pixel_pitch_mm: sensor pixel pitch p, mm (a constant, not fitted).
        w_mm: lens centre to sensor (effective focal length), mm.
        U_mm: lens centre to the plane of focus on the optical axis, mm (math.inf: focus at infinity).
        d_mm: effective aperture diameter, mm.
        distortion: up to 8 Brown–Conrady coefficients (k1, k2, p1, p2, k3, k4, k5, k6) [zeros]; frozen
            unless freed (`free("k1")`, `free(*distortion_parameter_names("opencv5"))`).
        theta_F: tilt of the plane of focus about the tilt axis, radians [0].
        phi: the tilt axis's direction from the camera x axis, radians [0]; frozen unless freed (`free("phi")`).
        R: (V, 3, 3) rotations camera_from_world [identity]; or `rvec` (V, 3) axis-angle.
        T_mm: (V, 3) translations, mm [(0, 0, 600)].
        principal_point_px: (cx, cy) [image centre]; frozen unless freed.
        blur_model: "ellipse", "first_order" or "paper" (see the module docstring).
        distortion_centre: "sensor" (D about the principal point) or "lens_axis" (D in the lens frame, about
            the tilted lens's axis; `renderer.Lens`) ["sensor"]; a model choice, not a parameter.
        length_scale_mm, pixel_scale_px: units of the stored translation and principal-point parameters.

    By default every parameter is free except the principal point.
    """

    def __init__(self, n_views: int, image_size_px, pixel_pitch_mm: float, w_mm: float, U_mm: float,
                 d_mm: float, theta_F: float = 0.0, R=None, T_mm=None, rvec=None, principal_point_px=None,
                 blur_model: str = "ellipse", length_scale_mm: float = 100.0, pixel_scale_px: float = 100.0,
                 dtype=torch.float64, distortion=None, phi: float = 0.0, distortion_centre: str = "sensor"):
        super().__init__()
        if distortion_centre not in DISTORTION_CENTRES:
            raise ValueError(f"distortion_centre: expected one of {DISTORTION_CENTRES}, got {distortion_centre!r}")
        self.distortion_centre = distortion_centre
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
        # d = 0 exactly would be a stationary point of |d_scaled| (zero gradient): start a hair above it.
        for name, v in stored_from_lens(w_mm, U_mm, max(float(d_mm), 1e-6), theta_F).items():
            setattr(self, name, P(torch.tensor(v, dtype=dtype)))
        self.phi = P(torch.tensor(float(phi), dtype=dtype))
        self.rvec = P(rvec.clone())
        self.T_scaled = P(T_mm / self.length_scale_mm)
        W, H = self.image_size_px
        centre = torch.tensor(image_centre_px(W, H), dtype=dtype)
        self.register_buffer("image_centre_px", centre)
        pp = centre if principal_point_px is None else torch.as_tensor(principal_point_px, dtype=dtype)
        self.pp_scaled = P((pp - centre) / self.pixel_scale_px)
        k = BrownConrady(() if distortion is None else tuple(distortion)).coefficients  # checked, padded to 8
        for name, v in zip(_DIST, k):
            setattr(self, name, P(torch.tensor(v, dtype=dtype)))
        # A constant added to every measured blur width: a blur detector's bias (e.g. from its edge model),
        # not optics. Frozen at 0 unless freed; the fit frees it so the bias does not leak into d and U.
        self.blur_offset_px = P(torch.tensor(0.0, dtype=dtype))
        self.freeze("principal_point", "distortion", "blur_offset", "phi")

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

    def free(self, *names: str) -> "LensCamera":
        """Let the named parameters be fitted (requires_grad = True); returns self."""
        for n in self.parameter_names(*names):
            getattr(self, n).requires_grad_(True)
        return self

    def freeze(self, *names: str) -> "LensCamera":
        """Hold the named parameters (requires_grad = False); returns self."""
        for n in self.parameter_names(*names):
            getattr(self, n).requires_grad_(False)
        return self

    def free_parameter_names(self) -> list[str]:
        return [n for n, p in self.named_parameters() if p.requires_grad]

    def set_lens(self, **values) -> "LensCamera":
        """Set stored lens parameters in place from lens values (`stored_from_lens`' keywords: w_mm, U_mm, d_mm,
        theta_F); returns self."""
        with torch.no_grad():
            for name, v in stored_from_lens(**values).items():
                getattr(self, name).fill_(v)
        return self

    # --- physical values ---------------------------------------------------------------------------------
    @property
    def n_views(self) -> int:
        return self.rvec.shape[0]

    @property
    def w_mm(self) -> torch.Tensor:
        return w_from_stored(self.log_w_mm)

    @property
    def U_mm(self) -> torch.Tensor:
        """Focus distance, mm (inf at focus at infinity)."""
        return U_from_stored(self.inv_U_per_m)

    @property
    def distortion(self) -> torch.Tensor:
        """(8,) Brown–Conrady coefficients (k1, k2, p1, p2, k3, k4, k5, k6)."""
        return torch.stack([getattr(self, n) for n in _DIST])

    @property
    def d_mm(self) -> torch.Tensor:
        return d_from_stored(self.d_scaled)

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

    @property
    def sensor(self) -> Sensor:
        """The sensor: `image_size_px` pixels of pitch `pixel_pitch_mm`."""
        return Sensor(*self.image_size_px, self.pixel_pitch_mm)

    @property
    def lens(self) -> Lens:
        """The lens as the one lens type, of this module's tensors (w, U, d, θF, principal point, distortion:
        gradients reach the parameters through it)."""
        return Lens(self.w_mm, self.U_mm, self.d_mm, self.theta_F, self.sensor, self.principal_point_px,
                    self.distortion, self.phi, self.distortion_centre)

    @property
    def distortion_frame(self) -> torch.Tensor | None:
        """(3, 3) camera_from_lens in which D acts (about the lens axis: OpenCV's R(τx, τy) of θL and φ,
        `renderer.cameras.lens.opencv_tilt`), or None for the distortion about the principal point."""
        if self.distortion_centre != "lens_axis":
            return None
        return tilt_rotation(*opencv_tilt(self.theta_L, self.phi))

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
        """(..., 3) camera-frame points -> (..., 2) pixels: uv = c + (w / p) D(x / z, y / z) (`project_pinhole`).

        `with_distortion` False skips D (callers that know all coefficients are held at 0 save its cost)."""
        if not with_distortion:
            return project_pinhole(p_cam, self.focal_px, self.principal_point_px)
        return project_pinhole(p_cam, self.focal_px, self.principal_point_px, self.distortion, self.distortion_frame)

    def blur_camera(self, p_cam: torch.Tensor) -> torch.Tensor:
        """(..., 3) camera-frame points -> (...,) blur diameters in pixels (eq (2)/(4), `blur_model`)."""
        p_tilt = tilt_frame(p_cam, self.phi)
        b_mm = optics.blur_diameter(p_tilt, self.w_mm, self.U_mm, self.d_mm, self.theta_F, self.blur_model)
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

    def jacobian(self, X_world: torch.Tensor, with_blur: bool = True, with_distortion: bool = True,
                 names=None):
        """`forward` and its derivatives with respect to the stored parameters, in closed form (no autodiff).

        The chain rule of uv = c + (w / p) D(x / z, y / z) and b = blur(p_cam; w, U, d, θF) / p + offset with
        p_cam = R(rvec) X + T: the pose by `transforms.rotated_point_jacobian`, the distortion by
        `distortion.distort_jacobian` and `distort_coefficient_jacobian`, the blur by
        `optics.blur_diameter_jacobian`, each divided by the stored parametrisation (log w, 1/U in dioptres,
        d in cm, T in `length_scale_mm`, principal point in `pixel_scale_px`). Checked against autograd in
        tests/renderer/test_jacobians.py.

        Args:
            X_world: (N, 3) world points, mm.
            with_blur, with_distortion: as in `forward` (without blur, b and its rows are 0).
            names: stored parameter names to differentiate by (None: all of them, free or not).
        Returns:
            uv: (V, N, 2) pixels; b: (V, N) blur diameters, pixels;
            jac: {stored name: (V, N, 3, size)} derivatives of (u, v, b) with respect to the parameter; for
            `rvec` and `T_scaled` (size 3) those of view v's own pose (the other views' rows do not depend
            on it).
        """
        names = tuple(n for n, _ in self.named_parameters()) if names is None else tuple(names)
        with torch.no_grad():
            proj = self._projection_terms(X_world, with_distortion, tuple(n for n in _DIST if n in names))
            blur = self._blur_terms(proj, with_blur)
            jac = self._lens_columns(proj, blur, names)
            jac.update(self._pose_columns(proj, blur, names))
            jac.update(self._sensor_columns(proj, blur, names))
        return proj.uv, blur.b, jac

    def _projection_terms(self, X_world: torch.Tensor, with_distortion: bool, dist_names=()) -> _ProjectionTerms:
        """The projection part of `jacobian`: pixels, ∂(x_d)/∂p_cam and ∂(x_d)/∂k of the coefficients
        `dist_names` (stored names) for all views (no autograd)."""
        dt, dev = self.rvec.dtype, self.rvec.device
        X = torch.as_tensor(X_world, dtype=dt, device=dev)
        rvec = self.rvec.detach()
        p_rot = torch.einsum("vij,nj->vni", axis_angle_to_matrix(rvec), X)   # (V, N, 3)
        p_cam = p_rot + self.T_mm.detach()[:, None, :]
        z = p_cam[..., 2]
        iz = 1.0 / z
        xn = p_cam[..., :2] * iz[..., None]
        k = self.distortion.detach()
        F = float(self.focal_px.detach())
        axis = with_distortion and self.distortion_centre == "lens_axis"
        J_k = J_angles = dthL = None
        if axis:  # D about the lens axis: its frame turns with θL (so w, U, θF) and φ
            xd, J_xy, J_k, J_angles, dthL = self._lens_axis_jacobians(xn, k)
            dxd_dp = _through_perspective(J_xy, xn, iz)
        elif with_distortion:
            xd, J_xy, J_k = distort_with_jacobians(xn, k, tuple(n[len("dist_"):] for n in dist_names))
            dxd_dp = _through_perspective(J_xy, xn, iz)
        else:
            zero = torch.zeros_like(z)
            xd = xn
            dxd_dp = torch.stack([iz, zero, -xn[..., 0] * iz, zero, iz, -xn[..., 1] * iz], -1).reshape(z.shape + (2, 3))
        uv = self.principal_point_px.detach() + F * xd
        return _ProjectionTerms(rvec, p_rot, p_cam, xn, k, xd, dxd_dp, uv, F, with_distortion, axis, J_k,
                                tuple(dist_names), J_angles, dthL)

    def _blur_terms(self, proj: _ProjectionTerms, with_blur: bool) -> _BlurTerms:
        """The blur part of `jacobian`: b (V, N) pixels, ∂b/∂(w, U, d, θF), ∂b/∂φ and the rows ∂(u, v, b)/∂p_cam."""
        pitch = self.pixel_pitch_mm
        dxd_dp, F = proj.dxd_dp, proj.F
        if not with_blur:
            rows = torch.cat([F * dxd_dp, torch.zeros_like(dxd_dp[..., :1, :])], -2)
            return _BlurTerms(False, torch.zeros_like(proj.p_cam[..., 2]), None, None, rows)
        phi = self.phi.detach()
        p_tilt = tilt_frame(proj.p_cam, phi)  # the blur is a tilt about x in the frame turned by φ
        b_mm, Jb = optics.blur_diameter_jacobian(p_tilt, self.w_mm.detach(), self.U_mm.detach(),
                                                 self.d_mm.detach(), self.theta_F.detach(), self.blur_model)
        b = b_mm / pitch + self.blur_offset_px.detach()
        c, sn = torch.cos(phi), torch.sin(phi)
        jt = Jb[..., :3]  # ∂b/∂p_tilt; p_tilt = M p_cam, M = [[c, s, 0], [−s, c, 0], [0, 0, 1]]
        db_dp = torch.stack([jt[..., 0] * c - jt[..., 1] * sn, jt[..., 0] * sn + jt[..., 1] * c,
                             jt[..., 2]], -1)
        db_dphi = jt[..., 0] * p_tilt[..., 1] - jt[..., 1] * p_tilt[..., 0]  # ∂p_tilt/∂φ = (y_t, −x_t, 0)
        rows = torch.cat([F * dxd_dp, db_dp[..., None, :] / pitch], -2)    # ∂(u, v, b)/∂p_cam
        return _BlurTerms(True, b, Jb[..., 3:], db_dphi, rows)

    def _lens_columns(self, proj: _ProjectionTerms, blur: _BlurTerms, names) -> dict:
        """`jacobian`'s columns of log_w_mm, inv_U_per_m, d_scaled and theta_F among `names`."""
        lens_names = ("log_w_mm", "inv_U_per_m", "d_scaled", "theta_F")
        if not any(n in names for n in lens_names):
            return {}
        # ∂/∂(w, U, d, θF), then by the stored parametrisation w = exp(log_w), U = 1000 / inv_U,
        # d = 10 |d_scaled|
        pitch = self.pixel_pitch_mm
        w, U = self.w_mm.detach(), self.U_mm.detach()
        lens = torch.zeros(proj.p_cam.shape[:-1] + (3, 4), dtype=proj.p_cam.dtype, device=proj.p_cam.device)
        lens[..., :2, 0] = proj.xd / pitch
        if blur.with_blur:
            lens[..., 2, :] = blur.db_dlens / pitch
        lens = lens * lens_from_stored_jacobian(w, U, self.d_scaled.detach())
        if proj.axis:  # through θL(w, 1/U, θF) of the distortion's frame, already by the stored parameters
            for i, g in zip((0, 1, 3), proj.dthL):
                lens[..., :2, i] += proj.F * proj.J_angles[0] * g
        return {n: lens[..., i:i + 1] for i, n in enumerate(lens_names) if n in names}

    def _pose_columns(self, proj: _ProjectionTerms, blur: _BlurTerms, names) -> dict:
        """`jacobian`'s columns of rvec and T_scaled among `names` (each view's own pose)."""
        jac = {}
        if "rvec" in names:
            jac["rvec"] = rotated_point_jacobian(proj.rvec[:, None, :], proj.p_rot, blur.rows)
        if "T_scaled" in names:
            jac["T_scaled"] = blur.rows * self.length_scale_mm
        return jac

    def _sensor_columns(self, proj: _ProjectionTerms, blur: _BlurTerms, names) -> dict:
        """`jacobian`'s columns of pp_scaled, phi, blur_offset_px and the distortion coefficients among `names`."""
        jac = {}
        shape, dt, dev = proj.p_cam.shape[:-1], proj.p_cam.dtype, proj.p_cam.device
        if "pp_scaled" in names:
            pp = torch.zeros(shape + (3, 2), dtype=dt, device=dev)
            pp[..., 0, 0] = self.pixel_scale_px
            pp[..., 1, 1] = self.pixel_scale_px
            jac["pp_scaled"] = pp
        if "phi" in names:
            dphi = torch.zeros(shape + (3, 1), dtype=dt, device=dev)
            if blur.with_blur:
                dphi[..., 2, 0] = blur.db_dphi / self.pixel_pitch_mm
            if proj.axis:
                dphi[..., :2, 0] = proj.F * proj.J_angles[1]
            jac["phi"] = dphi
        if "blur_offset_px" in names:
            off = torch.zeros(shape + (3, 1), dtype=dt, device=dev)
            if blur.with_blur:
                off[..., 2, 0] = 1.0
            jac["blur_offset_px"] = off
        dist_names = proj.dist_names
        if dist_names:  # side by side in one tensor, in `_DIST`'s order
            dk = torch.zeros(shape + (3, len(dist_names)), dtype=dt, device=dev)
            if proj.axis:
                dk[..., :2, :] = proj.F * proj.J_k[..., [_DIST.index(n) for n in dist_names]]
            elif proj.with_distortion:
                dk[..., :2, :] = proj.F * proj.J_k
            for i, n in enumerate(dist_names):
                jac[n] = dk[..., i:i + 1]
        return jac

    def _lens_axis_jacobians(self, xn: torch.Tensor, k: torch.Tensor):
        """D about the lens axis at ideal normalised points xn with its derivatives (no autograd): x_d, ∂x_d/∂xn,
        ∂x_d/∂k, [∂x_d/∂θL, ∂x_d/∂φ], and ∂θL/∂(log w, 1/U in dioptres, θF) (tan θL = w tan θF u / (1 + w u),
        u = 1/U in 1/mm: finite at focus at infinity, where θL = 0)."""
        theta_L, phi = self.theta_L.detach(), self.phi.detach()
        R = tilt_rotation(*opencv_tilt(theta_L, phi))
        dR = torch.func.jacfwd(lambda a, b: tilt_rotation(*opencv_tilt(a, b)), argnums=(0, 1))(theta_L, phi)
        xd, J_xy, J_k, J_angles = distort_about_axis_jacobians(xn, k, R, dR)
        w, u, tF = self.w_mm.detach(), self.inv_U_per_m.detach() / 1000.0, self.theta_F.detach()
        den = 1 + w * u
        t = w * torch.tan(tF) * u / den
        c = 1 / (1 + t * t)
        dthL = (c * torch.tan(tF) * u * w / (den * den),             # by log w (∂/∂w times w)
                c * w * torch.tan(tF) / (den * den) / 1000.0,         # by 1/U in dioptres
                c * w * u / (den * torch.cos(tF) ** 2))               # by θF
        return xd, J_xy, J_k, J_angles, dthL

    # --- rendering -----------------------------------------------------------------------------------------
    def view_camera(self, view: int) -> ThinLensCamera:
        """The renderer's thin-lens camera of one view, built from this module's tensors.

        Its w, U, d, θF, pose (R, T of the view), principal point and distortion coefficients are the module's
        parameters (through their physical values, not copies), so an image rendered with it
        (`renderer.render`, `integrator.trace` of its rays) has gradients with respect to every free parameter.
        It projects world points exactly as `project(X, view)` (its chief rays; `ThinLensCamera.project`), and
        traces each pixel through its undistorted position. Lengths in mm: render scenes in mm.

        Args:
            view: view index, 0 ≤ view < n_views.
        Returns:
            ThinLensCamera with image size `image_size_px`. Focus at infinity (1/U = 0) renders, but has no
            gradient with respect to 1/U there (U = 1000 / inv_U_per_m is infinite).
        """
        if not -self.n_views <= int(view) < self.n_views:
            raise IndexError(f"view: expected 0 <= view < {self.n_views}, got {view}")
        return ThinLensCamera.from_calibration(self.lens, self.R[view], self.T_mm[view])

    # --- convenience -------------------------------------------------------------------------------------
    def copy(self) -> "LensCamera":
        """An independent copy with the same free/frozen state: the parameters and buffers cloned (the same
        numbers), the module's other state (plain values, empty hook tables) copied one level deep: the same copy as
        `copy.deepcopy` in less than half its time (a calibration copies its camera a few hundred times)."""
        if self._modules or any(p is not None and p.grad is not None for p in self._parameters.values()):
            return copy.deepcopy(self)  # submodules or gradients: what deepcopy copies beyond this
        out = self.__class__.__new__(self.__class__)
        for k, v in self.__dict__.items():
            out.__dict__[k] = v.copy() if isinstance(v, (dict, set)) else v
        P = torch.nn.Parameter
        with torch.no_grad():
            out._parameters = {n: None if p is None else P(p.clone(), requires_grad=p.requires_grad)
                               for n, p in self._parameters.items()}
            out._buffers = {n: None if b is None else b.clone() for n, b in self._buffers.items()}
        return out

    def summary(self) -> dict:
        """Plain floats of the lens state (mm and degrees): the lens's `Lens.record()` and the module's own values."""
        with torch.no_grad():
            return {
                **self.lens.record(), "f_mm": float(self.f_mm),
                "theta_L_paper_deg": math.degrees(float(self.theta_L_paper)),
                "principal_point_px": [float(v) for v in self.principal_point_px],
                "distortion": [float(v) for v in self.distortion],
                "distortion_centre": self.distortion_centre,
                "blur_offset_px": float(self.blur_offset_px),
            }

    @classmethod
    def from_lens(cls, lens: Lens, n_views: int, **kwargs) -> "LensCamera":
        """The fitted module of a `Lens` (with its sensor), V views; `kwargs` as the constructor's (R, T_mm,
        rvec, blur_model, dtype …). The lens's principal point and distortion become the module's."""
        if lens.sensor is None:
            raise ValueError("lens.sensor: a fitted camera needs the lens's sensor (Sensor(W, H, pitch))")
        kwargs.setdefault("principal_point_px", lens.principal_point_px)
        kwargs.setdefault("distortion", lens.distortion)
        kwargs.setdefault("phi", float(lens.phi))
        kwargs.setdefault("distortion_centre", lens.distortion_centre)
        return cls(n_views, lens.sensor.size_px, lens.sensor.pixel_pitch, float(lens.w), float(lens.U),
                   float(lens.d), float(lens.theta_F), **kwargs)

    @classmethod
    def from_tilted_lens(cls, n_views: int, image_size_px, pixel_pitch_mm: float, w_mm: float, f_mm: float,
                         d_mm: float, theta_L: float, **kwargs) -> "LensCamera":
        """A camera whose thin lens (focal f, sensor at w) is tilted by θL about its centre (`Lens.from_tilt`:
        U and θF follow from the hinge and Scheimpflug rules, so U moves with the tilt)."""
        sensor = Sensor(int(image_size_px[0]), int(image_size_px[1]), float(pixel_pitch_mm))
        return cls.from_lens(Lens.from_tilt(w_mm, f_mm, theta_L, d_mm, sensor=sensor), n_views, **kwargs)

