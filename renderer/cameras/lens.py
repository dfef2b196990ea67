"""The one thin lens: its state (w, U, d, θF), its sensor, principal point and distortion, in one value.

    Lens(w, U, d, theta_F=0, sensor=None, principal_point_px=None, distortion=None, phi=0,
         distortion_centre="sensor")
    Lens.from_tilt(w, f, theta_L, d)        the hinge rule: a lens of focal length f tilted by θL about its centre
    Lens.from_theta_L(w, U, d, theta_L)     U kept, θF from the exact Scheimpflug rule
    Lens.paper()                            the tilt-lens paper's camera (EOS 6D, TS-E 45 mm, stage-1 values)
    Lens.focus_through(points, w=… or f=…, d=…)  the lens setting that focuses on three points (U, θF, φ)

Every camera that has a thin lens takes one: the renderer's `ThinLensCamera` (distributed ray tracing), the
fitted `LensCamera` (its `lens` is a `Lens` of its tensors, so gradients reach them), the Mitsuba sensor, the
fused path, tiltfit's synthetic captures, the experiments and the photometric fit. Only this class holds the
lens parameters; the others hold a `Lens` (tests/test_one_lens.py).

Conventions (docs/conventions.md): camera frame x right, y down, z forward, lens centre at the origin; the
sensor at z = −w; the plane of focus z = U + y_φ tan θF with y_φ = y cos φ − x sin φ (U = math.inf: focus at
infinity, |θF| < 90°): the lens and the plane of focus tilt about the axis (cos φ, sin φ, 0) of the lens plane,
φ = 0 the camera x axis (the papers' and OpenCV's only case), φ = 90° the y axis (a tilt-shift lens's
rotation ring turned by a quarter). Every relation of a tilt about x holds in the frame turned by φ about the
optical axis.

The distortion is centred on the principal point (`distortion_centre="sensor"`, the model of every calibration
library for an untilted lens) or on the lens's own axis (`"lens_axis"`: a real lens's distortion is symmetric
about its axis, which a tilt turns away from the perpendicular foot of the lens centre; it meets the sensor
w tan θL from the principal point across the tilt axis). About the lens axis, D acts in the lens frame
(`distortion_frame`, `renderer.cameras.distortion.distort_about_axis`): OpenCV's tilted model
(CALIB_TILTED_MODEL) with τ from θL and φ (`opencv_tilt`). For θL = 0 both centres are the same model. Lengths in scene units (mm for a real camera), angles in radians. w, U, d, θF may be Python
floats or 0-dim tensors (tensors keep their graph; only numbers are checked).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch

from . import optics
from renderer.core.params import DISTORTION_CENTRES  # noqa: F401 - where a lens's distortion is centred (`Lens.distortion_centre`)

#: The paper's camera: Canon EOS 6D (5472 × 3648, 6.54 µm pixels) with the TS-E 45 mm at f/2.8, stage-1 estimates.
PAPER_W_MM, PAPER_U_MM, PAPER_D_MM = 55.39, 618.4, 18.81


@dataclass(frozen=True)
class Sensor:
    """A sensor of W × H pixels of pitch p (scene units; mm for a real camera).

    Pixel (0, 0) is the centre of the top-left pixel, so the image centre is ((W − 1)/2, (H − 1)/2).
    """

    width_px: int
    height_px: int
    pixel_pitch: float

    def __post_init__(self):
        for name in ("width_px", "height_px"):
            v = getattr(self, name)
            if not (isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v >= 1):
                raise ValueError(f"{name}: expected a positive whole number of pixels, got {v!r}")
        if not (math.isfinite(float(self.pixel_pitch)) and float(self.pixel_pitch) > 0):
            raise ValueError(f"pixel_pitch: expected a positive length, got {self.pixel_pitch!r}")

    @property
    def size_px(self) -> tuple[int, int]:
        return int(self.width_px), int(self.height_px)

    @property
    def size(self) -> tuple[float, float]:
        """(width, height) of the sensor, scene units."""
        return self.width_px * self.pixel_pitch, self.height_px * self.pixel_pitch

    @property
    def center_px(self) -> tuple[float, float]:
        """The image centre ((W − 1)/2, (H − 1)/2), pixels: the default principal point."""
        from .projection import image_centre_px

        return image_centre_px(self.width_px, self.height_px)

    def binned(self, factor: int) -> "Sensor":
        """The sensor read out with `factor` × `factor` pixels binned, cropped to whole binned pixels."""
        if not (isinstance(factor, int) and factor >= 1):
            raise ValueError(f"factor: expected a positive integer, got {factor!r}")
        w, h = self.width_px // factor, self.height_px // factor
        if w < 2 or h < 2:
            raise ValueError(f"factor: binning by {factor} leaves a {w}x{h} image")
        return Sensor(w, h, self.pixel_pitch * factor)


#: Canon EOS 6D: full frame, 5472 × 3648, 6.54 µm pixels.
EOS_6D = Sensor(5472, 3648, 0.00654)


def _number(v) -> bool:
    return not isinstance(v, torch.Tensor)


def _float(v) -> float:
    """A number or a 0-dim tensor (graph or not) as a Python float."""
    return float(v.detach()) if isinstance(v, torch.Tensor) else float(v)


@dataclass(frozen=True)
class Lens:
    """A thin lens with a (possibly) tilted plane of focus, its sensor, principal point and distortion.

    Attributes:
        w: lens centre to sensor (effective focal length).
        U: lens centre to the plane of focus along the optical axis (math.inf: focus at infinity).
        d: effective aperture diameter (0: a pinhole).
        theta_F: tilt of the plane of focus z = U + y tan θF about the camera x axis, radians.
        sensor: the `Sensor` (None for a scene-file camera, whose screen is given in scene units).
        principal_point_px: (cx, cy) where the optical axis meets the image [the sensor's centre].
        distortion: None or up to 8 Brown–Conrady coefficients in OpenCV's order (k1, k2, p1, p2, k3, k4, k5,
            k6), about the principal point.
        phi: direction of the tilt axis in the lens plane, radians from the camera x axis towards y [0].
        distortion_centre: "sensor" (about the principal point) or "lens_axis" (in the lens's own frame, about
            its axis; module docstring) ["sensor"].
    """

    w: float
    U: float
    d: float
    theta_F: float = 0.0
    sensor: Sensor | None = None
    principal_point_px: tuple[float, float] | None = None
    distortion: tuple[float, ...] | None = None
    phi: float = 0.0
    distortion_centre: str = "sensor"

    def __post_init__(self):
        if _number(self.w) and not (math.isfinite(self.w) and self.w > 0):
            raise ValueError(f"w: expected a positive finite length, got {self.w!r}")
        if _number(self.U) and not (self.U > 0):
            raise ValueError(f"U: expected a positive length or inf, got {self.U!r}")
        if _number(self.d) and not (math.isfinite(self.d) and self.d >= 0):
            raise ValueError(f"d: expected an aperture diameter >= 0, got {self.d!r}")
        if _number(self.theta_F) and not abs(self.theta_F) < math.pi / 2:
            raise ValueError(f"theta_F: expected |θF| < 90°, got {math.degrees(self.theta_F)!r}°")
        if _number(self.phi) and not math.isfinite(self.phi):
            raise ValueError(f"phi: expected a finite angle, got {self.phi!r}")
        if self.distortion_centre not in DISTORTION_CENTRES:
            raise ValueError(f"distortion_centre: expected one of {DISTORTION_CENTRES}, got {self.distortion_centre!r}")

    # ------------------------------------------------------------------ constructors

    @classmethod
    def from_theta_L(cls, w, U, d, theta_L, **kw) -> "Lens":
        """The lens of focus distance U tilted by θL (radians): θF from the exact Scheimpflug rule
        tan θF = (U + w) tan θL / w."""
        theta_F = optics.theta_F_from_theta_L(theta_L, w, U)
        return cls(w, U, d, _same_kind(theta_F, w, U, theta_L), **kw)

    @classmethod
    def from_tilt(cls, w, f, theta_L, d, **kw) -> "Lens":
        """A lens of focal length f with the sensor at w, tilted by θL about its centre (radians): the hinge
        rule U = f w / (w cos θL − f) places the plane of focus, the Scheimpflug rule tilts it."""
        if all(_number(v) for v in (w, f, theta_L)) and not 0 < f < w * math.cos(theta_L):
            raise ValueError(f"f: expected 0 < f < w cos θL = {w * math.cos(theta_L):.6g} for a real plane of "
                             f"focus, got {f!r}")
        U = _same_kind(optics.focus_distance_tilted(w, f, theta_L), w, f, theta_L)
        return cls.from_theta_L(w, U, d, theta_L, **kw)

    @classmethod
    def focus_through(cls, points_cam, d, *, w=None, f=None, **kw) -> "Lens":
        """The lens whose plane of focus passes through three points (camera frame), as a photographer sets a
        tilt-shift lens (RenderMan's PxrCamera focuses the same way): U, θF and the tilt axis φ from the plane
        z = U + g_x x + g_y y through the points (tan θF = |g|, φ = atan2(−g_x, g_y), θF signed so that
        |φ| ≤ 90°), θL by the exact Scheimpflug rule.

        Give the sensor distance `w`, or the focal length `f` (then w is the one where the hinge rule
        U = f w / (w cos θL − f) holds for this plane: focusing moves the lens).

        Raises:
            ValueError naming `points` when no lens setting can: the points are collinear (no single plane), the
            plane is parallel to the optical axis or passes through or behind the lens centre (U ≤ 0); naming
            `f` when no sensor distance gives that focal length.
        """
        p = np.asarray(points_cam, dtype=np.float64)
        if p.shape != (3, 3) or not np.isfinite(p).all():
            raise ValueError(f"points: expected three finite points (x, y, z), got shape {p.shape}")
        if (w is None) == (f is None):
            raise ValueError("focus_through: give exactly one of w (sensor distance) and f (focal length)")
        n = np.cross(p[1] - p[0], p[2] - p[0])
        size = max(np.linalg.norm(p[1] - p[0]), np.linalg.norm(p[2] - p[0]), 1e-300)
        if np.linalg.norm(n) <= 1e-9 * size * size:
            raise ValueError("points: the three points are collinear; no single plane of focus passes through them")
        n = n / np.linalg.norm(n)
        if abs(n[2]) < 1e-9:
            raise ValueError("points: their plane is parallel to the optical axis; no plane of focus can hold it")
        U = float(n @ p[0] / n[2])
        if not U > 0:
            raise ValueError(f"points: their plane meets the optical axis at z = {U:.6g}, through or behind the lens "
                             "centre; a plane of focus lies in front of it")
        gx, gy = -n[0] / n[2], -n[1] / n[2]
        tan_F, phi = math.hypot(gx, gy), math.atan2(-gx, gy)
        if phi > math.pi / 2 or phi <= -math.pi / 2:  # the same plane with the opposite tilt about a turned axis
            phi, tan_F = phi - math.copysign(math.pi, phi), -tan_F
        if tan_F == 0:
            phi = 0.0
        theta_F = math.atan(tan_F)
        if w is None:
            w = _sensor_distance_for(f, U, theta_F)
        return cls(float(w), U, d, theta_F, phi=phi, **kw)

    @classmethod
    def paper(cls, sensor: Sensor | None = EOS_6D) -> "Lens":
        """The tilt-lens paper's camera: Canon EOS 6D with the TS-E 45 mm at f/2.8, stage-1 estimates
        w = 55.39, U = 618.4, d = 18.81 mm, untilted."""
        return cls(PAPER_W_MM, PAPER_U_MM, PAPER_D_MM, 0.0, sensor)

    def with_(self, **changes) -> "Lens":
        """A copy with some fields changed (`dataclasses.replace`)."""
        return replace(self, **changes)

    # ------------------------------------------------------------------ derived values

    @property
    def inv_U(self):
        """1 / U (0 for focus at infinity)."""
        return 1.0 / self.U if _number(self.U) else torch.reciprocal(self.U)

    @property
    def theta_L(self):
        """Exact lens tilt, radians (tan θL = w tan θF / (U + w)); a float when the parameters are floats."""
        return _same_kind(optics.theta_L_from_theta_F(self.theta_F, self.w, self.U), self.w, self.U, self.theta_F)

    @property
    def f(self):
        """Focal length of the thin lens in this state, f = U w cos θL / (U + w) (hinge rule)."""
        return _same_kind(optics.focal_length(self.w, self.U, self.theta_L), self.w, self.U, self.theta_F)

    def to_tilt_frame(self, p_cam):
        """(..., 3) camera-frame points in the frame turned by φ about the optical axis, where the tilt is about
        x: (x cos φ + y sin φ, y_φ, z) with y_φ = y cos φ − x sin φ (the identity for φ = 0; tensors keep
        their graph)."""
        if _number(self.phi) and self.phi == 0:
            return p_cam
        return tilt_frame(torch.as_tensor(p_cam), self.phi)

    def focus_plane(self) -> tuple[np.ndarray, float]:
        """The plane of focus as (m, U) with m · p = U for its points p (camera frame): m = (−g_x, −g_y, 1),
        z = U + g_x x + g_y y, g_x = −tan θF sin φ, g_y = tan θF cos φ."""
        t, phi = math.tan(_float(self.theta_F)), _float(self.phi)
        return np.array([t * math.sin(phi), -t * math.cos(phi), 1.0]), _float(self.U)

    @property
    def center_px(self) -> tuple[float, float]:
        """The principal point (cx, cy), pixels: given, else the sensor's centre."""
        if self.principal_point_px is not None:
            return self.principal_point_px
        return self._sensor("center_px").center_px

    @property
    def focal_px(self):
        """w / p: the focal length in pixels."""
        return self.w / self._sensor("focal_px").pixel_pitch

    @property
    def K(self) -> np.ndarray:
        """(3, 3) pixel-from-normalised-coordinates matrix [[w/p, 0, cx], [0, w/p, cy], [0, 0, 1]]."""
        from .projection import camera_matrix

        return camera_matrix(_float(self.focal_px), tuple(_float(c) for c in self.center_px))

    def binned(self, factor: int) -> "Lens":
        """The same optics read out with `factor` × `factor` pixels binned (image `factor` times smaller)."""
        pp = self.principal_point_px
        if pp is not None:
            pp = _scaled_px(pp, 1.0 / factor)
        return replace(self, sensor=self._sensor("binned").binned(factor), principal_point_px=pp)

    def resampled(self, width_px: int, height_px: int) -> "Lens":
        """The same optics read out as a `width_px` × `height_px` image of the same field of view (pixels
        W / width_px times larger; the caller keeps the aspect ratio): the principal point scaled with the pixels."""
        sensor = self._sensor("resampled")
        s = width_px / sensor.width_px
        return replace(self, sensor=Sensor(int(width_px), int(height_px), sensor.pixel_pitch / s),
                       principal_point_px=_scaled_px(tuple(_float(c) for c in self.center_px), s))

    def cropped(self, x0: int, y0: int, width_px: int, height_px: int) -> "Lens":
        """The same optics read out only on the window of pixels x0 ≤ x < x0 + width, y0 ≤ y < y0 + height:
        pixel (x, y) of the cropped lens is pixel (x0 + x, y0 + y) of this one (the principal point moves by
        the window's origin; the window may reach past the sensor's edge)."""
        if not all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in (x0, y0, width_px, height_px)):
            raise ValueError(f"window: expected whole pixels, got {(x0, y0, width_px, height_px)!r}")
        sensor = self._sensor("cropped")
        cx, cy = self.center_px
        return replace(self, sensor=Sensor(int(width_px), int(height_px), sensor.pixel_pitch),
                       principal_point_px=(cx - int(x0), cy - int(y0)))

    # ------------------------------------------------------------------ closed forms

    def project(self, p_cam):
        """(..., 3) camera-frame points -> (..., 2) pixels: the chief ray's pinhole projection at w with the
        distortion (`renderer.cameras.projection.project_pinhole`). numpy in, numpy out; tensors keep their
        graph."""
        from .projection import project_pinhole

        if self.distortion is None or not any(_float(k) != 0 for k in self.distortion):
            if isinstance(p_cam, torch.Tensor):
                return project_pinhole(p_cam, self.focal_px, self.center_px)
            return project_pinhole(np.asarray(p_cam, dtype=np.float64), _float(self.focal_px), self.center_px)
        frame = self.distortion_frame
        if isinstance(p_cam, torch.Tensor):
            return project_pinhole(p_cam, self.focal_px, self.center_px, self.distortion, frame)
        p = torch.as_tensor(np.asarray(p_cam, dtype=np.float64))
        return project_pinhole(p, self.focal_px, self.center_px, self.distortion, frame).numpy()

    def unproject(self, uv_px: torch.Tensor) -> torch.Tensor:
        """(..., 2) pixels -> (..., 3) unit camera-frame directions that `project` maps to them: the inverse of the
        distortion (Newton's method, about the principal point or the lens axis); NaN where it cannot be inverted
        (no root, or one that does not project back within 1e-3 px). Plain-number lens; float64 tensors."""
        from .distortion import undistort_about_axis
        from .projection import normalised_from_pixels

        f, c = _float(self.focal_px), tuple(_float(x) for x in self.center_px)
        xy = undistort_about_axis(normalised_from_pixels(uv_px, f, c), self.distortion or (0.0,), self.distortion_frame)
        v = torch.cat([xy, torch.ones_like(xy[..., :1])], -1)
        ok = torch.isfinite(xy).all(-1) & ((self.project(v) - uv_px).norm(dim=-1) < 1e-3)
        v = v / v.norm(dim=-1, keepdim=True)
        return torch.where(ok[..., None], v, torch.full_like(v, math.nan))

    def detached(self) -> "Lens":
        """The same lens with tensor fields (a fitted camera's) as plain floats."""
        dist = None if self.distortion is None else tuple(_float(k) for k in self.distortion)
        pp = None if self.principal_point_px is None else tuple(_float(c) for c in self.principal_point_px)
        return replace(self, w=_float(self.w), U=_float(self.U), d=_float(self.d), theta_F=_float(self.theta_F),
                       principal_point_px=pp, distortion=dist, phi=_float(self.phi))

    @property
    def lens_axis(self):
        """(3,) the lens axis, a unit vector in the camera frame pointing forward: the lens plane's normal
        (sin θL sin φ, −sin θL cos φ, cos θL) (a tensor where θL or φ is one)."""
        return lens_axis(self.theta_L, self.phi)

    @property
    def distortion_frame(self):
        """The (3, 3) rotation camera_from_lens in which the distortion acts (`distortion.distort_about_axis`):
        OpenCV's tilt R(τx, τy) of `opencv_tilt`, its z axis the lens axis; None when the distortion is
        about the principal point (`distortion_centre` "sensor", or θL a plain 0)."""
        if self.distortion_centre != "lens_axis":
            return None
        theta_L = self.theta_L
        if _number(theta_L) and _number(self.phi) and theta_L == 0:
            return None
        return tilt_rotation(*opencv_tilt(theta_L, self.phi))

    @property
    def lens_axis_px(self) -> tuple[float, float]:
        """Where the lens axis meets the image (pixels): the principal point moved by w tan θL across the
        tilt axis, c + (w / p) (n_x / n_z, n_y / n_z); OpenCV's principal point for this lens."""
        n = np.asarray([_float(v) for v in self.lens_axis])
        f = _float(self.focal_px)
        cx, cy = (_float(c) for c in self.center_px)
        return cx + f * n[0] / n[2], cy + f * n[1] / n[2]

    def blur_px(self, p_cam) -> np.ndarray:
        """(..., 3) camera-frame points -> (...,) blur-disc diameters, pixels: the exact thin-lens value for a lens
        tilted about its centre (`renderer.cameras.optics.blur_diameter_exact`, the equivalent-area diameter of the
        blur ellipse); for θF = 0 it is the paper's eq (2)."""
        p = self.to_tilt_frame(torch.as_tensor(np.asarray(p_cam, dtype=np.float64)))
        b = optics.blur_diameter_exact(p, self.w, self.U, self.d, self.theta_F)
        return b.numpy() / self._sensor("blur_px").pixel_pitch

    def scene_keys(self) -> dict:
        """The scene file's `thin_lens` camera keys of this lens (docs/file_formats.md): w, U, d, theta_F_deg,
        and sensor_size and principal_point_px when it has a sensor / principal point; numbers as plain floats."""
        keys = {"type": "thin_lens", "w": _float(self.w), "U": _float(self.U), "d": _float(self.d),
                "theta_F_deg": math.degrees(_float(self.theta_F))}
        if _float(self.phi) != 0:
            keys["tilt_axis_deg"] = math.degrees(_float(self.phi))
        if self.sensor is not None:
            keys["sensor_size"] = list(self.sensor.size)
        if self.principal_point_px is not None:
            keys["principal_point_px"] = [_float(c) for c in self.principal_point_px]
        return keys

    def record(self) -> dict:
        """w, U, d, θL and θF (degrees) as plain numbers: for tables and run records."""
        return {"w_mm": _float(self.w), "U_mm": _float(self.U), "d_mm": _float(self.d),
                "theta_L_deg": math.degrees(_float(self.theta_L)), "theta_F_deg": math.degrees(_float(self.theta_F)),
                "tilt_axis_deg": math.degrees(_float(self.phi))}

    def _sensor(self, what: str) -> Sensor:
        if self.sensor is None:
            raise ValueError(f"Lens.{what}: this lens has no sensor (give Lens(..., sensor=Sensor(W, H, p)))")
        return self.sensor


