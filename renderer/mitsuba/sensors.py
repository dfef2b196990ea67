"""Our tilted thin lens and inverted-perspective camera as Mitsuba 3 sensor plugins (`tilted_thinlens`,
`inverted_perspective`), written in Python with Dr.Jit arithmetic, so they run in every variant (scalar_rgb
traces per sample, llvm/cuda variants fuse them into Mitsuba's kernels).

Both follow our cameras' formulas (renderer/cameras/thin_lens.py, renderer/cameras/inverted_perspective.py)
in our camera frame (x right, y down, z forward) and move the ray to the world with the sensor's `to_world`,
which here is our camera pose [world_from_camera | position] (not Mitsuba's flipped perspective frame).

Film position: Mitsuba's `position_sample` ∈ [0, 1)² spans the film (x right, y down); our pixel (x, y)
covers [x − 0.5, x + 0.5] around its centre, so uv_px = position_sample · (W, H) − 0.5 (no crop window).
Lens samples: Mitsuba's `aperture_sample` through the same concentric disc map as ours (same distribution;
the sample-to-point map may differ, which changes no expectation). Rays carry weight 1, as ours do.

Lens distortion (renderer/cameras/distortion.py): a pixel is traced through its ideal position, the
Brown–Conrady model inverted by the same damped Newton steps (`undistort`); where they do not converge the
sample has weight 0, as our camera gives it no ray.

Properties (all floats unless noted; scene units, radians):
- common: `width_px`, `height_px` (ints, must match the film), `size_x`, `size_y` (screen or sensor extent),
  `cx`, `cy` (principal point, pixels), `to_world` (our camera pose), `distance` (screen distance, the
  focal length of the normalised coordinates), `k1`, `k2`, `p1`, `p2`, `k3`, `k4`, `k5`, `k6` (the lens
  distortion in OpenCV's order [0]);
- `tilted_thinlens`: `w`, `U`, `d`, `theta_F`, `phi` (the tilt axis's direction; θL derived by `Lens`);
- `inverted_perspective`: `alpha`, `p3` (pseudo-screen distance), `q3` (screen distance).

Call `register(mi)` after choosing a variant (registration is per variant); `sensor_dict(camera, ...)`
builds the dict of one of our camera objects.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from ..cameras.lens import Lens
from renderer.core.transforms import world_from_local_4x4

_REGISTERED: set = set()
COEFFICIENT_NAMES = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")  # OpenCV's order, as the scene file's
# Newton steps of `undistort`, and its convergence test: within 256 float32 ulps (renderer/cameras/distortion.py).
UNDISTORT_ITERATIONS = 20
UNDISTORT_TOL = 256 * 2.0**-23


def undistort(dr, k, xd, yd):
    """renderer/cameras/distortion.py's `undistort` in Dr.Jit arithmetic: Brown–Conrady distorted normalised
    coordinates (xd, yd) -> ideal ones (x, y) by damped Newton steps, and where they converged (ok)."""
    k1, k2, p1, p2, k3, k4, k5, k6 = k

    def model(x, y):  # distort(x, y) and its Jacobian (jxx, jxy = jyx, jyy)
        r2 = x * x + y * y
        a, b = 1 + r2 * (k1 + r2 * (k2 + r2 * k3)), 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
        da, db = k1 + r2 * (2 * k2 + 3 * r2 * k3), k4 + r2 * (2 * k5 + 3 * r2 * k6)
        s, ds = a / b, (da * b - a * db) / (b * b)
        fx = x * s + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        fy = y * s + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        jxx = s + 2 * x * x * ds + 2 * p1 * y + 6 * p2 * x
        jxy = 2 * x * y * ds + 2 * p1 * x + 2 * p2 * y
        jyy = s + 2 * y * y * ds + 6 * p1 * y + 2 * p2 * x
        return fx, fy, jxx, jxy, jyy

    x, y = xd, yd
    for _ in range(UNDISTORT_ITERATIONS):
        fx, fy, jxx, jxy, jyy = model(x, y)
        ex, ey = fx - xd, fy - yd
        det = jxx * jyy - jxy * jxy
        det = dr.select(det == 0, 1e-30, det)
        sx, sy = (jyy * ex - jxy * ey) / det, (jxx * ey - jxy * ex) / det
        # Steps limited to half the current radius plus a little, as ours: Newton stays where it inverts.
        limit = 0.5 * dr.sqrt(x * x + y * y) + 0.05
        scale = dr.minimum(limit / dr.maximum(dr.sqrt(sx * sx + sy * sy), 1e-30), 1.0)
        x, y = x - sx * scale, y - sy * scale
    fx, fy, jxx, jxy, jyy = model(x, y)
    residual = dr.sqrt((fx - xd) * (fx - xd) + (fy - yd) * (fy - yd))
    ok = (residual <= UNDISTORT_TOL * (1 + dr.sqrt(xd * xd + yd * yd))) & (jxx * jyy - jxy * jxy > 0)
    return x, y, ok


def _sensor_base(mi):
    """The base class of our sensor plugins for Mitsuba's current variant: film position to a screen point
    (through the inverse lens distortion) and the ray to the world; subclasses give `camera_ray`."""
    import drjit as dr

    class _OurSensor(mi.Sensor):
        def __init__(self, props):
            mi.Sensor.__init__(self, props)
            self.size_px = (props.get("width_px"), props.get("height_px"))
            self.pitch = (props.get("size_x") / self.size_px[0], props.get("size_y") / self.size_px[1])
            self.center_px = (props.get("cx"), props.get("cy"))
            self.distance = props.get("distance", 1.0)
            self.k = tuple(props.get(name, 0.0) for name in COEFFICIENT_NAMES)
            # camera_from_lens (row by row) where the distortion acts about a tilted lens's axis, else None
            rot = [props.get(f"lens_r{i}{j}", math.nan) for i in range(3) for j in range(3)]
            self.camera_from_lens = None if any(math.isnan(v) for v in rot) else rot

        def _screen(self, position_sample):
            """Film position -> (x, y) on our screen plane, camera frame, scene units, and whether the pixel has
            a ray: with a lens distortion, the ideal (undistorted) position the pixel is traced through."""
            u = position_sample.x * self.size_px[0] - 0.5
            v = position_sample.y * self.size_px[1] - 0.5
            xs, ys = (u - self.center_px[0]) * self.pitch[0], (v - self.center_px[1]) * self.pitch[1]
            if not any(self.k):
                return xs, ys, True
            xn, yn = xs / self.distance, ys / self.distance
            if self.camera_from_lens is None:
                x, y, ok = undistort(dr, self.k, xn, yn)
                return x * self.distance, y * self.distance, ok
            # distortion.undistort_about_axis: into the lens frame (Rᵀ (x, y, 1)), undistort there, back (R ·)
            r = self.camera_from_lens
            vx, vy, vz = (r[0 + i] * xn + r[3 + i] * yn + r[6 + i] for i in range(3))
            xl, yl, ok = undistort(dr, self.k, vx / vz, vy / vz)
            cx, cy, cz = (r[3 * i] * xl + r[3 * i + 1] * yl + r[3 * i + 2] for i in range(3))
            ok = ok & (vz > 0) & (cz > 0)
            return cx / cz * self.distance, cy / cz * self.distance, ok

        def sample_ray(self, time, wavelength_sample, position_sample, aperture_sample, active=True):
            xs, ys, ok = self._screen(position_sample)
            o, d = self.camera_ray(xs, ys, aperture_sample)
            ray = mi.Ray3f(o, dr.normalize(d), time, mi.Color0f())
            return self.world_transform() @ ray, mi.Spectrum(dr.select(ok, 1.0, 0.0))

        def sample_ray_differential(self, time, wavelength_sample, position_sample, aperture_sample, active=True):
            ray, weight = self.sample_ray(time, wavelength_sample, position_sample, aperture_sample, active)
            return mi.RayDifferential3f(ray), weight

        def bbox(self):
            return mi.ScalarBoundingBox3f()

    return _OurSensor


def _classes(mi):
    """{plugin name: sensor class} of our cameras for Mitsuba's current variant."""
    _OurSensor = _sensor_base(mi)

    class TiltedThinLens(_OurSensor):
        """renderer/cameras/thin_lens.py: every ray of a pixel leaves the tilted lens disc at S and has the
        direction c − (D/U)·S, c = (x_s, y_s, w), D = w − y_s tan θF.

        The Dr.Jit twin of thin_lens.py's row functions (`disc_rows`, `focus_weight_rows`, `direction_rows`):
        Mitsuba calls it inside its own kernels, where torch functions cannot run, so the formulas are written
        again here (checked ray for ray against the torch camera: tests/renderer/test_mitsuba_sensors.py)."""

        def __init__(self, props):
            _OurSensor.__init__(self, props)
            self.lens = Lens(props.get("w"), props.get("U"), props.get("d"), props.get("theta_F"),
                             phi=props.get("phi", 0.0))
            self.tan_F = math.tan(self.lens.theta_F)
            self.cos_L, self.sin_L = math.cos(self.lens.theta_L), math.sin(self.lens.theta_L)
            self.cos_phi, self.sin_phi = math.cos(self.lens.phi), math.sin(self.lens.phi)
            self.m_needs_sample_3 = self.lens.d > 0

        def camera_ray(self, xs, ys, aperture_sample):
            lens, c, s_ = self.lens, self.cos_phi, self.sin_phi
            disc = mi.warp.square_to_uniform_disk_concentric(aperture_sample) * (lens.d / 2)
            across = disc.y * self.cos_L  # the disc's point along the tilt axis (cos φ, sin φ) and across it
            s = mi.Vector3f(disc.x * c - across * s_, disc.x * s_ + across * c, disc.y * self.sin_L)
            focus = (lens.w - (ys * c - xs * s_) * self.tan_F) / lens.U
            return mi.Point3f(s), mi.Vector3f(xs, ys, lens.w) - focus * s

    class InvertedPerspective(_OurSensor):
        """renderer/cameras/inverted_perspective.py, eq. (1)-(3): p = (q1, q2, q3)·p3/q3 on the pseudo-screen,
        origin v = α (p1, p2, 0), direction p − v."""

        def __init__(self, props):
            _OurSensor.__init__(self, props)
            self.alpha, self.p3, self.q3 = props.get("alpha"), props.get("p3"), props.get("q3")
            self.m_needs_sample_3 = False

        def camera_ray(self, xs, ys, aperture_sample):
            k = self.p3 / self.q3
            p1, p2 = xs * k, ys * k
            origin = mi.Point3f(self.alpha * p1, self.alpha * p2, 0.0)
            return origin, mi.Vector3f(p1 - origin.x, p2 - origin.y, self.p3)

    return {"tilted_thinlens": TiltedThinLens, "inverted_perspective": InvertedPerspective}


