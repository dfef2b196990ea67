"""The boxes-on-a-floor scene of the tilt-lens paper's experiment (§4.2, Figs. 10–13), in millimetres.

The paper photographs boxes standing on a floor with a Canon EOS 6D and a TS-E 45 mm lens at f/2.8,
focused at about U = 618 mm, with the lens at θL = 0, +5° and −5°, and re-renders the scene as CG with the
calibrated lens. Its exact layout is not published; this one is built so that the same effects show:

- the camera looks 30° down at the floor; the optical axis meets the floor at U0 = 618.4 mm, the stage-1
  focus distance, so the floor at the image centre is sharp at θL = 0;
- four boxes between about 450 and 800 mm from the lens, so that no flat plane of focus holds all of
  them and tilting the plane of focus (θL = ±5° gives θF ≈ ±45°) visibly moves the sharp region;
- a checkered floor and checkered box faces, so every profile line crosses edges whose blur can be
  read off the brightness profile;
- a key light, a fill light and a little ambient light (cast shadows add more edges).

World frame: the project's camera convention, right-handed: X right, Y down, Z away from the camera. The
floor is the plane Y = 0, the boxes stand on it at Y < 0 and the lens centre sits at (0, −U0 sin 30°, 0).
The camera frame (x right, y down, z forward) is this frame pitched 30° down, and the plane of focus is
z = U + y tan θF in it, with y pointing down the image.

Scenes are built as scene-file dicts (`boxes_scene_dict`, the format of `renderer render`), so each one can
be written to JSON and rendered again from the command line, and loaded with `renderer`'s scene loader.
"""
from __future__ import annotations

import math

import numpy as np
from renderer import Lens, Sensor, load_scene
from renderer.cameras import EOS_6D

# Where the scene sits relative to the camera (see the module docstring).
FOCUS_DISTANCE_MM = Lens.paper().U  # stage-1 U of the paper: the optical axis meets the floor this far away
CAMERA_DEPRESSION_DEG = 30.0    # the optical axis points this far below the horizontal


# The paper's camera's sensor is `EOS_6D` (Canon EOS 6D: 5472 × 3648, 6.54 µm pixels); lens states are `renderer.Lens`.
__all__ = ["EOS_6D", "Lens", "Sensor", "boxes_scene", "boxes_scene_dict", "camera_pose", "profile_lines"]


def camera_pose() -> dict:
    """`position`, `look_at`, `up` of the camera in the world frame (mm): 30° down, axis meets the floor
    at FOCUS_DISTANCE_MM."""
    a = math.radians(CAMERA_DEPRESSION_DEG)
    return {"position": [0.0, -FOCUS_DISTANCE_MM * math.sin(a), 0.0],
            "look_at": [0.0, 0.0, FOCUS_DISTANCE_MM * math.cos(a)],
            "up": [0.0, -1.0, 0.0]}


def _checker(size_mm, a, b):
    return {"type": "checker", "size": size_mm, "colors": [list(a), list(b)]}


# Boxes: (name, centre on the floor (X, Z), size (sx, sy, sz), rotation about Y in degrees, material).
_BOXES = [
    ("box_near", (-105.0, 450.0), (75.0, 70.0, 75.0), 20.0,
     {"texture": _checker(12.5, (0.05, 0.12, 0.45), (0.85, 0.85, 0.8))}),
    ("box_small", (135.0, 470.0), (45.0, 45.0, 45.0), 40.0, {"color": [0.8, 0.65, 0.1]}),
    ("box_mid", (45.0, 590.0), (85.0, 95.0, 85.0), -25.0,
     {"texture": _checker(15.0, (0.75, 0.3, 0.05), (0.08, 0.06, 0.05))}),
    ("box_far", (-75.0, 770.0), (100.0, 140.0, 90.0), 10.0,
     {"texture": _checker(20.0, (0.1, 0.45, 0.12), (0.85, 0.85, 0.85))}),
]


