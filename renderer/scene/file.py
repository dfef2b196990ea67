"""Scene files: JSON in, a validated `Scene` out (every key is listed in docs/file_formats.md).

A scene file is one JSON object with the sections

| key | required | meaning |
|---|---|---|
| `image` | yes | `width`, `height` (pixels), `spp` [1], `max_depth` [5], `background` [[0,0,0]], `sampler` ["sobol"] |
| `camera` | yes | `type` [pinhole] and that camera's keys (see `renderer.cameras`) |
| `lights` | no | list of `{type: "point", position, intensity}` or `{type: "ambient", intensity}` |
| `objects` | no | list of `{name, shape: {type, ...}, material: {...}}`; names are unique |
| `layers` | no | mixed-projection layers (see `renderer.cameras.layers`) |
| `extends` | no | another scene file (relative to this one) this file is merged onto |
| `description` | no | free text for the reader |
| `animation` | no | `{frames, step}`: defaults for `renderer animate` (see `ANIMATION_PARAMS`) |

`extends` merges objects key by key (this file wins) and replaces everything else (lists included), so
a variant states only what differs from its base (relative file names inside are still resolved against
the folder of the file being loaded). `--set key.path=value` overrides are applied after the
merge and before validation: the value is parsed as JSON (falling back to a plain string), list elements
are addressed by index (`objects.2.material.color`) or by their `name` (`objects.plate.material.color`),
and a path into a missing section creates it.

Every problem raises `SceneError` with one line naming the file and the field, e.g.
`scene.json: objects[3].material.ior: expected a number, got 'glass'`. The file-level checks (encoding,
nesting depth, numbers finite and within float32, `extends` chain length, `--set` path length) are
`camio.checks`'s; the image limits are `MAX_IMAGE_SIDE`, `MAX_SPP` and `MAX_DEPTH` below.
"""
from __future__ import annotations

import copy
import dataclasses
import json
import os

import numpy as np

from renderer.cameras import build_camera
from camio.files import ImageIOError, read_image
from renderer.scene.materials import CheckerTexture, ImageTexture, Material
from renderer.core import params
from renderer.core.params import Param, SceneError, check_value, parse_params
from renderer.tracing.sampling import SAMPLERS
from camio.checks import MAX_JSON_DEPTH, MAX_SET_SEGMENTS, check_memory, check_tree, json_depth, merge, read_json
from camio.checks import read_scene_json  # noqa: F401 - owned there (no torch: the command line checks files first)
from renderer.scene.model import ImageSettings, Light, Scene, SceneObject
from renderer.shapes import build_shape

SECTIONS = ("image", "camera", "lights", "objects", "layers", "extends", "description", "animation")

# Stated limits of the image section: beyond them a render is a mistake, not a picture (a 65536-pixel side,
# 65536 samples per pixel, 64 bounces already mean hours or a mirror hall that converges long before).
MAX_IMAGE_SIDE = 1 << 16
MAX_SPP = params.MAX_SPP
MAX_DEPTH = 64
MAX_SHININESS = 1e6
# Peak bytes per pixel of a render (image, coverage, tile order and its sort keys), for the memory check.
BYTES_PER_PIXEL = 96

IMAGE_PARAMS = [
    Param("width", "int", doc=f"image width, pixels (at most {MAX_IMAGE_SIDE})"),
    Param("height", "int", doc=f"image height, pixels (at most {MAX_IMAGE_SIDE})"),
    Param("spp", "int", 1, f"samples per pixel, at most {MAX_SPP}"),
    Param("max_depth", "int", 5, f"secondary bounces (reflection, refraction) per path, at most {MAX_DEPTH}"),
    Param("background", "color", (0.0, 0.0, 0.0), "linear RGB seen by rays that hit nothing"),
    Param("sampler", "str", "sobol", "pixel and lens sample pattern", SAMPLERS),
]

LIGHT_PARAMS = {
    "point": [
        Param("position", "vec3", doc="scene units"),
        Param("intensity", "color", doc="linear RGB radiant intensity; irradiance falls off as 1/r²"),
    ],
    "ambient": [Param("intensity", "color", doc="linear RGB, added as intensity · albedo, no shadows")],
}