def lens_axis(theta_L, phi):
    """(3,) the axis of a lens tilted by θL about the axis at φ (camera frame, forward): the normal of its plane,
    (sin θL sin φ, −sin θL cos φ, cos θL); numpy for numbers, a tensor (graph kept) where either is one."""
    if _number(theta_L) and _number(phi):
        return np.array([math.sin(theta_L) * math.sin(phi), -math.sin(theta_L) * math.cos(phi), math.cos(theta_L)])
    t, p = (torch.as_tensor(v, dtype=torch.float64) if _number(v) else v for v in (theta_L, phi))
    p = p.to(t)
    return torch.stack([torch.sin(t) * torch.sin(p), -torch.sin(t) * torch.cos(p), torch.cos(t)])


def opencv_tilt(theta_L, phi):
    """OpenCV's tilt angles (τx, τy) of the tilted model (CALIB_TILTED_MODEL) for a lens tilted by θL about the
    axis at φ: R(τx, τy) = R_y(τy) R_x(τx) turns the lens frame (OpenCV's camera frame, z the lens axis n)
    into the sensor's, so its third column is n: τx = asin(n_y), τy = atan2(−n_x, n_z). Radians; tensors keep
    their graph. φ = 0 gives (−θL, 0)."""
    n = lens_axis(theta_L, phi)
    if isinstance(n, np.ndarray):
        return math.asin(n[1]), math.atan2(-n[0], n[2])
    return torch.asin(n[1]), torch.atan2(-n[0], n[2])


