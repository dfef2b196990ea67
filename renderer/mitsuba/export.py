"""Convert a renderer `Scene` into a Mitsuba 3 scene dict, to time and cross-check against a named peer.

What carries over (exactly, up to tessellation where noted):
- camera: `pinhole` (pose, horizontal field of view, square pixels, centred principal point) as a Mitsuba
  `perspective` sensor with a box pixel filter, so pixel (x, y) of both images covers the same solid angle;
  an untilted `thin_lens` with square pixels and centred principal point as Mitsuba's `thinlens`
  (aperture_radius d/2, focus_distance U); a tilted thin lens (or any thin lens), the `inverted_perspective`
  camera, the `orthographic` camera and any other pinhole (its α = 1 and α = 0 cases), and any camera with
  a lens distortion (each pixel traced through its undistorted position) through our sensor plugins
  (`renderer.mitsuba.sensors`);
- lights: `point` (radiant intensity, 1/r² fall-off in both); `ambient` (intensity · albedo, no shadows)
  added after the render from Mitsuba's albedo AOV of the first hit (`develop`);
- the background colour: composited after the render where Mitsuba's alpha says the camera ray missed
  (`develop`), as ours adds it where the primary ray hits nothing;
- shapes: `sphere`, `cylinder` (Mitsuba's open cylinder plus two disc caps), `rectangle`, `box`,
  `polyhedron` and `mesh` (their exact triangles), `csg` (the triangles of its boundary: each leaf's faces
  cut by the other leaves' planes, kept where the solid changes across them), `plane` (a square covering
  what the camera sees of the plane and the feet of the lights and objects on it, see `plane_pieces`),
  `cone` (triangles, `segments` around the axis, smooth side normals);
- materials: Lambert with reflectance (1 − reflect − transmit) · diffuse · albedo, two-sided as the
  renderer shades both sides of every surface; with a Phong highlight (which Mitsuba 3 lacks), or a diffuse
  weight other than 1 under ambient light, our `renderer_phong` plugin (`renderer.mitsuba.bsdfs`). The
  albedo is the colour, a checker texture (Mitsuba's `checkerboard`) or an image texture (Mitsuba's
  `bitmap`, bilinear, repeated, linear values): each shape's Mitsuba uv is mapped onto our texture
  coordinates (an affine `to_uv`; the sphere and cylinder turned so that their seams fall where ours do;
  triangle meshes carry our uv at their vertices), so checker cells and image texels land where ours do.
What does not: mirror reflection and refraction (the `direct` integrator follows no secondary rays; the
local term keeps its weight 1 − reflect − transmit, so only the reflected and refracted light is missing,
and a transparent object casts a full shadow), and layers; `to_mitsuba` names what it dropped in the
returned `dropped` list, and raises NotImplementedError for a camera it cannot express.

Frames. Mitsuba's camera looks along its local +z with +x to the left and +y up in the image; ours looks
along +z with x right and y down (OpenCV). So the sensor's to_world has columns (−x_cam, −y_cam, z_cam,
position) in world coordinates, which keeps the image unmirrored (checked in `benchmarks/renderer/bench_fig6_mitsuba.py`
by comparing the two images). Our sensor plugins work in our camera frame and need no flip.

Mitsuba is an optional extra (`pip install -e '.[test]'` or `'.[bench]'`); it is imported on first use.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from renderer.core.transforms import world_from_local_4x4 as _matrix

from .shapes import shape_dicts
from .variants import load_mitsuba


def _native_lens(camera) -> bool:
    """Whether Mitsuba's own `perspective` / `thinlens` sensor reproduces the camera (square pixels, centred
    principal point, untilted, no lens distortion)."""
    kind = type(camera).__name__
    if kind not in ("PinholeCamera", "ThinLensCamera"):
        return False
    (px, py), screen = camera.screen.pitch, camera.screen
    square = abs(px - py) <= 1e-9 * max(px, py)
    undistorted = camera.distortion is None or camera.distortion.is_identity
    return (square and undistorted and screen.principal_point_px is None
            and (kind == "PinholeCamera" or camera.lens.theta_F == 0))


def _sensor(mi, camera, spp: int, plugin: bool = False):
    """Mitsuba sensor dict: Mitsuba's own sensor where it matches the camera exactly (a thin lens: unless
    `plugin`), else our plugin (`renderer.mitsuba.sensors`)."""
    kind = type(camera).__name__
    if not _native_lens(camera) or (plugin and kind != "PinholeCamera"):
        from .sensors import sensor_dict

        return sensor_dict(mi, camera, spp)
    screen = camera.screen
    W, H = screen.width_px, screen.height_px
    q3 = screen.distance
    R = camera.transform.world_from_camera.numpy()
    t = camera.transform.position.numpy()
    to_world = _matrix(np.stack([-R[:, 0], -R[:, 1], R[:, 2]], axis=1), t)
    lens = {"type": "perspective"}
    if kind == "ThinLensCamera" and camera.lens.d > 0:
        lens = {"type": "thinlens", "aperture_radius": camera.lens.d / 2, "focus_distance": camera.lens.U}
    return {
        **lens,
        "fov_axis": "x",
        "fov": math.degrees(2 * math.atan(screen.size[0] / 2 / q3)),
        "to_world": mi.ScalarTransform4f(to_world),
        "film": {"type": "hdrfilm", "width": W, "height": H, "rfilter": {"type": "box"},
                 "pixel_format": "rgb", "component_format": "float32"},
        "sampler": {"type": "independent", "sample_count": spp},
    }


# --------------------------------------------------------------------------------------------------- scene


def to_mitsuba(scene, spp: int | None = None, integrator: dict | None = None, *, variant: str | None = None,
               plane_size: float | None = None, segments: int = 256, plugin_sensor: bool = False):
    """Mitsuba scene dict for `scene` (see the module docstring for what carries over).

    Args:
        spp: samples per pixel [scene.image.spp].
        integrator: Mitsuba integrator dict [direct lighting, one emitter sample, no BSDF samples]; wrapped in
            an `aov` integrator adding the albedo where the scene has ambient light.
        plane_size: side of the square standing in for an infinite plane, scene units, centred on the
            plane's point [None: rectangles sized and placed by `plane_pieces`].
        segments: facets around the axis of a cone (and of a textured cylinder's caps).
        variant: Mitsuba variant to set [None: the current one, else the default, see `load_mitsuba`].
        plugin_sensor: use our sensor plugin even where Mitsuba's own sensor matches (pinhole excepted).
    Returns:
        (scene_dict, dropped): the dict for `mitsuba.load_dict`, and a list of what could not be expressed.
        Pass what `mitsuba.render` makes of the dict through `develop` for the image.
    Raises:
        NotImplementedError: a camera or shape type with no Mitsuba counterpart (one line).
    """
    mi = load_mitsuba(variant)
    dropped: list[str] = []
    integrator = integrator or {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0}
    ambient = [light for light in scene.lights if light.type == "ambient" and any(light.intensity)]
    if ambient:
        integrator = {"type": "aov", "aovs": "albedo:albedo", "integrator": integrator}
    try:
        sensor = _sensor(mi, scene.camera, scene.image.spp if spp is None else spp, plugin_sensor)
    except NotImplementedError as e:
        raise NotImplementedError(f"mitsuba export: {e}") from None
    if ambient or any(scene.image.background):  # the alpha channel tells where the camera ray hit nothing
        sensor["film"]["pixel_format"] = "rgba"
    out = {"type": "scene", "integrator": integrator, "sensor": sensor}
    if not _distortion_inverts(scene.camera):
        dropped.append("camera.distortion beyond its invertible zone (ours averages a pixel's valid samples, "
                       "Mitsuba counts the others black)")
    if scene.layers:
        dropped.append("layers")
    for i, light in enumerate(scene.lights):
        if light.type == "point":
            out[f"light_{i}"] = {"type": "point", "position": list(light.position),
                                 "intensity": {"type": "rgb", "value": list(light.intensity)}}
        elif light.type != "ambient":
            dropped.append(f"lights[{i}]: type {light.type}")
    out.update(shape_dicts(mi, scene, dropped, plane_size=plane_size, segments=segments, tessellate=True))
    return out, dropped


def _distortion_inverts(camera, step_px: float = 0.25) -> bool:
    """Whether the camera's lens distortion (if any) inverts at every point of the image's border, sampled
    every `step_px` pixels: where it does not (beyond the zone where the model is monotonic, which grows from
    the centre), our camera gives a sample no ray and the pixel the mean of the others, and Mitsuba's film
    counts it as black."""
    if camera.distortion is None or camera.distortion.is_identity:
        return True
    x0, y0, x1, y1 = -0.5, -0.5, camera.width - 0.5, camera.height - 0.5
    xs = np.arange(x0, x1 + step_px, step_px).clip(max=x1)
    ys = np.arange(y0, y1 + step_px, step_px).clip(max=y1)
    border = np.concatenate([np.stack([xs, np.full_like(xs, y0)], -1), np.stack([xs, np.full_like(xs, y1)], -1),
                             np.stack([np.full_like(ys, x0), ys], -1), np.stack([np.full_like(ys, x1), ys], -1)])
    with torch.no_grad():
        _, ok = camera.undistort_pixels(torch.as_tensor(border))
    return bool(ok.all())


def develop(scene, raw) -> np.ndarray:
    """The (H, W, 3) linear RGB image from what `mitsuba.render` made of `to_mitsuba(scene)`'s dict: its RGB,
    plus the background colour where the camera rays missed (1 − alpha) and each ambient light's intensity
    times the albedo AOV, as our tracer adds them."""
    raw = np.asarray(raw, dtype=np.float32)
    image = raw[..., :3].copy()
    if any(scene.image.background):
        image += (1.0 - raw[..., 3:4]) * np.asarray(scene.image.background, dtype=np.float32)
    for light in scene.lights:
        if light.type == "ambient" and any(light.intensity):
            image += raw[..., -3:] * np.asarray(light.intensity, dtype=np.float32)
    return image