MATERIAL_PARAMS = [
    Param("color", "color", (0.8, 0.8, 0.8), "linear RGB albedo; also tints transmitted light"),
    Param("diffuse", "float", 1.0, "Lambertian weight"),
    Param("specular", "float", 0.0, "Phong highlight weight"),
    Param("shininess", "float", 32.0, f"Phong exponent, at most {MAX_SHININESS:g}"),
    Param("reflect", "float", 0.0, "mirror reflection weight"),
    Param("transmit", "float", 0.0, "transparency weight"),
    Param("ior", "float", 1.0, "index of refraction of the inside"),
    Param("texture", "dict", None, "checker or image texture replacing `color`"),
]

TEXTURE_PARAMS = {
    "checker": [
        Param("size", "float", doc="cell size, scene units (in the shape's uv coordinates)"),
        Param("colors", "list", [[0.9, 0.9, 0.9], [0.1, 0.1, 0.1]], "the two linear RGB colours"),
    ],
    "image": [
        Param("file", "str", doc="image file, relative to the scene file"),
        Param("size", "any", doc="scene units covered by one copy: a number or [sx, sy]"),
        Param("encoding", "str", None, "srgb or linear [8-bit files sRGB, others linear]", ("srgb", "linear")),
    ],
}

ANIMATION_PARAMS = [
    Param("frames", "int", doc="number of frames, >= 1"),
    Param("step", "float", doc="camera move per frame along its view direction, scene units"),
]


def parse_animation(cfg) -> dict:
    """The validated `animation` section ({frames, step}), or {} when the scene has none."""
    if cfg.get("animation") is None:
        return {}
    p = parse_params("animation", cfg["animation"], ANIMATION_PARAMS)
    if not 1 <= p["frames"] <= MAX_ANIMATION_FRAMES:
        raise SceneError(f"animation.frames: expected an integer in 1..{MAX_ANIMATION_FRAMES}, got {p['frames']}")
    return p


def _check_distortion_inverse(camera, width: int, height: int, grid: int = 33) -> None:
    """Refuse a lens distortion under which no pixel has an undistorted direction (the image would be all
    background): rays are generated on a grid of up to grid × grid pixel centres."""
    import torch

    if camera.distortion is None or camera.distortion.is_identity:
        return
    xs = torch.linspace(0, width - 1, min(width, grid), dtype=torch.float64)
    ys = torch.linspace(0, height - 1, min(height, grid), dtype=torch.float64)
    uv = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), dim=-1).reshape(-1, 2)
    with torch.no_grad():
        rays = camera.generate_rays(uv)
        ok = rays.valid & torch.isfinite(rays.direction).all(-1)
    if not bool(ok.any()):
        raise SceneError("camera.distortion: no pixel of the image has an undistorted direction (the distortion "
                         "has no inverse there; check the coefficients' size and sign)")


def require_objects(path: str, scene) -> None:
    """Refuse to render a scene without objects (`build_scene` accepts one, for its camera alone)."""
    if not scene.objects:
        raise SceneError(f"{path}: objects: the scene has no objects; add at least one to render it")


# The most frames one animation renders (the command line's limit on counts, renderer.cli.main.MAX_COUNT).
MAX_ANIMATION_FRAMES = 1 << 16


OBJECT_PARAMS = [
    Param("name", "str", doc="unique name (layers refer to objects by name)"),
    Param("shape", "dict", doc="{type, ...} (see renderer.shapes)"),
    Param("material", "dict", {}, "see MATERIAL_PARAMS"),
]


# ----------------------------------------------------------------------------------------------- reading


def parse_override(text: str) -> tuple[list[str], object]:
    """'a.b.2.c=value' -> (['a', 'b', '2', 'c'], value parsed as JSON, else the raw string)."""
    key, sep, raw = text.partition("=")
    keys = key.strip().split(".")
    shown = text if len(text) <= 60 else text[:57] + "..."
    if not sep or not all(keys):
        raise SceneError(f"--set {shown}: expected key.path=value, e.g. camera.alpha=2")
    if len(keys) > MAX_SET_SEGMENTS:
        raise SceneError(f"--set {shown}: a path of {len(keys)} keys; at most {MAX_SET_SEGMENTS} are allowed")
    if json_depth(raw) > MAX_JSON_DEPTH:
        raise SceneError(f"--set {shown}: value nested deeper than {MAX_JSON_DEPTH} levels")
    try:
        value = json.loads(raw)
    except ValueError:
        value = raw
    return keys, value


