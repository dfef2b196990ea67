"""The scene-file format as data: a JSON Schema and a Markdown reference, both built from the declared `Param`
tables the validator itself uses (`renderer.scene.file`, `renderer.cameras`, `renderer.shapes`), so neither
can drift from the code. `python -m tiltfit.files.formats` writes them, with the calibration formats, into
docs/file_formats.md and docs/schemas/; tests check the committed files equal a fresh build.

The schema is for editors and other tools: it checks structure, types and the stated ranges. The Python
validator is the authority; it also refuses what JSON Schema cannot express (NaN/Infinity literals, integers
too large for a float, non-zero magnitudes that flush to zero in float32, `camera.position == look_at`).
"""
from __future__ import annotations

from renderer.core.params import REQUIRED, Param, params_table
from camio.checks import FLOAT32_MAX, MAX_EXTENDS, MAX_JSON_BYTES, MAX_JSON_DEPTH, MAX_SET_SEGMENTS

SCHEMA_DIALECT = "https://json-schema.org/draft/2020-12/schema"
_NUMBER = {"type": "number", "minimum": -FLOAT32_MAX, "maximum": FLOAT32_MAX}


def _distortion_schema() -> dict:
    from renderer.cameras.distortion import CENTRES, N_COEFFICIENTS

    return {"type": ["object", "null"], "description": "lens distortion, OpenCV's order and normalisation",
            "properties": {"model": {"const": "brown_conrady"},
                           "coefficients": {"type": "array", "items": _NUMBER, "minItems": 1,
                                            "maxItems": N_COEFFICIENTS},
                           "centre": {"enum": list(CENTRES), "description": "sensor: about the principal point "
                                      "[default]; lens_axis: about a thin lens's own (tilted) axis"}},
            "additionalProperties": False}


def param_schema(p: Param) -> dict:
    """JSON Schema of one declared parameter (its kind, choices and documentation)."""
    vec = lambda n: {"type": "array", "items": _NUMBER, "minItems": n, "maxItems": n}  # noqa: E731
    kinds = {
        "float": dict(_NUMBER), "int": {"type": "integer"}, "bool": {"type": "boolean"}, "str": {"type": "string"},
        "vec2": vec(2), "vec3": vec(3), "color": {"oneOf": [dict(_NUMBER, minimum=0), vec(3)]},
        "list": {"type": "array"}, "dict": {"type": "object"}, "any": {},
    }
    out = dict(kinds[p.kind])
    if p.choices:
        out["enum"] = list(p.choices)
    if p.default is not REQUIRED and p.default is not None:
        out["default"] = list(p.default) if isinstance(p.default, tuple) else p.default
    if p.default is None:  # optional without a value: null allowed
        out = {"anyOf": [out, {"type": "null"}]}
    out["description"] = p.doc
    return out


def object_schema(params: list[Param], type_name: str | None = None, extra: dict | None = None) -> dict:
    """An object of these parameters (no other keys); `type_name` adds the `type` discriminator."""
    props = {p.name: param_schema(p) for p in params}
    required = [p.name for p in params if p.default is REQUIRED]
    if type_name is not None:
        props = {"type": {"const": type_name}, **props}
        required = ["type", *required]
    props.update(extra or {})
    return {"type": "object", "properties": props, "required": required, "additionalProperties": False}


def _limits(schema: dict, limits: dict) -> dict:
    for key, bounds in limits.items():
        schema["properties"][key].update(bounds)
    return schema


def scene_schema() -> dict:
    """The JSON Schema of a scene file (draft 2020-12)."""
    from renderer.scene import file as sf
    distortion = _distortion_schema()
    from renderer.cameras import CAMERAS, POSE_PARAMS
    from renderer.scene.plugins import load_plugins
    from renderer.shapes import SHAPES

    load_plugins()  # as `scene_reference`

    image = _limits(object_schema(sf.IMAGE_PARAMS), {
        "width": {"minimum": 1, "maximum": sf.MAX_IMAGE_SIDE}, "height": {"minimum": 1, "maximum": sf.MAX_IMAGE_SIDE},
        "spp": {"minimum": 1, "maximum": sf.MAX_SPP}, "max_depth": {"minimum": 0, "maximum": sf.MAX_DEPTH}})
    cameras = []
    for name, (params, _) in sorted(CAMERAS.items()):
        cam = object_schema(POSE_PARAMS + params, name, {"distortion": distortion})
        cam["required"] = [k for k in cam["required"] if k != "type"]  # type defaults to pinhole
        cameras.append(cam)
    shapes = [object_schema(params, name) for name, (params, _) in sorted(SHAPES.items())]
    textures = [object_schema(params, name) for name, params in sorted(sf.TEXTURE_PARAMS.items())]
    material = object_schema(sf.MATERIAL_PARAMS)
    material["properties"]["texture"] = {"anyOf": [*textures, {"type": "null"}]}
    material["properties"]["shininess"].update({"minimum": 0, "maximum": sf.MAX_SHININESS})
    obj = object_schema(sf.OBJECT_PARAMS)
    obj["properties"]["shape"] = {"oneOf": shapes}
    obj["properties"]["material"] = material
    lights = [object_schema(params, name) for name, params in sorted(sf.LIGHT_PARAMS.items())]
    return {
        "$schema": SCHEMA_DIALECT,
        "$id": "https://unusual-cameras.invalid/schemas/scene.schema.json",
        "title": "renderer scene file",
        "description": "See docs/file_formats.md. Generated by `python -m tiltfit.files.formats`; do not edit.",
        "type": "object",
        "properties": {**{section: {} for section in sf.SECTIONS}, **{
            "image": image, "camera": {"oneOf": cameras}, "lights": {"type": "array", "items": {"oneOf": lights}},
            "objects": {"type": "array", "items": obj}, "layers": {"type": ["array", "null"]},
            "extends": {"type": "string", "description": "base scene file, relative to this one"},
            "description": {"type": "string"},
            **({"animation": object_schema(sf.ANIMATION_PARAMS)} if hasattr(sf, "ANIMATION_PARAMS") else {})}},
        "additionalProperties": False,
    }


