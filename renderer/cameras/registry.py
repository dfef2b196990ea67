"""The camera registry: every camera module registers its class under a name (`register_camera`), and
`build_camera` validates a scene file's `camera` section against the pose parameters and the camera's own
`PARAMS` and builds it. The package (`renderer.cameras`) imports every camera module, so all are registered
once it is imported."""
from __future__ import annotations

from renderer.core.params import Param, SceneError, parse_params
from renderer.core.transforms import CameraTransform
from .base import Camera

CAMERAS: dict[str, tuple[list[Param], object]] = {}

POSE_PARAMS = [
    Param("position", "vec3", (0.0, 0.0, 0.0), "viewpoint, scene units"),
    Param("look_at", "vec3", (0.0, 0.0, 1.0), "point the optical axis passes through"),
    Param("up", "vec3", (0.0, -1.0, 0.0), "world direction shown upwards in the image"),
]

SCREEN_PARAMS = [
    Param("screen_distance", "float", 1.0, "q3: screen distance from the viewpoint, scene units"),
    Param("screen_size", "vec2", None, "[width, height] of the screen, scene units"),
    Param("fov_deg", "float", None, "horizontal field of view (instead of screen_size), degrees"),
]


def register_camera(name: str, params: list[Param]):
    """Class decorator: register a camera class (with a `from_config` classmethod) under `name`."""

    def deco(cls):
        CAMERAS[name] = (params, cls)
        return cls

    return deco


def camera_class(kind: str):
    """The registered class of camera type `kind` (plugins loaded if needed), or None."""
    if kind not in CAMERAS:
        from renderer.scene.plugins import load_plugins

        load_plugins()
    entry = CAMERAS.get(kind)
    return None if entry is None else entry[1]


def build_camera(path: str, cfg: dict, width: int, height: int) -> Camera:
    """Validate the `camera` section and build the camera it names (`type`)."""
    if not isinstance(cfg, dict):
        raise SceneError(f"{path}: expected an object, got {cfg!r}")
    kind = cfg.get("type", "pinhole")
    if kind not in CAMERAS:
        from renderer.scene.plugins import load_plugins

        load_plugins()
    if kind not in CAMERAS:
        raise SceneError(f"{path}.type: unknown camera {kind!r} (expected one of: {', '.join(sorted(CAMERAS))})")
    params, cls = CAMERAS[kind]
    parsed = parse_params(path, cfg, POSE_PARAMS + params, ignore=("type",))
    if parsed["position"] == parsed["look_at"]:
        raise SceneError(f"{path}.look_at: equals camera.position {list(parsed['position'])}, so there is no "
                         "viewing direction")
    try:
        transform = CameraTransform.look_at(parsed["position"], parsed["look_at"], parsed["up"])
    except ValueError as e:
        raise SceneError(f"{path}: {e}") from None
    return cls.from_config(path, parsed, transform, width, height)