def apply_override(cfg: dict, text: str) -> None:
    """Apply one `--set key.path=value` to the raw scene dict in place (see the module docstring)."""
    keys, value = parse_override(text)
    node, where = cfg, ""
    for i, key in enumerate(keys):
        last = i == len(keys) - 1
        here = f"{where}.{key}" if where else key
        if isinstance(node, list):
            index = _list_index(node, key)
            if index is None:
                raise SceneError(f"--set {text}: {where} has no element {key!r} "
                                 f"(give an index 0..{len(node) - 1} or an element's name)")
            if last:
                node[index] = value
            else:
                if not isinstance(node[index], (dict, list)):
                    node[index] = {}
                node = node[index]
        elif isinstance(node, dict):
            if last:
                node[key] = value
            else:
                if key not in node or node[key] is None:
                    node[key] = {}
                elif not isinstance(node[key], (dict, list)):
                    raise SceneError(f"--set {text}: {here} is {node[key]!r}, not a section or list")
                node = node[key]
        where = here


def _list_index(node: list, key: str) -> int | None:
    if key.lstrip("-").isdigit():
        i = int(key)
        return i if 0 <= i < len(node) else None
    for i, item in enumerate(node):
        if isinstance(item, dict) and item.get("name") == key:
            return i
    return None


def _check_finite(value, path: str) -> None:
    """Reject NaN, ±inf, integers too large for a float and magnitudes outside float32 anywhere (Python's
    JSON reader accepts them all; the tracer computes in float32), and nesting beyond MAX_JSON_DEPTH."""
    check_tree(value, path, SceneError, float32=True)


# -------------------------------------------------------------------------------------------- validating


def load_scene(source, overrides=(), base_dir: str | None = None) -> Scene:
    """Read, override and validate a scene; build its camera, shapes, materials, lights and layers.

    Args:
        source: path of a JSON scene file, or the scene as a dict (not modified).
        overrides: `key.path=value` strings, applied in order before validation.
        base_dir: folder that relative file names (meshes, textures) are resolved against
            [the scene file's folder, or the working directory for a dict].
    Returns:
        The Scene.
    Raises:
        SceneError: one line naming the file and the field.
    """
    if isinstance(overrides, str):
        overrides = [overrides]
    if isinstance(source, dict):
        check_tree(source, "", SceneError)  # depth first: deepcopy and merge recurse
        name, cfg = None, copy.deepcopy(source)
        base_dir = base_dir or "."
    else:
        name = os.fspath(source)
        cfg = read_scene_json(name)
        base_dir = base_dir or os.path.dirname(os.path.abspath(name))
    try:
        if not isinstance(cfg, dict):
            raise SceneError(f"expected an object at the top level, got {cfg!r}")
        for text in overrides:
            apply_override(cfg, text)
        cfg.pop("extends", None)
        return build_scene(cfg, base_dir)
    except SceneError as e:
        raise SceneError(f"{name}: {e}" if name else str(e)) from None