def register(mi) -> None:
    """Register both plugins with Mitsuba for its current variant (idempotent)."""
    variant = mi.variant()
    if variant in _REGISTERED:
        return
    for name, cls in _classes(mi).items():
        mi.register_sensor(name, lambda props, cls=cls: cls(props))
    _REGISTERED.add(variant)


def _coefficients(camera) -> dict:
    """The camera's lens distortion as sensor properties {k1: ..., p1: ...}, {} without one."""
    distortion = camera.distortion
    if distortion is None or distortion.is_identity:
        return {}
    out = {name: float(v) for name, v in zip(COEFFICIENT_NAMES, distortion.coefficients)}
    if distortion.camera_from_lens is not None:  # about a tilted lens's axis: the rotation into its frame
        R = np.asarray(torch.as_tensor(distortion.camera_from_lens).detach().cpu(), dtype=np.float64)
        out.update({f"lens_r{i}{j}": float(R[i, j]) for i in range(3) for j in range(3)})
    return out


def sensor_dict(mi, camera, spp: int, sampler: str = "independent") -> dict:
    """Mitsuba sensor dict for our `thin_lens`, `inverted_perspective`, `pinhole` or `orthographic` camera (box
    filter, RGB film); the last two as the inverted perspective at α = 0 and α = 1 with p3 = q3 (eq. (1)-(3):
    the rays of a pinhole through the origin, of the orthographic camera parallel from its screen points).

    Raises NotImplementedError for other camera types.
    """
    register(mi)
    kind = type(camera).__name__
    screen = camera.screen
    W, H = screen.width_px, screen.height_px
    (cx, cy) = screen.center_px
    M = world_from_local_4x4(camera.transform.world_from_camera.numpy(), camera.transform.position.numpy())
    common = {"width_px": W, "height_px": H, "size_x": float(screen.size[0]), "size_y": float(screen.size[1]),
              "cx": float(cx), "cy": float(cy), "to_world": mi.ScalarTransform4f(M),
              "distance": float(screen.distance), **_coefficients(camera),
              "film": {"type": "hdrfilm", "width": W, "height": H, "rfilter": {"type": "box"},
                       "pixel_format": "rgb", "component_format": "float32"},
              "sampler": {"type": sampler, "sample_count": int(spp)}}
    if kind == "ThinLensCamera":
        lens = camera.lens
        return {"type": "tilted_thinlens", "w": float(lens.w), "U": float(lens.U), "d": float(lens.d),
                "theta_F": float(lens.theta_F), "phi": float(lens.phi), **common}
    if kind == "InvertedPerspectiveCamera":
        return {"type": "inverted_perspective", "alpha": camera.alpha, "p3": camera.pseudo_screen_distance,
                "q3": float(screen.distance), **common}
    if kind in ("PinholeCamera", "OrthographicCamera"):  # the inverted perspective at α = 0 and α = 1, p3 = q3
        q3 = float(screen.distance)
        return {"type": "inverted_perspective", "alpha": float(kind == "OrthographicCamera"), "p3": q3, "q3": q3,
                **common}
    raise NotImplementedError(f"camera {kind} has no Mitsuba sensor plugin")
