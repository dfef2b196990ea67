"""docs/file_formats.md and docs/schemas/ are built from the validators' declarations and must match them."""
from __future__ import annotations

import glob
import json
import os

import jsonschema
import pytest

from renderer.scene.file import read_scene_json
from tiltfit.files import formats

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def test_committed_docs_equal_a_fresh_build():
    for rel, text in formats.build().items():
        path = os.path.join(formats.DOCS, rel)
        assert os.path.isfile(path), f"{rel} missing: run python -m tiltfit.files.formats"
        with open(path, encoding="utf-8") as f:
            assert f.read() == text, f"{rel} is out of date: run python -m tiltfit.files.formats"


@pytest.mark.parametrize("name", ["scene", "target", "det"])
def test_schemas_are_valid_json_schemas(name):
    jsonschema.Draft202012Validator.check_schema(json.loads(formats.build()[f"schemas/{name}.schema.json"]))


def test_every_shipped_scene_satisfies_the_schema_and_broken_ones_do_not():
    schema = json.loads(formats.build()["schemas/scene.schema.json"])
    validator = jsonschema.Draft202012Validator(schema)
    scenes = [f for f in glob.glob(os.path.join(ROOT, "renderer", "scenes", "*.json")) if "gallery" not in f]
    assert len(scenes) >= 5, scenes
    for f in scenes:
        errors = [e.message for e in validator.iter_errors(read_scene_json(f))]
        assert not errors, f"{f}: {errors[:3]}"
    cfg = read_scene_json(scenes[0])
    for key, value in (("width", "wide"), ("spp", 70000), ("colour", 1)):
        bad = json.loads(json.dumps(cfg))
        bad["image"][key] = value
        assert list(validator.iter_errors(bad)), f"image.{key} = {value!r} must fail the schema"


def test_the_reference_states_the_limits_the_code_enforces():
    from renderer.scene import file as scenefile

    text = formats.build()["file_formats.md"]
    for needle in (f"`spp` ≤ {scenefile.MAX_SPP}", f"`max_depth` ≤ {scenefile.MAX_DEPTH}", "| `radius` |",
                   "diameter of the blur disc", "Overflow policy"):
        assert needle in text, f"file_formats.md lacks {needle!r}"


def test_schema_and_validator_agree_on_optional_sections():
    """camera.distortion and animation: accepted by the validator and by the schema alike."""
    from renderer.scene.file import build_scene

    validator = jsonschema.Draft202012Validator(json.loads(formats.build()["schemas/scene.schema.json"]))
    cfg = read_scene_json(os.path.join(ROOT, "renderer", "scenes", "fig6.json"))
    cfg["camera"]["distortion"] = {"model": "brown_conrady", "coefficients": [0.1, 0.0, 0.0, 0.0]}
    cfg["animation"] = {"frames": 3, "step": 0.5}
    assert not [e.message for e in validator.iter_errors(cfg)], "the schema accepts distortion and animation"
    assert build_scene(cfg) is not None, "the validator accepts them"
    cfg["camera"]["distortion"]["coefficients"] = [0.0] * 9
    assert list(validator.iter_errors(cfg)), "nine coefficients fail the schema"
