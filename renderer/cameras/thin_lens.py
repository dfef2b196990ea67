"""Thin lens with a tilted lens and plane of focus: distributed ray tracing (Cook 1984; tilt-lens paper 3.3).

| key | unit | default | meaning |
|---|---|---|---|
| `w` | scene | required | lens centre to sensor (effective focal length) |
| `U` | scene | — | lens centre to the plane of focus along the optical axis (give `U` or `f`) |
| `f` | scene | — | focal length instead of `U`; U then follows from the hinge rule for the lens tilt |
| `d` | scene | required | aperture diameter (0: a pinhole) |
| `sensor_size` | scene | required | [width, height] of the sensor at distance w |
| `theta_F_deg` | degrees | 0 | tilt of the plane of focus z = U + y tan θF about the camera x axis, \\|θF\\| < 90 |
| `theta_L_deg` | degrees | — | lens tilt instead of `theta_F_deg`, converted exactly (`renderer.cameras.optics`) |
| `principal_point_px` | pixels | centre | (cx, cy) where the optical axis meets the image |
| `tilt_axis_deg` | degrees | 0 | direction φ of the tilt axis from the camera x axis (a tilt-shift lens's rotation), \\|φ\\| ≤ 360 |
| `focus_points` | scene | — | three world points the plane of focus passes through, instead of U/f and the tilts |

Geometry (camera frame x right, y down, z forward; lens centre at the origin):
- The sensor is at z = −w behind the lens. The image is read out upright: pixel (x, y) maps through
  `Screen` (made from the lens: its w and principal point) to (x_s, y_s) (sensor size at distance w), its sensor point is P = (−x_s, −y_s, −w) and its
  chief ray, through the lens centre, has direction c = (x_s, y_s, w) -- the same ray as a pinhole with
  screen distance w and the same screen size. So world points land on the same pixels as for that pinhole.
- The lens disc (diameter d) lies in the lens plane z = y tan θL; a lens sample lens_uv ∈ [0, 1)² is
  mapped to the disc by the concentric mapping, S = (s_x, s_y cos θL, s_y sin θL).
- The plane of focus is z = U + y tan θF, θF and θL related by the exact Scheimpflug rule
  tan θF = (U + w) tan θL / w. The chief ray meets it at P_f = t c with t = U / D, D = w − y_s tan θF.
- Every ray of the pixel starts at S and passes through P_f: direction P_f − S when P_f is in front of
  the lens (t > 0, paper eq. (5)), S − P_f when P_f is behind it (t < 0, the virtual focus point of
  pixels with no finite focus distance, eq. (6)), and c when the chief ray is parallel to the plane
  (D = 0). One branch-free form covers all three: the direction is
        c − (D / U) · S   (= (D / U)(P_f − S), a positive multiple of the right one in each case),
  finite for every pixel and every |θF| < 90°. It is exactly the thin-lens refraction of the ray from P
  through S for a lens of focal length f = U w cos θL / (U + w) (see tests).
- d = 0 gives S = 0 and the direction c: bit for bit the pinhole. θF = 0 gives the plain thin lens.
- A tilt axis turned by φ (`tilt_axis_deg`; the rotation of a tilt-shift lens) is the same geometry in the
  frame turned by φ about the optical axis: y becomes y_φ = y cos φ − x sin φ in the plane of focus and D,
  and the disc's point is s_x a + s_y (b cos θL + ẑ sin θL) with a = (cos φ, sin φ, 0),
  b = (−sin φ, cos φ, 0).
Rays are valid everywhere and carry weight 1 (no cos⁴ vignetting). Pixels beyond the Scheimpflug line
(y_s > w / tan θL, only for extreme tilts) would put the sensor in front of the lens plane; the formula
extends smoothly there.
"""
from __future__ import annotations

import copy
import math

import torch

from . import optics
from renderer.core.blend import carries_derivative, selector
from camio.checks import is_finite_number
from renderer.core.params import Param, SceneError
from renderer.core.rays import Rays, normalize_rows_, unit_vectors_from_rows, vectors_from_rows
from renderer.core.transforms import CameraTransform
from .base import Camera, Screen
from .distortion import BrownConrady
from .lens import Lens
from .registry import register_camera

