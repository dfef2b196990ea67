"""Fuzz corpus for `renderer render` / `renderer gallery`: bad and extreme inputs, run in-process.

Every case must end in one of two ways: exit 0 with a finite image, or exit 2 with one line
`renderer: <file>: <field>: ...` naming the file and the field; never a traceback, a hang, a NaN/Inf image,
or a file left behind. The corpus is generated (`cases()`), small (4×3-pixel images, 1 spp) and fast; the
categories follow issue 12: encoding, depth, number, size, physics, overflow, message, cli, gallery.
A few cases run as subprocesses (SIGINT, SIGTERM) in `test_interrupt_*`.
"""
from __future__ import annotations

import copy
import json
import os
import signal
import sys

import pytest

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import fuzz_harness  # noqa: E402

PNG_MAGIC = b"\x89PNG\r\n\x1a\n" + bytes(range(40))
HUGE = "1" + "0" * 400  # a 401-digit integer, written as JSON text

BASE = {
    "image": {"width": 4, "height": 3, "spp": 1, "max_depth": 2, "background": [0.1, 0.1, 0.1]},
    "camera": {"type": "pinhole", "position": [0, 0, -5], "look_at": [0, 0, 0], "up": [0, -1, 0], "fov_deg": 40},
    "lights": [{"type": "point", "position": [2, -3, -4], "intensity": [20, 20, 20]}],
    "objects": [
        {"name": "ball", "shape": {"type": "sphere", "center": [0, 0, 0], "radius": 1},
         "material": {"color": [0.8, 0.3, 0.2], "specular": 0.5, "shininess": 32}},
        {"name": "floor", "shape": {"type": "plane", "point": [0, 1, 0], "normal": [0, -1, 0]},
         "material": {"color": [0.5, 0.5, 0.5]}},
    ],
}

CAMERAS = {
    "thin_lens": {"type": "thin_lens", "position": [0, 0, -5], "look_at": [0, 0, 0], "w": 1, "U": 5, "d": 0.2,
                  "sensor_size": [0.8, 0.6], "theta_F_deg": 5},
    "inverted_perspective": {"type": "inverted_perspective", "position": [0, 0, -5], "look_at": [0, 0, 0],
                             "fov_deg": 40, "alpha": 2, "pseudo_screen_distance": 4},
}

# A thin lens focused through three world points (U, θF and the tilt axis follow from them).
FOCUS_POINTS = {"type": "thin_lens", "position": [0, 0, -5], "look_at": [0, 0, 0], "w": 1, "d": 0.2,
                "sensor_size": [0.8, 0.6], "focus_points": [[0, 0, 0], [1, 0, 0.5], [0, 1, 0]]}

# Numeric fields (path into the scene, camera variant) and the values every one of them is tried with.
FIELDS = [
    ("image.background.0", None), ("camera.position.0", None), ("camera.position.2", None),
    ("camera.look_at.1", None), ("camera.up.1", None), ("camera.fov_deg", None), ("camera.screen_distance", None),
    ("lights.0.position.1", None), ("lights.0.intensity.0", None), ("objects.0.shape.center.0", None),
    ("objects.0.shape.radius", None), ("objects.0.material.shininess", None), ("objects.0.material.specular", None),
    ("objects.0.material.ior", None), ("objects.0.material.color.1", None), ("objects.1.shape.normal.1", None),
    ("camera.w", "thin_lens"), ("camera.d", "thin_lens"), ("camera.U", "thin_lens"),
    ("camera.theta_F_deg", "thin_lens"), ("camera.alpha", "inverted_perspective"),
    ("camera.pseudo_screen_distance", "inverted_perspective"),
]
VALUES = ["1e39", "-1e39", "1e300", "1e-300", "1e-39", "NaN", "Infinity", "-Infinity", HUGE, "-" + HUGE,
          "0", "-1", '"x"', "null", "[]", "true", "3.3e38", "1e30"]


def _field_name(path: str) -> str:
    """objects.0.shape.radius -> objects[0].shape.radius (as messages write it)."""
    out = []
    for part in path.split("."):
        if part.isdigit():
            out[-1] += f"[{part}]"
        else:
            out.append(part)
    return ".".join(out)


