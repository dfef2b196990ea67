"""Scene files: validation messages (one line, naming the field), overrides, `extends`, shipped scenes."""
from __future__ import annotations

import glob
import json
import os

import numpy as np
import pytest

from renderer import SceneError
from camio.files import write_image
from renderer.scene.file import load_scene

SCENES = os.path.join(os.path.dirname(__file__), "..", "..", "renderer", "scenes")


def minimal():
    return {
        "image": {"width": 8, "height": 6},
        "camera": {"type": "pinhole", "fov_deg": 40},
        "lights": [{"type": "point", "position": [0, -2, 0], "intensity": [5, 5, 5]},
                   {"type": "ambient", "intensity": 0.1}],
        "objects": [
            {"name": "ball", "shape": {"type": "sphere", "center": [0, 0, 5], "radius": 1},
             "material": {"color": [1, 0, 0], "reflect": 0.2}},
            {"name": "floor", "shape": {"type": "plane", "point": [0, 1, 0], "normal": [0, -1, 0]}},
        ],
    }


def error_of(source, overrides=()) -> str:
    with pytest.raises(SceneError) as info:
        load_scene(source, overrides)
    message = str(info.value)
    assert "\n" not in message, f"message is not one line: {message!r}"
    return message


def write_scene(tmp_path, cfg, name="scene.json") -> str:
    path = tmp_path / name
    path.write_text(json.dumps(cfg) if not isinstance(cfg, str) else cfg)
    return str(path)


def test_minimal_scene_fills_defaults():
    scene = load_scene(minimal())
    assert (scene.image.spp, scene.image.max_depth, scene.image.sampler) == (1, 5, "sobol"), "image defaults"
    assert scene.image.background == (0.0, 0.0, 0.0), "default background is black"
    assert (scene.camera.width, scene.camera.height) == (8, 6), "camera takes the image size"
    assert [o.name for o in scene.objects] == ["ball", "floor"], "objects in file order"
    assert scene.objects[0].material.reflect == 0.2 and scene.objects[1].material.color == (0.8, 0.8, 0.8)
    assert [l.type for l in scene.lights] == ["point", "ambient"], "both light types"
    assert scene.lights[1].intensity == (0.1, 0.1, 0.1), "a single number is a grey colour"


DELETE = object()


def _with(path, value):
    """minimal() with the key at dotted `path` set to value (or deleted if value is DELETE)."""
    cfg = minimal()
    node = cfg
    keys = path.split(".")
    for k in keys[:-1]:
        node = node[int(k)] if isinstance(node, list) else node[k]
    last = keys[-1]
    if value is DELETE:
        del node[last]
    elif isinstance(node, list):
        node[int(last)] = value
    else:
        node[last] = value
    return cfg


BAD = [
    # (key path, value, expected start of the message)
    ("colour", 1, "colour: unknown key"),
    ("image.gamma", 2.2, "image.gamma: unknown key"),
    ("objects.0.material.gloss", 1, "objects[0].material.gloss: unknown key"),
    ("objects.0.material.ior", "glass", "objects[0].material.ior: expected a number, got 'glass'"),
    ("image.width", 8.5, "image.width: expected an integer"),
    ("image.width", 0, "image.width: expected an integer >= 1"),
    ("image.width", DELETE, "image.width: missing required key"),
    ("camera", DELETE, "camera: missing required section"),
    ("objects.1.shape", DELETE, "objects[1].shape: missing required key"),
    ("objects.1.name", "ball", "objects[1].name: duplicate name 'ball'"),
    ("objects.0.shape.radius", [1], "objects[0].shape.radius: expected a number"),
    ("objects.0.shape.type", "torus", "objects[0].shape.type: unknown shape 'torus'"),
    ("objects.0.material.color", [1, 0], "objects[0].material.color: expected a list of 3 numbers"),
    ("objects.0.material.transmit", 1.5, "objects[0].material.transmit: expected a weight in [0, 1]"),
    ("objects.0.material.texture", {"type": "marble"}, "objects[0].material.texture.type: expected one of"),
    ("objects.0.material.texture", {"type": "checker"}, "objects[0].material.texture.size: missing required key"),
    ("objects.0.material.texture", {"type": "image", "file": "nope.png", "size": 1},
     "objects[0].material.texture.file: "),
    ("image.sampler", "halton", "image.sampler: expected one of independent, stratified, sobol, center"),
    ("lights.0.type", "spot", "lights[0].type: expected one of point, ambient"),
    ("lights.0.position", DELETE, "lights[0].position: missing required key"),
    ("lights", {"type": "point"}, "lights: expected a list"),
    ("camera.type", "fisheye", "camera.type: unknown camera 'fisheye'"),
    ("layers", [{"objects": ["ghost"], "alpha": 1, "pseudo_screen_center": [0, 0, 5]}],
     "layers[0].objects: unknown object 'ghost'"),
]