THIN_LENS_PARAMS = [
    Param("w", "float", doc="lens centre to sensor (effective focal length), scene units"),
    Param("U", "float", None, "lens centre to the plane of focus along the optical axis, scene units"),
    Param("f", "float", None, "focal length instead of U (U from the hinge rule), scene units"),
    Param("d", "float", doc="aperture diameter, scene units (0: pinhole)"),
    Param("sensor_size", "vec2", doc="[width, height] of the sensor at distance w, scene units"),
    Param("theta_F_deg", "float", None, "tilt of the plane of focus about the camera x axis, degrees [0]"),
    Param("theta_L_deg", "float", None, "lens tilt instead of theta_F_deg (exact conversion), degrees"),
    Param("principal_point_px", "vec2", None, "(cx, cy) principal point, pixels [image centre]"),
    Param("tilt_axis_deg", "float", None, "direction of the tilt axis from the camera x axis, degrees within ±360 "
          "[0]"),
    Param("focus_points", "list", None, "three world points to focus on, instead of U/f and the tilts "
          "(U, theta_F and the tilt axis follow)"),
]


def _like(value, like: torch.Tensor) -> torch.Tensor:
    """A float or tensor parameter as a tensor of `like`'s dtype and device (a tensor keeps its graph)."""
    if isinstance(value, torch.Tensor):
        return value.to(dtype=like.dtype, device=like.device)
    return torch.tensor(value, dtype=like.dtype, device=like.device)


def concentric_disk(lens_uv: torch.Tensor) -> torch.Tensor:
    """Shirley–Chiu concentric map of (..., 2) uniform samples in [0, 1)² to the unit disc, (..., 2).

    Area-preserving and low-distortion, so stratified or Sobol samples stay well spread on the disc;
    (0.5, 0.5) maps to the centre.
    """
    return torch.stack(concentric_disk_xy(lens_uv), -1)