def scene_objects() -> list[dict]:
    """The floor and the boxes as scene-file `objects` entries (mm, world frame of the module docstring)."""
    objects = [{"name": "floor",
                "shape": {"type": "plane", "point": [0.0, 0.0, 0.0], "normal": [0.0, -1.0, 0.0]},
                "material": {"texture": _checker(20.0, (0.75, 0.75, 0.72), (0.12, 0.12, 0.12))}}]
    for name, (x, z), size, rot_y, material in _BOXES:
        objects.append({"name": name,
                        "shape": {"type": "box", "center": [x, -size[1] / 2, z], "size": list(size),
                                  "rotation_deg": [0.0, rot_y, 0.0]},
                        "material": dict(material)})
    return objects


def scene_lights() -> list[dict]:
    """A key light up and to the left, a weaker fill from the right, a little ambient light (linear RGB)."""
    return [{"type": "point", "position": [-250.0, -750.0, 250.0], "intensity": [1.6e6, 1.6e6, 1.5e6]},
            {"type": "point", "position": [400.0, -450.0, 50.0], "intensity": [3.0e5, 3.0e5, 3.2e5]},
            {"type": "ambient", "intensity": [0.04, 0.04, 0.045]}]


def boxes_scene_dict(lens: Lens, sensor: Sensor = EOS_6D, downscale: int = 16, spp: int = 16,
                     sampler: str = "sobol") -> dict:
    """The boxes scene seen through a (tilted) thin lens, as a scene-file dict.

    Args:
        lens: the lens state (w, U, d, θF; its own sensor, if any, is not used).
        sensor: the camera's sensor [EOS 6D].
        downscale: pixel binning; the image is (W // k) x (H // k) pixels covering the same sensor (the
            blur in pixels shrinks by k) [16: 342 x 228].
        spp, sampler: samples per pixel and sample pattern stored in the `image` section.
    Returns:
        dict with `description`, `image`, `camera` (type `thin_lens`), `lights`, `objects`.
    """
    binned = sensor.binned(downscale)
    keys = {k: v for k, v in lens.scene_keys().items() if k not in ("sensor_size", "principal_point_px")}
    camera = {**keys, **camera_pose(), "sensor_size": list(binned.size)}
    return {
        "description": "Boxes on a checkered floor (tilt-lens paper, Sec. 4.2), mm; tiltfit.experiments.scenes.",
        "image": {"width": binned.width_px, "height": binned.height_px, "spp": spp, "max_depth": 1, "sampler": sampler},
        "camera": camera,
        "lights": scene_lights(),
        "objects": scene_objects(),
    }


def boxes_scene(lens: Lens, sensor: Sensor = EOS_6D, downscale: int = 16, spp: int = 16,
                sampler: str = "sobol"):
    """The boxes scene as a `renderer.Scene` (see `boxes_scene_dict` for the arguments)."""
    return load_scene(boxes_scene_dict(lens, sensor, downscale, spp, sampler))


# The profile lines of Fig. 13, as fractions of the image width and height (0 = left/top edge of the
# image, 1 = right/bottom edge), so that they fall on the same scene points at every resolution.
# red: top to bottom over the far floor, box_mid's front and the near floor (depth changes along it, so
#   a tilt of the plane of focus moves the sharp part along the line);
# green: across box_near, the floor and box_small, with a bend (depth nearly constant along the first leg).
_LINES_FRACTION = {
    "red": [(0.62, 0.05), (0.62, 0.95)],
    "green": [(0.04, 0.56), (0.55, 0.56), (0.96, 0.50)],
}


def profile_lines(width_px: int, height_px: int) -> dict[str, np.ndarray]:
    """The red and green profile lines for a W x H image, in pixels.

    A fraction f of the image width maps to x = f · W − 0.5, since (0, 0) is the centre of the top-left
    pixel and the image's left edge is at x = −0.5.
    Returns:
        {"red": (K, 2) array, "green": (K, 2) array} of (x, y) vertices, pixels.
    """
    out = {}
    for name, pts in _LINES_FRACTION.items():
        f = np.asarray(pts, dtype=np.float64)
        out[name] = np.stack([f[:, 0] * width_px - 0.5, f[:, 1] * height_px - 0.5], -1)
    return out