def lens_tilt_from_opencv(tau_x: float, tau_y: float) -> tuple[float, float]:
    """(θL, φ), radians, of OpenCV's (τx, τy) (the inverse of `opencv_tilt`): n = R(τx, τy) ẑ =
    (−sin τy cos τx, sin τx, cos τy cos τx), θL = acos(n_z) signed and φ chosen with |φ| ≤ 90° (as
    `Lens.focus_through` does), φ = 0 for an untilted lens."""
    n = tilt_rotation(tau_x, tau_y)[:, 2]
    s = math.hypot(n[0], n[1])
    if s == 0:
        return 0.0, 0.0
    theta_L, phi = math.atan2(s, n[2]), math.atan2(n[0], -n[1])
    if phi > math.pi / 2 or phi <= -math.pi / 2:  # the same axis with the opposite tilt
        phi, theta_L = phi - math.copysign(math.pi, phi), -theta_L
    return theta_L, phi


def tilt_rotation(tau_x, tau_y):
    """OpenCV's tilt rotation R(τx, τy) = R_y(τy) R_x(τx) (calib3d's computeTiltProjectionMatrix, matRotXY),
    (3, 3): numpy for numbers, a tensor (graph kept) where either angle is one."""
    if _number(tau_x) and _number(tau_y):
        cx, sx, cy, sy = math.cos(tau_x), math.sin(tau_x), math.cos(tau_y), math.sin(tau_y)
        return np.array([[cy, sy * sx, -sy * cx], [0.0, cx, sx], [sy, -cy * sx, cy * cx]])
    tx, ty = (torch.as_tensor(v, dtype=torch.float64) if _number(v) else v for v in (tau_x, tau_y))
    ty = ty.to(tx)
    cx, sx, cy, sy = torch.cos(tx), torch.sin(tx), torch.cos(ty), torch.sin(ty)
    zero = torch.zeros_like(cx)
    return torch.stack([torch.stack([cy, sy * sx, -sy * cx]), torch.stack([zero, cx, sx]),
                        torch.stack([sy, -cy * sx, cy * cx])])