def concentric_disk_xy(lens_uv: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """`concentric_disk` as its two (...,) components x, y (no stacking)."""
    ab = 2 * lens_uv.movedim(-1, 0) - 1  # rows a, b
    a, b = ab[0], ab[1]
    magnitude = ab.abs()
    # Which of |a|, |b| is larger has no order over the samples: `selector` blends instead of branching.
    pick = selector(magnitude[0] > magnitude[1])
    r, other = pick.pair(a, b)
    # phi = π/4 · b/a where |a| > |b|, else π/2 − π/4 · a/b: each ratio only where its denominator (r) is the
    # larger magnitude; r = 0 (a = b = 0) divides by 1 instead, so no 0/0.
    q = (math.pi / 4) * (other / (r + (r == 0)))
    phi = pick(q, math.pi / 2 - q)
    return r * torch.cos(phi), r * torch.sin(phi)


# The tilted thin lens's ray, per component (rows x, y, z), written once: the eager camera (`ThinLensCamera.lens_rows`,
# `rays_in_camera`) and the compiled fused path (`renderer.tracing.fused`) call these. `_rays_in_place` repeats
# them with in-place steps (the same operations in the same order, so the same bits: tests/renderer/test_thin_lens.py),
# and Mitsuba's sensor (`renderer.mitsuba.sensors.TiltedThinLens`) in Dr.Jit, which torch functions cannot run in.

def disc_rows(lx, ly, half_d, cos_theta_L, sin_theta_L):
    """The lens disc's point (s_x, s_y cos θL, s_y sin θL), (s_x, s_y) = (lx, ly) · d/2, of unit-disc samples (lx, ly),
    tilt axis the camera x axis."""
    sx, sy = lx * half_d, ly * half_d
    return sx, sy * cos_theta_L, sy * sin_theta_L


def focus_weight_rows(y, z, tan_theta_F, U):
    """D / U = (z − y tan θF) / U for chief directions (x, y, z) (y in the frame of the tilt axis): the pixel's focus
    point is P_f = (x, y, z) · U / D."""
    return (z - y * tan_theta_F) / U


def direction_rows(x, y, z, sx, sy, sz, weight):
    """The ray direction c − (D/U) S (not normalised) of chief direction c = (x, y, z) and lens point S."""
    return x - weight * sx, y - weight * sy, z - weight * sz


def focus_lens(path: str, cfg: dict, transform: CameraTransform) -> Lens:
    """The lens of a `focus_points` camera: the plane of focus through three world points (`Lens.focus_through`
    in the camera frame of `transform`). Messages name the field."""
    for key in ("U", "f", "theta_F_deg", "theta_L_deg", "tilt_axis_deg"):
        if cfg.get(key) is not None:
            raise SceneError(f"{path}: give focus_points or {key}, not both (the points set U and the tilts)")
    pts = cfg["focus_points"]
    if not (len(pts) == 3 and all(isinstance(q, (list, tuple)) and len(q) == 3 for q in pts)
            and all(is_finite_number(v) for q in pts for v in q)):
        raise SceneError(f"{path}.focus_points: expected three points [x, y, z] of finite numbers, got {pts!r}")
    _check_lens_and_sensor(path, cfg)
    world = torch.tensor(pts, dtype=torch.float64)
    cam = transform.points_to_camera(world).numpy()
    try:
        return Lens.focus_through(cam, cfg["d"], w=cfg["w"])
    except ValueError as e:
        raise SceneError(f"{path}.focus_points: {str(e).removeprefix('points: ')}") from None


# The tilt axis's range, the same as CALIB.json's (`tiltfit.files.calib`): a turn either way. A larger number is a
# typing error, not a rotation (1e9° would quietly render as 280°).
MAX_TILT_AXIS_DEG = 360.0


def _check_lens_and_sensor(path: str, cfg: dict) -> None:
    """The checks every thin lens takes, however its focus is given (U, f or focus_points): w > 0, d >= 0 and a
    sensor of positive width and height (a zero size divides by zero; a negative one turns the image by 180°)."""
    if cfg["w"] <= 0:
        raise SceneError(f"{path}.w: expected a positive distance, got {cfg['w']}")
    if cfg["d"] < 0:
        raise SceneError(f"{path}.d: expected a diameter >= 0, got {cfg['d']}")
    sx, sy = cfg["sensor_size"]
    if not (sx > 0 and sy > 0):
        raise SceneError(f"{path}.sensor_size: expected positive sizes, got {[sx, sy]}")


def parse_lens(path: str, cfg: dict) -> Lens:
    """Validate the thin-lens keys and resolve the `Lens` (U, θF exactly). Messages name the field."""
    phi = cfg.get("tilt_axis_deg")
    if phi is not None and not abs(phi) <= MAX_TILT_AXIS_DEG:
        raise SceneError(f"{path}.tilt_axis_deg: expected an angle within ±{MAX_TILT_AXIS_DEG:g}°, got {phi}")
    return _parse_lens(path, cfg).with_(phi=math.radians(phi or 0.0))


def _parse_lens(path: str, cfg: dict) -> Lens:
    w, d = cfg["w"], cfg["d"]
    _check_lens_and_sensor(path, cfg)
    if cfg.get("theta_F_deg") is not None and cfg.get("theta_L_deg") is not None:
        raise SceneError(f"{path}: give theta_F_deg or theta_L_deg, not both")
    if (cfg.get("U") is None) == (cfg.get("f") is None):
        raise SceneError(f"{path}: give exactly one of U (focus distance) and f (focal length)")
    for key in ("theta_F_deg", "theta_L_deg"):
        if cfg.get(key) is not None and not abs(cfg[key]) < 90:
            raise SceneError(f"{path}.{key}: expected an angle in (-90, 90), got {cfg[key]}")
    if cfg.get("U") is not None:
        U = cfg["U"]
        if U <= 0:
            raise SceneError(f"{path}.U: expected a positive distance, got {U}")
        if cfg.get("theta_L_deg") is not None:
            return Lens.from_theta_L(w, U, d, math.radians(cfg["theta_L_deg"]))
        return Lens(w, U, d, math.radians(cfg.get("theta_F_deg") or 0.0))
    f = cfg["f"]
    if cfg.get("theta_L_deg") is not None:
        theta_L = math.radians(cfg["theta_L_deg"])
    else:
        theta_F = math.radians(cfg.get("theta_F_deg") or 0.0)
        if not 0 < f < w:
            raise SceneError(f"{path}.f: expected 0 < f < w = {w} for a real plane of focus, got {f}")
        theta_L = float(optics.theta_L_from_theta_F_f(theta_F, w, f))
    if not 0 < f < w * math.cos(theta_L):
        raise SceneError(f"{path}.f: expected 0 < f < w cos(theta_L) = {w * math.cos(theta_L):.6g} "
                         f"for a real plane of focus, got {f}")
    return Lens.from_tilt(w, f, theta_L, d)


@register_camera("thin_lens", THIN_LENS_PARAMS)
class ThinLensCamera(Camera):
    """Thin lens of aperture d, sensor at w, plane of focus z = U + y tan θF (distributed ray tracing).

    Its lens is `lens` (a `renderer.cameras.lens.Lens`: w, U, d, θF, principal point and distortion, and θL, f
    derived; scene units, radians), the only place the camera keeps them: the sensor mapping (`screen`, at
    distance w about the lens's principal point) and the distortion (`distortion`) are read from it on every
    call, never copied, so a lens replaced after construction (`cam.lens = cam.lens.with_(w=...)`) moves the
    rays, the projection and the undistortion with it. The lens's numbers may be Python floats or 0-dim tensors:
    with tensors that require grad, gradients reach them through every ray.

    Args:
        transform: the pose.
        lens: the `Lens`.
        image_size_px: (W, H) pixels, and sensor_size: (width, height) of the sensor, scene units: the pixel grid
            of a lens without a `Sensor` (a scene file's, whose pixels need not be square); None for a lens
            with one (its `size_px` and `size`).
    """

    uses_lens_samples = True

    def __init__(self, transform, lens: Lens, image_size_px=None, sensor_size=None):
        if not isinstance(lens, Lens):
            raise TypeError(f"lens: expected a renderer.cameras.lens.Lens, got {type(lens).__name__}")
        if (image_size_px is None) != (sensor_size is None):
            raise ValueError("image_size_px, sensor_size: give both (a lens without a Sensor) or neither")
        if image_size_px is None and lens.sensor is None:
            raise ValueError("lens.sensor: a lens without a Sensor needs image_size_px and sensor_size")
        if image_size_px is not None and lens.sensor is not None:
            raise ValueError("image_size_px, sensor_size: this lens has a Sensor; give neither (one pixel grid)")
        self.transform = transform
        self.lens = lens
        self._grid = None if image_size_px is None else (
            int(image_size_px[0]), int(image_size_px[1]), (sensor_size[0], sensor_size[1]))

    @property
    def screen(self) -> Screen:
        """The pixel-to-sensor mapping at distance w about the principal point, both the lens's (made on each
        call from `lens`, so it always agrees with it)."""
        lens = self.lens
        if self._grid is None:
            (W, H), size = lens.sensor.size_px, lens.sensor.size
        else:
            W, H, size = self._grid
        return Screen(W, H, size, lens.w, lens.principal_point_px)

    @property
    def distortion(self) -> BrownConrady | None:
        """The lens's distortion (`Lens.distortion` in `Lens.distortion_frame`), None without one; made once per
        lens value."""
        lens = self.lens
        if lens.distortion is None:
            return None
        cached = self.__dict__.get("_distortion_of")
        if cached is None or cached[0] is not lens:
            cached = (lens, BrownConrady(lens.distortion, lens.distortion_frame))
            self._distortion_of = cached
        return cached[1]

    def with_lens(self, lens: Lens) -> "ThinLensCamera":
        """The same camera (pose, pixel grid) with another lens."""
        out = copy.copy(self)
        out.lens = lens
        return out

    @classmethod
    def from_config(cls, path, cfg, transform, width, height):
        if cfg.get("focus_points") is not None:
            lens = focus_lens(path, cfg, transform)
        else:
            lens = parse_lens(path, cfg)
        pp = cfg.get("principal_point_px")
        if pp is not None:
            lens = lens.with_(principal_point_px=tuple(pp))
        return cls(transform, lens, (width, height), tuple(cfg["sensor_size"]))

    @classmethod
    def from_calibration(cls, lens: Lens, R, T) -> "ThinLensCamera":
        """The camera of a calibrated lens (tiltfit's; `LensCamera.view_camera` builds its views with it): the
        lens's sensor of W x H pixels of pitch p at w, its principal point and distortion (about the lens axis
        where `lens.distortion_centre` says so: rays of each pixel through its ideal position, undistorted in
        the lens frame), pose
        X_cam = R X_world + T.

        Args:
            lens: the `Lens`, with its sensor (numbers or 0-dim tensors: gradients reach them).
            R: (3, 3) rotation camera_from_world; T: (3,) translation.
        """
        if lens.sensor is None:
            raise ValueError("lens.sensor: a calibrated camera needs the lens's sensor (Sensor(W, H, pitch))")
        return cls(CameraTransform.from_extrinsics(R, T), lens)

    def lens_points(self, lens_uv: torch.Tensor) -> torch.Tensor:
        """(..., 2) samples in [0, 1)² -> (..., 3) points on the tilted lens disc, camera frame."""
        return torch.stack(self.lens_rows(lens_uv), -1)

    def lens_rows(self, lens_uv: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """`lens_points` as its three (...,) components: the disc's point (s_a, s_b) on the tilt axis
        a = (cos φ, sin φ, 0) and across it, b cos θL + ẑ sin θL with b = (−sin φ, cos φ, 0)."""
        lx, ly = concentric_disk_xy(lens_uv)
        theta_L = _like(self.lens.theta_L, lx)
        sx, across, sz = disc_rows(lx, ly, self.lens.d / 2, torch.cos(theta_L), torch.sin(theta_L))
        if self._untwisted():
            return sx, across, sz
        phi = _like(self.lens.phi, sx)
        c, s = torch.cos(phi), torch.sin(phi)
        return sx * c - across * s, sx * s + across * c, sz

    def _untwisted(self) -> bool:
        """Whether the tilt axis is the camera x axis (φ = 0 as a plain number)."""
        return not isinstance(self.lens.phi, torch.Tensor) and self.lens.phi == 0

    def focus_weight(self, c: torch.Tensor) -> torch.Tensor:
        """D / U = 1 / t for chief directions c = (x_s, y_s, w): the pixel's focus point is P_f = c · U / D."""
        return self._focus_weight(c[..., 0], c[..., 1], c[..., 2])

    def _focus_weight(self, x: torch.Tensor, y: torch.Tensor, z) -> torch.Tensor:
        """(z − y_φ tan θF) / U with y_φ = y cos φ − x sin φ: where the chief ray (x, y, z) meets the plane of
        focus."""
        if not self._untwisted():
            phi = _like(self.lens.phi, y)
            y = y * torch.cos(phi) - x * torch.sin(phi)
        return focus_weight_rows(y, z, torch.tan(_like(self.lens.theta_F, y)), self.lens.U)

    def rays_in_camera(self, uv_px: torch.Tensor, lens_uv: torch.Tensor) -> Rays:
        # Per component (x, y, z rows), without (..., 3) intermediates, whose length-3 last axis is slow in
        # eager torch. The (..., 3) results are views of (3, ...) rows, which the tracer's row code takes
        # without a copy.
        if self._plain(uv_px, lens_uv):
            return self._rays_in_place(uv_px, lens_uv)
        x, y, z = self.screen.plane_rows(uv_px)
        sx, sy, sz = self.lens_rows(lens_uv.to(x))
        weight = self._focus_weight(x, y, z)
        dx, dy, dz = direction_rows(x, y, z, sx, sy, sz, weight)
        valid = torch.ones(x.shape, dtype=torch.bool, device=x.device)
        return Rays(vectors_from_rows(sx, sy, sz), unit_vectors_from_rows(dx, dy, dz), valid, torch.ones_like(x))

    def _plain(self, uv_px: torch.Tensor, lens_uv: torch.Tensor) -> bool:
        """Whether `_rays_in_place` may answer: lens and screen parameters plain numbers (the principal point
        and pitch too), inputs of one shape that carry no derivative of any kind (reverse or forward mode,
        torch.func), eager tracing."""
        lens = self.lens
        screen = self.screen
        params = (lens.w, lens.U, lens.d, lens.theta_F, *screen.center_px, *screen.pitch)
        return (not any(isinstance(p, torch.Tensor) for p in params) and self._untwisted()
                and uv_px.shape == lens_uv.shape
                and not carries_derivative(uv_px) and not carries_derivative(lens_uv)
                and not torch.compiler.is_compiling())

    def _rays_in_place(self, uv_px: torch.Tensor, lens_uv: torch.Tensor) -> Rays:
        """`rays_in_camera`'s formulas, the same operations in the same order (the same bits), written into
        two (3, ...) blocks with in-place steps: fewer temporaries and no stacking copies (eager, no
        gradients)."""
        x, y = self.screen.plane_xy(uv_px)
        z = self.lens.w  # a number: rounded to x's dtype in each operation, as a filled row would be
        lx, ly = concentric_disk_xy(lens_uv.to(x))
        origin = torch.empty((3, *x.shape), dtype=x.dtype, device=x.device)
        torch.mul(lx, self.lens.d / 2, out=origin[0])
        sy = ly.mul_(self.lens.d / 2)
        theta_L = _like(self.lens.theta_L, x)
        torch.mul(sy, torch.cos(theta_L), out=origin[1])
        torch.mul(sy, torch.sin(theta_L), out=origin[2])
        weight = self._focus_weight(x, y, z)
        d = torch.mul(origin, weight)  # weight · S, then P − weight · S row by row
        torch.sub(x, d[0], out=d[0])
        torch.sub(y, d[1], out=d[1])
        d[2].neg_().add_(z)
        normalize_rows_(d)
        valid = torch.ones(x.shape, dtype=torch.bool, device=x.device)
        return Rays(origin.movedim(0, -1), d.movedim(0, -1), valid, torch.ones_like(x))

    def focus_geometry(self, uv_px: torch.Tensor, distorted: bool = True):
        """Where the rays of sensor points converge, and the aperture they come from, world frame.

        Every ray `generate_rays` traces from the sensor point of `uv_px` leaves a point L of the lens disc and
        passes through that point's conjugate, its focus point q (on the plane of focus): the ray is the line
        (L, q). A pixel's blur is therefore the aperture disc seen through q, in closed form
        (`tiltfit.photometric.aperture` integrates a checkerboard over it exactly).

        Args:
            uv_px: (..., 2) pixel positions (distorted pixels are traced through their ideal positions, as in
                `generate_rays`).
            distorted: whether `uv_px` are pixels of the distorted image [True]; False: already ideal pixels (as
                `undistort_pixels` gives them), taken as they are.
        Returns:
            q_h: (..., 4) homogeneous focus points (x, y, z, s), world frame: q = (x, y, z) / s, with s ≤ 0 for
                focus points at infinity or behind the lens (s = D/U, `focus_weight`).
            centre: (3,) the lens centre; axes: (2, 3) two orthogonal half-diameter vectors of the aperture
                disc (length d/2), so its points are centre + a·axes[0] + b·axes[1], a² + b² ≤ 1.
            valid: (...,) False where the distortion cannot be inverted.
        """
        if distorted:
            ideal_px, valid = self.undistort_pixels(uv_px)
        else:
            ideal_px, valid = uv_px, torch.ones(uv_px.shape[:-1], dtype=torch.bool, device=uv_px.device)
        x, y, z = self.screen.plane_rows(ideal_px)
        weight = self._focus_weight(x, y, z)
        R = self.transform.world_from_camera.to(x)
        t = self.transform.position.to(x)
        c = torch.stack([x, y, z], -1)
        q = c @ R.transpose(-1, -2) + weight[..., None] * t
        # The lens points of the samples that `concentric_disk` maps to (1, 0) and (0, 1): the disc's axes.
        ends = torch.tensor([[1.0, 0.5], [0.5, 1.0]], dtype=x.dtype, device=x.device)
        local = torch.stack(self.lens_rows(ends), -1)
        return torch.cat([q, weight[..., None]], -1), t, local @ R.transpose(-1, -2), valid

    def project(self, p_world: torch.Tensor) -> torch.Tensor:
        """Chief-ray projection (pixel of the blur spot's centre of projection), same as the pinhole at w."""
        return self.project_central(p_world)