def _set_text(scene: dict, path: str, raw: str) -> str:
    """The scene as JSON text with the value at `path` replaced by the raw JSON token `raw`."""
    marker = "__FUZZ_VALUE__"
    node, keys = scene, path.split(".")
    for k in keys[:-1]:
        node = node[int(k)] if isinstance(node, list) else node.setdefault(k, {})
    last = keys[-1]
    if isinstance(node, list):
        node[int(last)] = marker
    else:
        node[last] = marker
    return json.dumps(scene).replace(f'"{marker}"', raw)


def _scene(camera: str | None = None) -> dict:
    s = copy.deepcopy(BASE)
    if camera:
        s["camera"] = copy.deepcopy(CAMERAS[camera])
    return s


def _render(files: dict, *extra, expect="either", fields=(), category="number", name="", output="out.exr",
            scene="scene.json") -> dict:
    return {"name": name, "category": category, "files": files, "expect": expect, "fields": fields,
            "argv": ["render", f"{{d}}/{scene}", "-o", f"{{d}}/{output}", "--quiet", *extra], "output": output}


def _number_cases() -> list[dict]:
    out = []
    for path, camera in FIELDS:
        for raw in VALUES:
            text = _set_text(_scene(camera), path, raw)
            expect = "refuse" if raw in ("1e39", "-1e39", "1e300", "1e-300", "1e-39", "NaN", "Infinity",
                                         "-Infinity", HUGE, "-" + HUGE, '"x"', "[]", "true") else "either"
            out.append(_render({"scene.json": text}, expect=expect, name=f"number/{path}={raw[:12]}",
                               fields=("scene.json", _field_name(path).rsplit("[", 1)[0]) if expect == "refuse"
                               else ()))
    return out