def build_scene(cfg: dict, base_dir: str = ".") -> Scene:
    """Validate an already merged and overridden scene dict and build the Scene (messages without file)."""
    _check_finite(cfg, "")
    for key in cfg:
        if key not in SECTIONS:
            raise SceneError(f"{key}: unknown key (expected one of: {', '.join(SECTIONS)})")
    if "description" in cfg:
        check_value("description", "str", cfg["description"])
    parse_animation(cfg)
    for key in ("image", "camera"):
        if key not in cfg:
            raise SceneError(f"{key}: missing required section")
    camera_cfg = cfg["camera"]
    if isinstance(camera_cfg, dict) and isinstance(camera_cfg.get("file"), str):  # files beside the scene
        camera_cfg = {**camera_cfg, "file": os.path.join(base_dir, os.path.expanduser(camera_cfg["file"]))}
    image = ImageSettings(**_positive_image(parse_params("image", _image_size_from_camera(cfg["image"], camera_cfg),
                                                         IMAGE_PARAMS)))
    distortion = camera_cfg.get("distortion") if isinstance(camera_cfg, dict) else None
    if isinstance(camera_cfg, dict) and "distortion" in camera_cfg:
        camera_cfg = {k: v for k, v in camera_cfg.items() if k != "distortion"}
    camera = build_camera("camera", camera_cfg, image.width, image.height)
    if distortion is not None:
        from renderer.cameras.distortion import distortion_from_config

        parsed = distortion_from_config("camera.distortion", distortion)
        lens = getattr(camera, "lens", None)
        if lens is not None:  # a thin lens's distortion is its lens's (about its own axis where the file says so)
            camera.lens = lens.with_(distortion=parsed.coefficients, distortion_centre=distortion.get("centre", "sensor"))
        else:
            camera.distortion = parsed
        _check_distortion_inverse(camera, image.width, image.height)
    lights = [_light(f"lights[{i}]", c) for i, c in enumerate(_list(cfg, "lights"))]
    objects = []
    first_use: dict[str, int] = {}
    for i, c in enumerate(_list(cfg, "objects")):
        path = f"objects[{i}]"
        obj = _object(path, c, base_dir)
        if obj.name in first_use:
            raise SceneError(f"{path}.name: duplicate name {obj.name!r} (also objects[{first_use[obj.name]}])")
        first_use[obj.name] = i
        objects.append(obj)
    layers = []
    if cfg.get("layers") is not None:
        layer_cfgs = check_value("layers", "list", cfg["layers"])
        if layer_cfgs:
            try:
                from renderer.cameras.layers import build_layers
            except ModuleNotFoundError as e:
                if e.name != f"{__package__}.cameras.layers":
                    raise
                raise SceneError("layers: mixed-projection layers are not available in this version") from None
            layers = build_layers("layers", layer_cfgs, [o.name for o in objects], camera, cfg["camera"])
    return Scene(objects=objects, lights=lights, camera=camera, image=image, layers=layers)


def _image_size_from_camera(image_cfg, camera_cfg):
    """The `image` section with `width` and `height` filled in from the camera where it has a size of its own
    (a calibrated camera: the calibration's image) and the scene gives none."""
    if not isinstance(image_cfg, dict) or not isinstance(camera_cfg, dict) or \
            ("width" in image_cfg and "height" in image_cfg):
        return image_cfg
    from renderer.cameras.registry import camera_class

    cls = camera_class(str(camera_cfg.get("type", "pinhole")))
    size = getattr(cls, "image_size", None)
    if size is None:
        return image_cfg
    W, H = size("camera", camera_cfg)
    if "width" in image_cfg:  # the other side of the same aspect ratio
        return {**image_cfg, "height": max(1, round(image_cfg["width"] * H / W))} \
            if isinstance(image_cfg["width"], int) else image_cfg
    if "height" in image_cfg:
        return {**image_cfg, "width": max(1, round(image_cfg["height"] * W / H))} \
            if isinstance(image_cfg["height"], int) else image_cfg
    return {**image_cfg, "width": W, "height": H}


def _list(cfg: dict, key: str) -> list:
    return check_value(key, "list", cfg.get(key, []))


def _positive_image(p: dict) -> dict:
    for key, low, high in (("width", 1, MAX_IMAGE_SIDE), ("height", 1, MAX_IMAGE_SIDE), ("spp", 1, MAX_SPP),
                           ("max_depth", 0, MAX_DEPTH)):
        if p[key] < low:
            raise SceneError(f"image.{key}: expected an integer >= {low}, got {p[key]}")
        if p[key] > high:
            raise SceneError(f"image.{key}: expected an integer <= {high}, got {p[key]}")
    check_memory("image", p["width"] * p["height"] * BYTES_PER_PIXEL, SceneError,
                 f"a {p['width']}x{p['height']} image")
    return p


