"""Declared, documented parameters for components built from plain dicts (scene-file sections).

Each camera, shape, material or light declares its parameters once as `Param`s (name, kind, default, doc);
`parse_params` validates a dict against them at the boundary and raises `SceneError` with the field's full
path, what was expected and what was received. The same table renders as user documentation.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from camio.errors import SceneError  # noqa: F401 - raised here, and importable from here as before
from camio.checks import describe, is_finite_number, is_number

REQUIRED = object()

#: The pixel-and-lens sample patterns (`renderer.tracing.sampling`), named here so that parsing needs no torch.
SAMPLERS = ("independent", "stratified", "sobol", "center")
#: Where a lens's distortion is centred (`renderer.cameras.Lens.distortion_centre`), named here for file readers.
DISTORTION_CENTRES = ("sensor", "lens_axis")
#: Samples per pixel beyond which a render is a mistake (`renderer.scene.file`'s image limits); the sampler draws a
#: pixel's samples at once, so 1e9 asked for 32 GB.
MAX_SPP = 1 << 16


@dataclass(frozen=True)
class Param:
    """One parameter: `kind` is float, int, bool, str, vec2, vec3, color, list, dict or any."""

    name: str
    kind: str
    default: Any = REQUIRED
    doc: str = ""
    choices: tuple | None = None


def check_value(path: str, kind: str, value, choices=None):
    """Validate one value of a declared kind; returns it normalised (floats, tuples)."""

    def fail(expected):
        raise SceneError(f"{path}: expected {expected}, got {describe(value)}")

    if kind == "any":
        return value
    if kind in ("float", "int"):
        if not is_number(value):
            fail("a number")
        if not is_finite_number(value):
            fail("a finite number")
        if kind == "int":
            if float(value) != int(value):
                fail("an integer")
            return int(value)
        return float(value)
    if kind == "bool":
        if not isinstance(value, bool):
            fail("true or false")
        return value
    if kind == "str":
        if not isinstance(value, str):
            fail("a string")
        if choices is not None and value not in choices:
            fail("one of " + ", ".join(map(str, choices)))
        return value
    if kind in ("vec2", "vec3", "color"):
        n = 2 if kind == "vec2" else 3
        if is_number(value) and kind == "color":
            value = [value] * 3
        if not isinstance(value, (list, tuple)) or len(value) != n or not all(is_number(v) for v in value):
            fail(f"a list of {n} numbers")
        if not all(is_finite_number(v) for v in value):
            fail(f"a list of {n} finite numbers")
        return tuple(float(v) for v in value)
    if kind == "list":
        if not isinstance(value, list):
            fail("a list")
        return value
    if kind == "dict":
        if not isinstance(value, dict):
            fail("an object")
        return value
    raise AssertionError(f"unknown parameter kind {kind}")


def parse_params(path: str, cfg, params: list[Param], ignore: tuple[str, ...] = ()) -> dict:
    """Validate `cfg` (a dict from a scene file) against declared params; fill defaults.

    Args:
        path: where `cfg` sits in the file, e.g. "camera" or "objects[2].shape", used in messages.
        params: the declared parameters; unknown keys are an error.
        ignore: keys that the caller handles itself (e.g. "type").
    """
    if not isinstance(cfg, dict):
        raise SceneError(f"{path}: expected an object, got {cfg!r}")
    known = {p.name for p in params}
    for key in cfg:
        if key not in known and key not in ignore:
            raise SceneError(f"{path}.{key}: unknown key (expected one of: {', '.join(sorted(known))})")
    out = {}
    for p in params:
        if p.name in cfg:
            out[p.name] = check_value(f"{path}.{p.name}", p.kind, cfg[p.name], p.choices)
        elif p.default is REQUIRED:
            raise SceneError(f"{path}.{p.name}: missing required key")
        else:
            out[p.name] = p.default
    return out


def params_table(params: list[Param]) -> str:
    """Markdown table of parameters (name, kind, default, meaning) for docs and --help."""
    rows = ["| key | kind | default | meaning |", "|---|---|---|---|"]
    for p in params:
        d = "required" if p.default is REQUIRED else repr(p.default)
        rows.append(f"| `{p.name}` | {p.kind} | {d} | {p.doc} |")
    return "\n".join(rows)