def _encoding_cases() -> list[dict]:
    text = json.dumps(BASE)
    blobs = {
        "utf16le-bom": b"\xff\xfe" + text.encode("utf-16-le"), "utf16be-bom": b"\xfe\xff" + text.encode("utf-16-be"),
        "utf16-nobom": text.encode("utf-16-le"), "utf32": text.encode("utf-32"),
        "latin1": text.replace('"ball"', '"b\u00e4ll"').encode("latin-1"), "png": PNG_MAGIC,
        "jpeg": b"\xff\xd8\xff\xe0" + bytes(60), "empty": b"", "nul": b"\x00" * 10, "garbage": bytes(range(256)),
        "truncated": text[: len(text) // 2].encode(), "not-object": b"[1, 2, 3]", "string": b'"scene"',
        "trailing": (text + " }").encode(),
    }
    out = [_render({"scene.json": b}, expect="refuse", category="encoding", name=f"encoding/{k}",
                   fields=("scene.json",)) for k, b in blobs.items()]
    out.append(_render({"scene.json": text.replace('"ball"', '"\\ud800"').encode()}, category="encoding",
                       name="encoding/lone-surrogate"))
    out.append(_render({"scene.json": b"\xef\xbb\xbf" + text.encode()}, category="encoding", name="encoding/utf8-bom"))
    out.append(_render({"scene.json": None}, expect="refuse", category="encoding", name="encoding/folder",
                       fields=("scene.json",)))
    out.append(_render({}, expect="refuse", category="encoding", name="encoding/missing", fields=("scene.json",)))
    mesh_scene = _scene()
    mesh_scene["objects"][0]["shape"] = {"type": "mesh", "file": "m.obj"}
    for k, b in (("utf16", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n".encode("utf-16")), ("png", PNG_MAGIC),
                 ("latin1", "# caf\xe9\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n".encode("latin-1"))):
        out.append(_render({"scene.json": json.dumps(mesh_scene), "m.obj": b}, category="encoding",
                           name=f"encoding/mesh-{k}", fields=("scene.json",)))
    return out


def _deep(depth: int, leaf="1", open_="[", close="]") -> str:
    return open_ * depth + leaf + close * depth


def _depth_cases() -> list[dict]:
    out = []
    for depth in (70, 1000, 100000):
        for where in ("description", "objects.0.material.color", "image.background", "lights"):
            text = _set_text(_scene(), where, _deep(depth))
            out.append(_render({"scene.json": text}, expect="refuse", category="depth",
                               name=f"depth/{where}/{depth}", fields=("scene.json",)))
        text = _set_text(_scene(), "description", _deep(depth, "1", '{"a":', "}"))
        out.append(_render({"scene.json": text}, expect="refuse", category="depth", name=f"depth/dict/{depth}",
                           fields=("scene.json",)))
        out.append(_render({"scene.json": json.dumps(BASE)}, "--set", f"description={_deep(depth)}",
                           expect="refuse", category="depth", name=f"depth/set-value/{depth}", fields=("--set",)))
    for n in (70, 2000):
        out.append(_render({"scene.json": json.dumps(BASE)}, "--set", ".".join(["a"] * n) + "=1", expect="refuse",
                           category="depth", name=f"depth/set-path/{n}", fields=("--set",)))
    for n in (40, 1100):
        files = {"scene.json": json.dumps({"extends": "s1.json"})}
        for i in range(1, n):
            files[f"s{i}.json"] = json.dumps({"extends": f"s{i + 1}.json"})
        files[f"s{n}.json"] = json.dumps(BASE)
        out.append(_render(files, expect="refuse", category="depth", name=f"depth/extends/{n}",
                           fields=("extends",)))
    files = {"scene.json": json.dumps({**BASE, "extends": "b.json"}), "b.json": json.dumps({"extends": "scene.json"})}
    out.append(_render(files, expect="refuse", category="depth", name="depth/extends-cycle", fields=("extends",)))
    files = {"scene.json": json.dumps({"extends": "b.json"}), "b.json": json.dumps(BASE)}
    out.append(_render(files, expect="ok", category="depth", name="depth/extends-ok"))
    return out


def _size_cases() -> list[dict]:
    out = []
    for name, image, expect in (
            ("width1e9", {"width": 1000000000, "height": 1}, "refuse"),
            ("100000x100000", {"width": 100000, "height": 100000}, "refuse"),
            ("spp1e9", {"spp": 1000000000}, "refuse"), ("spp65537", {"spp": 65537}, "refuse"),
            ("max_depth1e6", {"max_depth": 1000000}, "refuse"), ("max_depth65", {"max_depth": 65}, "refuse"),
            ("width0", {"width": 0}, "refuse"), ("height-1", {"height": -1}, "refuse"),
            ("width2.5", {"width": 2.5}, "refuse"), ("spp0", {"spp": 0}, "refuse"),
            ("width-float", {"width": 4.0}, "either"), ("max_depth0", {"max_depth": 0}, "either"),
            ("max_depth64-mirrors", {"max_depth": 64}, "either"), ("1x1", {"width": 1, "height": 1}, "either"),
            ("max_depth1e6-mirrors", {"max_depth": 1000000}, "refuse")):
        s = _scene()
        s["image"].update(image)
        if "mirrors" in name:
            s["objects"] = [
                {"name": "m1", "shape": {"type": "plane", "point": [0, 0, 3], "normal": [0, 0, -1]},
                 "material": {"reflect": 1.0, "diffuse": 0}},
                {"name": "m2", "shape": {"type": "plane", "point": [0, 0, -6], "normal": [0, 0, 1]},
                 "material": {"reflect": 1.0, "diffuse": 0}}]
        key = next(iter(image))
        out.append(_render({"scene.json": json.dumps(s)}, expect=expect, category="size", name=f"size/{name}",
                           fields=("scene.json", f"image.{key}") if expect == "refuse" else ()))
    for spp in ("0", "-3", "1e9", "1000000000", "x"):
        out.append(_render({"scene.json": json.dumps(BASE)}, "--spp", spp, expect="refuse", category="size",
                           name=f"size/--spp={spp}", fields=("--spp",)))
    return out


def _physics_cases() -> list[dict]:
    out = []
    tweaks = {
        "position==look_at": ("camera.look_at", [0, 0, -5], "refuse", "camera.look_at"),
        "up-parallel": ("camera.up", [0, 0, 1], "refuse", "camera"),
        "up-zero": ("camera.up", [0, 0, 0], "refuse", "camera"),
        "radius0": ("objects.0.shape.radius", 0, "refuse", "radius"),
        "radius-neg": ("objects.0.shape.radius", -1, "refuse", "radius"),
        "normal-zero": ("objects.1.shape.normal", [0, 0, 0], "refuse", "normal"),
        "ior0": ("objects.0.material.ior", 0, "refuse", "ior"),
        "intensity-neg": ("lights.0.intensity", [-1, 0, 0], "refuse", "intensity"),
        "fov180": ("camera.fov_deg", 180, "refuse", "fov_deg"),
        "reflect+transmit": ("objects.0.material", {"reflect": 0.7, "transmit": 0.7}, "refuse", "material"),
        "cone-tiny": ("objects.0.shape", {"type": "cone", "center": [0, 0, 0], "axis": [0, 1, 0], "radius": 1,
                                          "height": 1e-300}, "refuse", "height"),
        "cone-small": ("objects.0.shape", {"type": "cone", "center": [0, 0, 0], "axis": [0, 1, 0], "radius": 1,
                                           "height": 1e-30}, "either", ""),
        "cylinder-axis0": ("objects.0.shape", {"type": "cylinder", "center": [0, 0, 0], "axis": [0, 0, 0],
                                               "radius": 1, "height": 1}, "refuse", "axis"),
        "box-size0": ("objects.0.shape", {"type": "box", "center": [0, 0, 0], "size": [0, 1, 1]}, "refuse", "size"),
        "polyhedron-empty": ("objects.0.shape", {"type": "polyhedron", "halfspaces": []}, "refuse", "halfspaces"),
        "polyhedron-nan": ("objects.0.shape", {"type": "polyhedron", "halfspaces": [[1, 0, 0, "NaN"]]}, "refuse",
                           "halfspaces"),
        "unknown-shape": ("objects.0.shape.type", "teapot", "refuse", "type"),
        "unknown-key": ("image.colour", 1, "refuse", "image.colour"),
        "thin-lens-w0": ("camera", {**CAMERAS["thin_lens"], "w": 0}, "refuse", "camera.w"),
        "thin-lens-U<w": ("camera", {**CAMERAS["thin_lens"], "U": 0.5}, "either", ""),
        "thin-lens-theta90": ("camera", {**CAMERAS["thin_lens"], "theta_F_deg": 90}, "refuse", "camera"),
        "alpha-neg": ("camera", {**CAMERAS["inverted_perspective"], "alpha": -3}, "either", ""),
        "sensor0": ("camera", {**CAMERAS["thin_lens"], "sensor_size": [0, 0.6]}, "refuse", "sensor_size"),
        # issue 33 §4: focus_points skipped the sensor check ([0, 0] divided by zero, a negative size turned the
        # image by 180° with exit 0), and the tilt axis had no range (1e9° rendered as 280°).
        "focus-points-sensor0": ("camera", {**FOCUS_POINTS, "sensor_size": [0, 0]}, "refuse", "camera.sensor_size"),
        "focus-points-sensor-neg": ("camera", {**FOCUS_POINTS, "sensor_size": [-36, -27]}, "refuse",
                                    "camera.sensor_size"),
        "focus-points-sensor-neg-x": ("camera", {**FOCUS_POINTS, "sensor_size": [-0.8, 0.6]}, "refuse",
                                      "camera.sensor_size"),
        "focus-points-ok": ("camera", FOCUS_POINTS, "ok", ""),
        "focus-points-w0": ("camera", {**FOCUS_POINTS, "w": 0}, "refuse", "camera.w"),
        "tilt-axis-1e9": ("camera", {**CAMERAS["thin_lens"], "tilt_axis_deg": 1e9}, "refuse", "camera.tilt_axis_deg"),
        "tilt-axis-361": ("camera", {**CAMERAS["thin_lens"], "tilt_axis_deg": -361}, "refuse",
                          "camera.tilt_axis_deg"),
        "tilt-axis-360": ("camera", {**CAMERAS["thin_lens"], "tilt_axis_deg": 360}, "ok", ""),
        "tilt-axis-with-focus-points": ("camera", {**FOCUS_POINTS, "tilt_axis_deg": 1e9}, "refuse",
                                        "camera: give focus_points or tilt_axis_deg"),
        "light-at-surface": ("lights.0.position", [0, 0, -1], "either", ""),
        "light-inside": ("lights.0.position", [0, 0, 0], "either", ""),
        "camera-inside": ("camera.position", [0, 0, 0.2], "either", ""),
    }
    for name, (path, value, expect, field) in tweaks.items():
        text = _set_text(_scene(), path, json.dumps(value).replace('"NaN"', "NaN"))
        out.append(_render({"scene.json": text}, expect=expect, category="physics", name=f"physics/{name}",
                           fields=("scene.json", field) if expect == "refuse" else ()))
    return out


def _mesh(text: str | bytes) -> dict:
    s = _scene()
    s["objects"][0]["shape"] = {"type": "mesh", "file": "m.obj"}
    return {"scene.json": json.dumps(s), "m.obj": text}


def _message_cases() -> list[dict]:
    out = []
    tri = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"
    for name, text, fields in (
            ("mesh-nan", "v nan 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", ("m.obj", "NaN")),
            ("mesh-inf", "v inf 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", ("m.obj",)),
            ("mesh-1e39", "v 1e39 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", ("m.obj",)),
            ("mesh-huge", f"v {HUGE} 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", ("m.obj",)),
            ("mesh-empty", "", ("m.obj",)), ("mesh-no-faces", "v 0 0 0\n", ("m.obj",)),
            ("mesh-bad-index", "v 0 0 0\nf 1 2 3\n", ("m.obj",)),
            ("mesh-degenerate", "v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n", ("shape.file", "zero area")),
            ("mesh-text", "v a b c\nf 1 2 3\n", ("m.obj",))):
        out.append(_render(_mesh(text), expect="refuse", category="message", name=f"message/{name}",
                           fields=fields))
    out.append(_render(_mesh(tri), category="message", name="message/mesh-ok", expect="ok"))
    # Textures: a truncated PNG (libpng complains on fd 2), image bytes that are not an image, a folder.
    png = _tiny_png()
    for name, blob in (("texture-truncated", png[: len(png) // 2]), ("texture-garbage", b"not an image"),
                       ("texture-empty", b"")):
        s = _scene()
        s["objects"][0]["material"]["texture"] = {"type": "image", "file": "t.png", "size": 1}
        out.append(_render({"scene.json": json.dumps(s), "t.png": blob}, expect="refuse", category="message",
                           name=f"message/{name}", fields=("t.png",)))
    s = _scene()
    s["objects"][0]["material"]["texture"] = {"type": "image", "file": "t.png", "size": 1}
    out.append(_render({"scene.json": json.dumps(s), "t.png": png}, expect="ok", category="message",
                       name="message/texture-ok"))
    for name, value in (("checker-colors-nan", [["NaN", 0, 0], [1, 1, 1]]), ("checker-size0", 0),
                        ("checker-colors-huge", [[HUGE, 0, 0], [1, 1, 1]])):
        s = _scene()
        tex = {"type": "checker", "size": value if name == "checker-size0" else 0.5}
        if name != "checker-size0":
            tex["colors"] = "__C__"
        s["objects"][0]["material"]["texture"] = tex
        text = json.dumps(s).replace('"__C__"', json.dumps(value).replace('"NaN"', "NaN").replace(f'"{HUGE}"', HUGE))
        out.append(_render({"scene.json": text}, expect="refuse", category="message", name=f"message/{name}",
                           fields=("scene.json", "texture")))
    return out


def _tiny_png() -> bytes:
    import numpy as np
    import OpenImageIO as oiio

    import tempfile
    with tempfile.TemporaryDirectory() as d:
        p = os.path.join(d, "t.png")
        out = oiio.ImageOutput.create(p)
        out.open(p, oiio.ImageSpec(32, 32, 3, oiio.UINT8))
        out.write_image(np.random.default_rng(0).random((32, 32, 3)).astype(np.float32))
        out.close()
        return open(p, "rb").read()


def _overflow_cases() -> list[dict]:
    out = []
    for name, path, value, expect in (
            ("intensity1e39", "lights.0.intensity", [1e39] * 3, "refuse"),
            ("intensity1e300", "lights.0.intensity", [1e300] * 3, "refuse"),
            ("intensity3e38", "lights.0.intensity", [3e38] * 3, "either"),
            ("intensity1e37-close", "lights", [{"type": "point", "position": [0, 0, -1.01], "intensity": [1e37] * 3}],
             "either"),
            ("ambient3e38", "lights", [{"type": "ambient", "intensity": [3e38] * 3}], "either"),
            ("background1e39", "image.background", [1e39] * 3, "refuse"),
            ("background3e38", "image.background", [3e38] * 3, "either"),
            ("shininess1e308", "objects.0.material.shininess", 1e308, "refuse"),
            ("shininess1e30", "objects.0.material.shininess", 1e30, "refuse"),
            ("shininess1e6", "objects.0.material.shininess", 1e6, "either"),
            ("camera1e39", "camera.position", [1e39, 0, 0], "refuse"),
            ("camera1e30", "camera.position", [0, 0, -1e30], "either"),
            ("sphere1e39", "objects.0.shape.center", [1e39, 0, 0], "refuse"),
            ("radius3e38", "objects.0.shape.radius", 3e38, "either"),
            ("aperture1e39", "camera", {**CAMERAS["thin_lens"], "d": 1e39}, "refuse"),
            ("aperture1e30", "camera", {**CAMERAS["thin_lens"], "d": 1e30}, "either"),
            ("alpha1e39", "camera", {**CAMERAS["inverted_perspective"], "alpha": 1e39}, "refuse"),
            ("p3-1e39", "camera", {**CAMERAS["inverted_perspective"], "pseudo_screen_distance": 1e39}, "refuse"),
            ("p3-1e30", "camera", {**CAMERAS["inverted_perspective"], "pseudo_screen_distance": 1e30}, "either"),
            ("color3e38-specular", "objects.0.material", {"color": [3e38] * 3, "specular": 1, "reflect": 0},
             "either")):
        text = _set_text(_scene(), path, json.dumps(value))
        out.append(_render({"scene.json": text}, expect=expect, category="overflow", name=f"overflow/{name}",
                           fields=("scene.json",)))
    return out


def _cli_cases() -> list[dict]:
    base = {"scene.json": json.dumps(BASE)}
    out = []
    for name, extra, expect, fields in (
            ("device-meta", ["--device", "meta"], "refuse", ("--device",)),
            ("device-foo", ["--device", "foo"], "refuse", ("--device",)),
            ("device-cuda:99", ["--device", "cuda:99"], "refuse", ("--device",)),
            ("seed2^70", ["--seed", str(2**70)], "refuse", ("--seed",)),
            ("seed-1", ["--seed", "-1"], "refuse", ("--seed",)),
            ("seed-x", ["--seed", "x"], "refuse", ("--seed",)),
            ("seed2^63-1", ["--seed", str(2**63 - 1)], "either", ()),
            ("set-malformed", ["--set", "=3"], "refuse", ("--set",)),
            ("set-no-equals", ["--set", "image.width"], "refuse", ("--set",)),
            ("set-bad-index", ["--set", "objects.9.name=x"], "refuse", ("--set", "objects")),
            ("set-huge", ["--set", f"image.width={HUGE}"], "refuse", ("image.width",)),
            ("set-nan", ["--set", "camera.fov_deg=NaN"], "refuse", ("camera.fov_deg",)),
            ("set-into-number", ["--set", "image.width.x=1"], "refuse", ("--set",)),
            ("encoding-bad", ["--encoding", "gamma"], "refuse", ("--encoding",)),
            ("sampler-bad", ["--sampler", "magic"], "refuse", ("--sampler",))):
        out.append(_render(base, *extra, expect=expect, category="cli", name=f"cli/{name}", fields=fields))
    for name, files, output, fields in (
            ("output-folder", {**base, "out.exr": None}, "out.exr", ("out.exr", "folder")),
            ("output-bmp", base, "out.bmp", ("out.bmp",)),
            ("output-noext", base, "out", ("out",)),
            ("output-under-file", {**base, "f": b"x"}, "f/out.exr", ("f",))):
        out.append(_render(files, expect="refuse", category="cli", name=f"cli/{name}", output=output, fields=fields))
    # A failed run must leave an existing output as it was.
    bad = _set_text(_scene(), "image.width", "0")
    out.append(_render({"scene.json": bad, "out.exr": b"previous"}, expect="refuse", category="cli",
                       name="cli/existing-output-kept", fields=("image.width",)))
    for enc in ("srgb", "linear"):
        for ext in ("png", "tif", "exr"):
            out.append(_render(base, "--encoding", enc, expect="ok", category="cli", name=f"cli/ok-{enc}.{ext}",
                               output=f"out.{ext}"))
    return out


def _gallery_cases() -> list[dict]:
    out = []
    scene = json.dumps(BASE)

    def gallery(files, expect="refuse", fields=("m.json",), name=""):
        return {"name": f"gallery/{name}", "category": "gallery", "files": files, "expect": expect,
                "fields": fields, "output": "g.png",
                "argv": ["gallery", "--manifest", "{d}/m.json", "-o", "{d}/g.png", "--quick"]}

    for name, blob in (("utf16", json.dumps([{"scene": "s.json", "label": "a"}]).encode("utf-16")),
                       ("png", PNG_MAGIC), ("deep", _deep(5000).encode()), ("object", b"{}"), ("empty-list", b"[]"),
                       ("entry-not-object", b"[1]"), ("entry-no-label", json.dumps([{"scene": "s.json"}]).encode()),
                       ("entry-bad-set", json.dumps([{"scene": "s.json", "label": "a", "set": "x=1"}]).encode()),
                       ("missing-scene", json.dumps([{"scene": "nope.json", "label": "a"}]).encode()),
                       ("bad-override", json.dumps([{"scene": "s.json", "label": "a",
                                                     "set": ["image.width=-4"]}]).encode())):
        fields = ("m.json",) if name not in ("missing-scene", "bad-override") else ("json",)
        out.append(gallery({"m.json": blob, "s.json": scene}, fields=fields, name=name))
    out.append(gallery({"m.json": json.dumps([{"scene": "s.json", "label": "a"}]), "s.json": scene}, expect="ok",
                       fields=(), name="ok"))
    out.append(gallery({"m.json": json.dumps([{"scene": "s.json", "label": "a"}]), "s.json": scene, "g.png": None},
                       fields=("g.png",), name="output-folder"))
    return out


def _merged_feature_cases() -> list[dict]:
    """`renderer animate`, the csg shape and camera.distortion (added by other issues)."""
    out = []
    base = {"scene.json": json.dumps(BASE)}

    def animate(files, *extra, expect="refuse", fields=(), name=""):
        return {"name": f"animate/{name}", "category": "animate", "files": files, "expect": expect, "fields": fields,
                "output": "anim", "argv": ["animate", "{d}/scene.json", "-o", "{d}/anim", "--quiet", *extra]}

    for value in ("0", "-1", "1e9", "70000", "x"):
        out.append(animate(base, "--method", "trace", "--frames", value, "--step", "0.1", fields=("--frames",),
                           name=f"--frames={value}"))
    for value in ("nan", "inf", "-inf", "1e39", "1e400"):
        out.append(animate(base, "--method", "trace", "--frames", "2", "--step", value, fields=("--step",),
                           name=f"--step={value}"))
    out.append(animate({**base, "anim": b"a file"}, "--method", "trace", "--frames", "2", "--step", "0.1",
                       fields=("anim",), name="output-is-a-file"))
    out.append(animate(base, "--method", "trace", "--frames", "2", "--step", "0.1", expect="either",
                       name="trace-ok"))
    out.append(animate({"scene.json": _set_text(_scene(), "image.width", HUGE)}, "--method", "trace", "--frames",
                       "2", "--step", "0.1", fields=("image.width",), name="huge-width"))
    out.append(animate(base, "--method", "beam", "--frames", "2", "--step", "0.1", expect="either",
                       name="beam-sphere"))
    leaf = {"type": "polyhedron", "halfspaces": [[1, 0, 0, 1], [-1, 0, 0, 1], [0, 1, 0, 1], [0, -1, 0, 1],
                                                  [0, 0, 1, 1], [0, 0, -1, 1]]}
    for name, shape, expect, field in (
            ("ok", {"type": "csg", "op": "intersection", "children": [leaf, leaf]}, "either", ""),
            ("no-children", {"type": "csg", "op": "union", "children": []}, "refuse", "children"),
            ("bad-op", {"type": "csg", "op": "xor", "children": [leaf]}, "refuse", "op"),
            ("child-nan", {"type": "csg", "op": "union", "children": [{**leaf, "halfspaces": [[1, 0, 0, "NaN"]]}]},
             "refuse", "halfspaces"),
            ("child-sphere", {"type": "csg", "op": "union", "children": [{"type": "sphere", "center": [0, 0, 0],
                                                                          "radius": 1}]}, "refuse", "children"),
            ("deep", json.loads(_deep_csg(40, leaf)), "either", ""),
            ("too-deep", json.loads(_deep_csg(70, leaf)), "refuse", "")):
        text = _set_text(_scene(), "objects.0.shape", json.dumps(shape).replace('"NaN"', "NaN"))
        out.append(_render({"scene.json": text}, expect=expect, category="csg", name=f"csg/{name}",
                           fields=("scene.json", field) if expect == "refuse" else ()))
    for name, coeffs, expect in (("nan", "[NaN, 0, 0, 0]", "refuse"), ("huge", f"[{HUGE}, 0, 0, 0]", "refuse"),
                                 ("1e39", "[1e39, 0, 0, 0]", "refuse"), ("nine", "[0, 0, 0, 0, 0, 0, 0, 0, 0]",
                                                                        "refuse"),
                                 ("empty", "[]", "refuse"), ("k1=0.1", "[0.1, 0, 0, 0]", "either"),
                                 ("k1=1e30", "[1e30, 0, 0, 0]", "either"), ("k1=-5", "[-5, 0, 0, 0]", "either")):
        scene = _scene()
        scene["camera"]["distortion"] = {"model": "brown_conrady", "coefficients": "__C__"}
        text = json.dumps(scene).replace('"__C__"', coeffs)
        out.append(_render({"scene.json": text}, expect=expect, category="distortion", name=f"distortion/{name}",
                           fields=("scene.json", "distortion") if expect == "refuse" else ()))
    return out


def _deep_csg(depth: int, leaf: dict) -> str:
    text = json.dumps(leaf)
    for _ in range(depth):
        text = '{"type": "csg", "op": "union", "children": [' + text + "]}"
    return text


def cases() -> list[dict]:
    """The whole renderer corpus (names unique)."""
    out = (_encoding_cases() + _depth_cases() + _number_cases() + _size_cases() + _physics_cases()
           + _message_cases() + _overflow_cases() + _cli_cases() + _gallery_cases() + _merged_feature_cases())
    return fuzz_harness.unique(out)


CASES = cases()


@pytest.mark.parametrize("case", CASES, ids=[c["name"] for c in CASES])
def test_fuzz_case(case):
    fuzz_harness.check(case, "renderer")


def test_corpus_covers_every_category():
    counts = {}
    for c in CASES:
        counts[c["category"]] = counts.get(c["category"], 0) + 1
    assert set(counts) == {"encoding", "depth", "number", "size", "physics", "message", "overflow", "cli",
                           "gallery", "animate", "csg", "distortion"}, f"categories: {counts}"
    assert len(CASES) >= 400, f"renderer corpus has {len(CASES)} cases"


SLOW_SCENE = {**BASE, "image": {"width": 1024, "height": 1024, "spp": 64, "max_depth": 8}}


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_interrupt_render_one_line_exit_130_nothing_left(tmp_path, sig):
    scene = tmp_path / "scene.json"
    scene.write_text(json.dumps(SLOW_SCENE))
    out = tmp_path / "out.exr"
    out.write_bytes(b"previous")
    rc, lines = fuzz_harness.interrupt_after_progress(["renderer", "render", str(scene), "-o", str(out)], sig, "render")
    last = [ln for ln in lines if ln.startswith("renderer:")]
    assert rc == 130, f"exit {rc}: {lines[-3:]}"
    assert last == ["renderer: interrupted"], f"one line at the end: {lines[-3:]}"
    assert sorted(os.listdir(tmp_path)) == ["out.exr", "scene.json"], f"left behind: {os.listdir(tmp_path)}"
    assert out.read_bytes() == b"previous", "the existing output survives an interrupt"