def _typed(path: str, cfg, table: dict) -> tuple[str, dict]:
    """Validate a `{type, ...}` dict against `table[type]` (a list of Params)."""
    if not isinstance(cfg, dict):
        raise SceneError(f"{path}: expected an object, got {cfg!r}")
    if "type" not in cfg:
        raise SceneError(f"{path}.type: missing required key (one of: {', '.join(table)})")
    kind = cfg["type"]
    if kind not in table:
        raise SceneError(f"{path}.type: expected one of {', '.join(table)}, got {kind!r}")
    return kind, parse_params(path, cfg, table[kind], ignore=("type",))


def _light(path: str, cfg) -> Light:
    kind, p = _typed(path, cfg, LIGHT_PARAMS)
    if min(p["intensity"]) < 0:
        raise SceneError(f"{path}.intensity: expected non-negative values, got {list(p['intensity'])}")
    return Light(kind, p["intensity"], p.get("position"))


def _object(path: str, cfg, base_dir: str) -> SceneObject:
    p = parse_params(path, cfg, OBJECT_PARAMS)
    shape = build_shape(f"{path}.shape", p["shape"], base_dir)
    material = build_material(f"{path}.material", p["material"], base_dir)
    own = getattr(shape, "texture", None)  # a shape that brings its own albedo (a calibration target's print)
    if own is not None and material.texture is None and "color" not in p["material"]:
        material = dataclasses.replace(material, texture=own)
    return SceneObject(p["name"], shape, material)


def build_material(path: str, cfg: dict, base_dir: str = ".") -> Material:
    """Validate a `material` section (weights in [0, 1], reflect + transmit <= 1, ior > 0)."""
    p = parse_params(path, cfg, MATERIAL_PARAMS)
    for key in ("diffuse", "specular", "reflect", "transmit"):
        if not 0.0 <= p[key] <= 1.0:
            raise SceneError(f"{path}.{key}: expected a weight in [0, 1], got {p[key]}")
    if p["reflect"] + p["transmit"] > 1.0 + 1e-9:
        raise SceneError(f"{path}: reflect + transmit must not exceed 1, got {p['reflect'] + p['transmit']}")
    if p["ior"] <= 0:
        raise SceneError(f"{path}.ior: expected a positive index of refraction, got {p['ior']}")
    if not 0 <= p["shininess"] <= MAX_SHININESS:
        raise SceneError(f"{path}.shininess: expected an exponent in [0, {MAX_SHININESS:g}], got {p['shininess']}")
    if min(p["color"]) < 0:
        raise SceneError(f"{path}.color: expected non-negative values, got {list(p['color'])}")
    texture = None
    if p["texture"] is not None:
        texture = _texture(f"{path}.texture", p["texture"], base_dir)
    return Material(p["color"], p["diffuse"], p["specular"], p["shininess"], p["reflect"], p["transmit"], p["ior"],
                    texture)


def _texture(path: str, cfg, base_dir: str):
    kind, p = _typed(path, cfg, TEXTURE_PARAMS)
    if kind == "checker":
        if p["size"] <= 0:
            raise SceneError(f"{path}.size: expected a positive length, got {p['size']}")
        colors = p["colors"]
        if len(colors) != 2:
            raise SceneError(f"{path}.colors: expected two colours, got {colors!r}")
        return CheckerTexture(p["size"], tuple(check_value(f"{path}.colors[{i}]", "color", c)
                                               for i, c in enumerate(colors)))
    size = p["size"]
    size = check_value(f"{path}.size", "vec2" if isinstance(size, list) else "float", size)
    size = size if isinstance(size, tuple) else (size, size)
    if min(size) <= 0:
        raise SceneError(f"{path}.size: expected positive lengths, got {list(size)}")
    file = os.path.join(base_dir, p["file"])
    try:
        pixels = read_image(file, p["encoding"])
    except ImageIOError as e:
        raise SceneError(f"{path}.file: {e}") from None
    channels = pixels.shape[2]
    rgb = pixels[..., :3] if channels >= 3 else np.repeat(pixels[..., :1], 3, axis=2)
    return ImageTexture(p["file"], size, np.ascontiguousarray(rgb, dtype=np.float32))