def tilt_frame(p_cam: torch.Tensor, phi) -> torch.Tensor:
    """(..., 3) camera-frame points turned by −φ about the optical axis: (x cos φ + y sin φ, y_φ, z) with
    y_φ = y cos φ − x sin φ, the frame in which a tilt about the axis (cos φ, sin φ, 0) is a tilt about x."""
    phi = torch.as_tensor(phi, dtype=p_cam.dtype, device=p_cam.device)
    c, s = torch.cos(phi), torch.sin(phi)
    x, y, z = p_cam.unbind(-1)
    return torch.stack([x * c + y * s, y * c - x * s, z], -1)


def _scaled_px(point_px, s: float) -> tuple:
    """Pixel coordinates (pixel centres at integers) of an image resampled by `s` (s < 1: coarser pixels): the pixel
    edges, at c + 0.5, scale."""
    return tuple((c + 0.5) * s - 0.5 for c in point_px)


def _sensor_distance_for(f: float, U: float, theta_F: float) -> float:
    """The sensor distance w at which a lens of focal length f focuses on the plane (U, θF): the root of
    U w cos θL / (U + w) = f with tan θL = w tan θF / (U + w) (hinge and Scheimpflug rules), by bisection (the
    left side grows with w from 0 towards U cos θF)."""
    if not (math.isfinite(f) and f > 0):
        raise ValueError(f"f: expected a positive focal length, got {f!r}")

    def focal(w):
        return float(optics.focal_length(w, U, optics.theta_L_from_theta_F(theta_F, w, U)))

    lo, hi = 0.0, max(f, 1.0)
    while focal(hi) < f:
        hi *= 2
        if hi > 1e12 * max(f, U):
            raise ValueError(f"f: a lens of focal length {f:g} cannot focus on this plane (U = {U:.6g}); "
                             "it needs f < U cos θF")
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if focal(mid) < f else (lo, mid)
    return 0.5 * (lo + hi)


def _same_kind(value, *params):
    """`value` as a Python float when every parameter is a plain number, else the tensor (keeps its graph)."""
    if any(isinstance(p, torch.Tensor) for p in params):
        return value
    return float(value)