@pytest.mark.parametrize("path,value,expected", BAD, ids=[f"{b[2].split(':')[0]}-{i}" for i, b in enumerate(BAD)])
def test_bad_scene_gives_one_line_naming_the_field(tmp_path, path, value, expected):
    file = write_scene(tmp_path, _with(path, value))
    message = error_of(file)
    assert message.startswith(f"{file}: {expected}"), f"got {message!r}, expected it to start with {expected!r}"


@pytest.mark.parametrize("literal", ["NaN", "Infinity", "-Infinity"])
def test_nan_and_infinity_are_rejected_with_their_path(tmp_path, literal):
    text = json.dumps(minimal()).replace('"radius": 1', f'"radius": {literal}')
    message = error_of(write_scene(tmp_path, text))
    assert "objects[0].shape.radius: expected a finite number" in message, message
    # inside free-form lists too (checker colours are checked only at the end otherwise)
    message = error_of(minimal(), [f"objects.1.material.texture={{\"type\": \"checker\", \"size\": 1, "
                                   f"\"colors\": [[1, 1, {literal}], [0, 0, 0]]}}"])
    assert message.startswith("objects[1].material.texture.colors[0][2]: expected a finite number"), message


def test_bad_json_names_line_and_column(tmp_path):
    file = write_scene(tmp_path, '{\n  "image": {"width": 8,, "height": 6}\n}')
    message = error_of(file)
    assert message.startswith(f"{file}:2:"), f"expected file:line:col, got {message!r}"
    assert "not valid JSON" in message, message


def test_missing_file_is_one_line(tmp_path):
    message = error_of(str(tmp_path / "none.json"))
    assert "none.json: cannot read scene file" in message, message


def test_overrides_set_values_by_index_and_name_and_create_sections():
    scene = load_scene(minimal(), ["camera.fov_deg=30", "objects.0.material.color=[0, 1, 0]",
                                   "objects.floor.material.reflect=0.5", "image.sampler=center",
                                   "objects.ball.shape.radius=2"])
    assert scene.image.sampler == "center", "string values fall back to plain strings"
    assert scene.objects[0].material.color == (0.0, 1.0, 0.0), "list index"
    assert scene.objects[1].material.reflect == 0.5, "element by name; the missing material section is created"
    assert scene.objects[0].shape.radius == 2.0, "nested shape key"
    wide = load_scene(minimal()).camera.screen.size[0]
    assert scene.camera.screen.size[0] < wide, "fov override narrows the screen"


@pytest.mark.parametrize("override,expected", [
    ("objects.7.material.color=[1,0,0]", "--set objects.7.material.color=[1,0,0]: objects has no element '7'"),
    ("objects.ghost.material.reflect=1", "objects has no element 'ghost'"),
    ("image.width.x=3", "image.width is 8, not a section or list"),
    ("camera.alpha", "expected key.path=value"),
    ("image..width=3", "expected key.path=value"),
    ("image.width=NaN", "image.width: expected a finite number"),
    ("objects.0.material.ior=\"glass\"", "objects[0].material.ior: expected a number, got 'glass'"),
])
def test_bad_override_is_one_clear_line(override, expected):
    message = error_of(minimal(), [override])
    assert expected in message, f"got {message!r}"


