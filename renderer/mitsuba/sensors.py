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

Properties (all floats unless noted; scene units, radians):
- common: `width_px`, `height_px` (ints, must match the film), `size_x`, `size_y` (screen or sensor extent),
  `cx`, `cy` (principal point, pixels), `to_world` (our camera pose);
- `tilted_thinlens`: `w`, `U`, `d`, `theta_F`, `theta_L`;
- `inverted_perspective`: `alpha`, `p3` (pseudo-screen distance), `q3` (screen distance).

Call `register(mi)` after choosing a variant (registration is per variant); `sensor_dict(camera, ...)`
builds the dict of one of our camera objects.
"""
from __future__ import annotations

import math

from ..transforms import world_from_local_4x4

_REGISTERED: set = set()


def _classes(mi):
    import drjit as dr

    class _OurSensor(mi.Sensor):
        def __init__(self, props):
            mi.Sensor.__init__(self, props)
            self.size_px = (props.get("width_px"), props.get("height_px"))
            self.pitch = (props.get("size_x") / self.size_px[0], props.get("size_y") / self.size_px[1])
            self.center_px = (props.get("cx"), props.get("cy"))

        def _screen(self, position_sample):
            """Film position -> (x, y) on our screen plane, camera frame, scene units."""
            u = position_sample.x * self.size_px[0] - 0.5
            v = position_sample.y * self.size_px[1] - 0.5
            return (u - self.center_px[0]) * self.pitch[0], (v - self.center_px[1]) * self.pitch[1]

        def sample_ray(self, time, wavelength_sample, position_sample, aperture_sample, active=True):
            o, d = self.camera_ray(position_sample, aperture_sample)
            ray = mi.Ray3f(o, dr.normalize(d), time, mi.Color0f())
            return self.world_transform() @ ray, mi.Spectrum(1.0)

        def sample_ray_differential(self, time, wavelength_sample, position_sample, aperture_sample, active=True):
            ray, weight = self.sample_ray(time, wavelength_sample, position_sample, aperture_sample, active)
            return mi.RayDifferential3f(ray), weight

        def bbox(self):
            return mi.ScalarBoundingBox3f()

    class TiltedThinLens(_OurSensor):
        """renderer/cameras/thin_lens.py: every ray of a pixel leaves the tilted lens disc at S and has the
        direction c − (D/U)·S, c = (x_s, y_s, w), D = w − y_s tan θF."""

        def __init__(self, props):
            _OurSensor.__init__(self, props)
            self.w, self.U, self.d = props.get("w"), props.get("U"), props.get("d")
            self.tan_F = math.tan(props.get("theta_F"))
            self.cos_L, self.sin_L = math.cos(props.get("theta_L")), math.sin(props.get("theta_L"))
            self.m_needs_sample_3 = self.d > 0

        def camera_ray(self, position_sample, aperture_sample):
            xs, ys = self._screen(position_sample)
            disc = mi.warp.square_to_uniform_disk_concentric(aperture_sample) * (self.d / 2)
            s = mi.Vector3f(disc.x, disc.y * self.cos_L, disc.y * self.sin_L)
            focus = (self.w - ys * self.tan_F) / self.U
            return mi.Point3f(s), mi.Vector3f(xs, ys, self.w) - focus * s

    class InvertedPerspective(_OurSensor):
        """renderer/cameras/inverted_perspective.py, eq. (1)-(3): p = (q1, q2, q3)·p3/q3 on the pseudo-screen,
        origin v = α (p1, p2, 0), direction p − v."""

        def __init__(self, props):
            _OurSensor.__init__(self, props)
            self.alpha, self.p3, self.q3 = props.get("alpha"), props.get("p3"), props.get("q3")
            self.m_needs_sample_3 = False

        def camera_ray(self, position_sample, aperture_sample):
            xs, ys = self._screen(position_sample)
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


def sensor_dict(mi, camera, spp: int, sampler: str = "independent") -> dict:
    """Mitsuba sensor dict for our `thin_lens` or `inverted_perspective` camera (box filter, RGB film).

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
              "film": {"type": "hdrfilm", "width": W, "height": H, "rfilter": {"type": "box"},
                       "pixel_format": "rgb", "component_format": "float32"},
              "sampler": {"type": sampler, "sample_count": int(spp)}}
    if kind == "ThinLensCamera":
        return {"type": "tilted_thinlens", "w": camera.w, "U": camera.U, "d": camera.d,
                "theta_F": camera.theta_F, "theta_L": camera.theta_L, **common}
    if kind == "InvertedPerspectiveCamera":
        return {"type": "inverted_perspective", "alpha": camera.alpha, "p3": camera.pseudo_screen_distance,
                "q3": float(screen.distance), **common}
    raise NotImplementedError(f"camera {kind} has no Mitsuba sensor plugin")