def scene_reference() -> str:
    """Markdown reference of the scene file: every section's keys, kinds, defaults and meaning, and the limits."""
    from renderer.scene import file as sf
    from renderer.cameras import CAMERAS, POSE_PARAMS
    from renderer.scene.plugins import load_plugins
    from renderer.shapes import SHAPES

    load_plugins()  # the installed packages' cameras and shapes (tiltfit's calibrated camera and target shape)
    out = ["## Scene files (`renderer render SCENE.json`)", "",
           "JSON, UTF-8. Top-level sections: " + ", ".join(f"`{s}`" for s in sf.SECTIONS) + ". "
           "Schema: [docs/schemas/scene.schema.json](schemas/scene.schema.json).", "",
           "### `image`", "", params_table(sf.IMAGE_PARAMS), "",
           "### `camera`", "", "Every camera takes the pose keys, and an optional `distortion`: `{model: "
           "\"brown_conrady\", coefficients: [k1, k2, p1, p2, k3 (, k4, k5, k6)]}` (OpenCV's order and "
           "normalisation), with `centre: \"lens_axis\"` on a `thin_lens` camera applied in the tilted lens's own "
           "frame, about its axis (OpenCV's tilted model; `centre: \"sensor\"`, the default, is about the "
           "principal point):", "", params_table(POSE_PARAMS), ""]
    for name, (params, _) in sorted(CAMERAS.items()):
        out += [f"#### `type: {name}`", "", params_table(params), ""]
    if hasattr(sf, "ANIMATION_PARAMS"):
        out += ["### `animation`", "", params_table(sf.ANIMATION_PARAMS), ""]
    out += ["### `lights[]`", ""]
    for name, params in sorted(sf.LIGHT_PARAMS.items()):
        out += [f"#### `type: {name}`", "", params_table(params), ""]
    out += ["### `objects[]`", "", params_table(sf.OBJECT_PARAMS), "", "#### `material`", "",
            params_table(sf.MATERIAL_PARAMS), ""]
    for name, params in sorted(sf.TEXTURE_PARAMS.items()):
        out += [f"#### `material.texture`, `type: {name}`", "", params_table(params), ""]
    for name, (params, _) in sorted(SHAPES.items()):
        out += [f"#### `shape`, `type: {name}`", "", params_table(params), ""]
    out += [
        "### Limits and number rules", "",
        f"- A JSON file is at most {MAX_JSON_BYTES >> 20} MiB, UTF-8 (a UTF-8 byte-order mark is accepted), nested at "
        f"most {MAX_JSON_DEPTH} levels; an `extends` chain holds at most {MAX_EXTENDS} files; a `--set` path has at "
        f"most {MAX_SET_SEGMENTS} keys.",
        "- Every number is finite (`NaN`, `Infinity` and integers beyond 1.8e308 are refused) and, because the "
        f"tracer computes in float32, has a magnitude of 0 or between 1.18e-38 and {FLOAT32_MAX:.4g}.",
        f"- `image.width`/`height` ≤ {sf.MAX_IMAGE_SIDE}, `spp` ≤ {sf.MAX_SPP}, `max_depth` ≤ {sf.MAX_DEPTH} "
        f"(recursion is bounded by it), `shininess` ≤ {sf.MAX_SHININESS:g}; an image that needs more memory than is "
        "available (about 96 bytes per pixel) is refused before rendering.",
        "- `camera.position` must differ from `camera.look_at`; `up` must not be parallel to the view.",
        "- Overflow policy: inputs outside float32 are refused at validation. Inputs inside it can still overflow "
        "in a product (a light intensity of 3e38 times an albedo above 1); the finished image is then checked, and "
        "a render with NaN or infinite pixels is refused with exit status 2 (`the render overflowed float32`); "
        "nothing is written. No image with NaN/Inf pixels is ever written with exit status 0.",
        "",
        "Every refusal is one line, `renderer: <file>: <field>: expected ..., got ...`, exit status 2.", ""]
    return "\n".join(out)