def test_extends_merges_sections_and_replaces_lists(tmp_path):
    write_scene(tmp_path, minimal(), "base.json")
    child = write_scene(tmp_path, {"extends": "base.json", "image": {"spp": 3}, "lights": []}, "child.json")
    scene = load_scene(child)
    assert (scene.image.width, scene.image.spp) == (8, 3), "image merged key by key"
    assert scene.lights == [], "lists are replaced, not merged"
    assert len(scene.objects) == 2, "untouched sections come from the base"
    write_scene(tmp_path, {"extends": "loop_b.json"}, "loop_a.json")
    write_scene(tmp_path, {"extends": "loop_a.json"}, "loop_b.json")
    assert "circular" in error_of(str(tmp_path / "loop_a.json"))


def test_image_texture_is_read_relative_to_the_scene_file(tmp_path):
    (tmp_path / "tex").mkdir()
    pixels = np.zeros((4, 6, 3), np.float32)
    pixels[:, 3:] = 1.0
    write_image(str(tmp_path / "tex" / "half.png"), pixels)
    cfg = minimal()
    cfg["objects"][1]["material"] = {"texture": {"type": "image", "file": "tex/half.png", "size": [3, 2]}}
    scene = load_scene(write_scene(tmp_path, cfg))
    texture = scene.objects[1].material.texture
    assert texture.size == (3.0, 2.0) and texture.pixels.shape == (4, 6, 3), "size and (H, W, 3) pixels"
    assert np.allclose(texture.pixels[0, :3], 0) and np.allclose(texture.pixels[0, 3:], 1), "pixels decoded"


def test_layers_build_from_object_names():
    cfg = minimal()
    cfg["layers"] = [{"objects": ["ball"], "alpha": 2, "pseudo_screen_center": [0, 0, 5]}]
    scene = load_scene(cfg)
    assert len(scene.layers) == 1 and scene.layers[0].object_ids == frozenset({0}), "layer refers to the ball"


SHIPPED = sorted(p for p in glob.glob(os.path.join(SCENES, "*.json")) if not p.endswith("gallery.json"))


@pytest.mark.parametrize("path", SHIPPED, ids=[os.path.basename(p) for p in SHIPPED])
def test_every_shipped_scene_loads(path):
    scene = load_scene(path)
    assert scene.objects and scene.camera.width > 0, f"{path} has objects and a camera"


def test_every_gallery_entry_loads():
    from renderer.cli.main import GALLERY_MANIFEST, read_manifest

    entries = read_manifest(GALLERY_MANIFEST)
    assert len(entries) >= 12, "the paper's Figs. 6-10 are all in the gallery"
    for entry in entries:
        load_scene(entry["scene"], entry["set"])


def test_fig6_scene_matches_the_paper():
    """Plate at 5, nine objects at 4 (five 0.8 cubes, sphere, cone, cylinder, 0.12 cube), a 0.8 cube at 2."""
    with open(os.path.join(SCENES, "fig6.json")) as f:
        objects = json.load(f)["objects"]
    depth = {o["name"]: o["shape"]["center"][2] for o in objects}
    kinds = sorted(o["shape"]["type"] for o in objects if depth[o["name"]] == 4.0)
    assert kinds == ["box"] * 6 + ["cone", "cylinder", "sphere"], f"objects at distance 4: {kinds}"
    cubes = sorted(o["shape"]["size"][0] for o in objects if depth[o["name"]] == 4.0 and o["shape"]["type"] == "box")
    assert cubes == [0.12] + [0.8] * 5, f"cube sizes at distance 4: {cubes}"
    assert depth["plate"] == 5.0 and depth["front_cube"] == 2.0, "plate at 5, translucent cube at 2"
    front = next(o for o in objects if o["name"] == "front_cube")
    assert front["shape"]["size"] == [0.8] * 3 and front["material"]["transmit"] > 0, "translucent 0.8 cube"
