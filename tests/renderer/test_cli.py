"""The `renderer` command: render to PNG/EXR, overrides, the gallery, and one-line errors with exit status 2."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from renderer.cli.main import main
from camio.files import read_image
from renderer.tracing.render import render
from renderer.scene.file import load_scene


def scene_dict(width=16, height=12):
    return {
        "image": {"width": width, "height": height, "spp": 2, "background": [0.1, 0.2, 0.3]},
        "camera": {"type": "pinhole", "fov_deg": 50},
        "lights": [{"type": "point", "position": [2, -3, 0], "intensity": [20, 20, 20]},
                   {"type": "ambient", "intensity": 0.05}],
        "objects": [{"name": "ball", "shape": {"type": "sphere", "center": [0, 0, 4], "radius": 1},
                     "material": {"color": [0.9, 0.3, 0.2]}}],
    }


@pytest.fixture
def scene_file(tmp_path):
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(scene_dict()))
    return str(path)


def run_cli(capsys, *argv):
    code = main(list(argv))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_render_png_is_8bit_srgb_of_the_right_size(tmp_path, scene_file, capsys):
    out = tmp_path / "out.png"
    code, _, err = run_cli(capsys, "render", scene_file, "-o", str(out), "--spp", "1")
    assert code == 0, f"render failed: {err}"
    image = read_image(str(out))
    assert image.shape == (12, 16, 3), f"PNG has the scene's size, got {image.shape}"
    assert "render:" in err, "progress goes to stderr"


def test_render_exr_keeps_the_linear_render(tmp_path, scene_file, capsys):
    out = tmp_path / "out.exr"
    code, _, err = run_cli(capsys, "render", scene_file, "-o", str(out), "--quiet", "--sampler", "stratified")
    assert code == 0, err
    assert err == "", "--quiet prints nothing"
    expected = render(load_scene(scene_file), sampler="stratified").image.numpy()
    assert np.allclose(read_image(str(out)), expected, atol=1e-6), "EXR holds the linear float image"


def test_set_overrides_and_shipped_scene_names(tmp_path, capsys):
    out = tmp_path / "fig.png"
    code, _, err = run_cli(capsys, "render", "fig7", "-o", str(out), "--quiet", "--spp", "1",
                           "--set", "image.width=9", "--set", "image.height=7", "--set", "camera.alpha=1")
    assert code == 0, err
    assert read_image(str(out)).shape == (7, 9, 3), "--set image.width/height changed the output size"


@pytest.mark.parametrize("problem,expected", [
    ("unknown_key", "scene.json: objects[0].material.gloss: unknown key"),
    ("bad_json", "scene.json:1:"),
    ("missing", "missing.json: cannot read scene file"),
    ("bad_set", "--set objects.5.material.reflect=1: objects has no element '5'"),
    ("bad_ext", "out.bmp: unsupported output format .bmp"),
    ("bad_folder", "is not a folder"),
])
def test_errors_are_one_line_exit_2_and_leave_no_file(tmp_path, capsys, problem, expected):
    cfg = scene_dict()
    out = tmp_path / ("out.bmp" if problem == "bad_ext" else "out.png")
    extra = []
    if problem == "unknown_key":
        cfg["objects"][0]["material"]["gloss"] = 1
    if problem == "bad_set":
        extra = ["--set", "objects.5.material.reflect=1"]
    if problem == "bad_folder":
        (tmp_path / "file").write_text("")
        out = tmp_path / "file" / "out.png"
    scene = tmp_path / ("missing.json" if problem == "missing" else "scene.json")
    if problem != "missing":
        scene.write_text("{,}" if problem == "bad_json" else json.dumps(cfg))
    before = sorted(os.listdir(tmp_path))
    code, out_text, err = run_cli(capsys, "render", str(scene), "-o", str(out), "--quiet", *extra)
    assert code == 2, f"exit status 2 for {problem}, got {code}"
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("renderer: "), f"one 'renderer: ...' line, got {err!r}"
    assert expected in lines[0], f"{expected!r} not in {lines[0]!r}"
    assert sorted(os.listdir(tmp_path)) == before, "no output or temporary file left behind"


def test_gallery_writes_a_labelled_contact_sheet(tmp_path, scene_file, capsys):
    manifest = tmp_path / "gallery.json"
    manifest.write_text(json.dumps([
        {"scene": "scene.json", "label": "plain"},
        {"scene": "scene.json", "label": "green", "set": ["objects.ball.material.color=[0,1,0]"], "note": "x"},
    ]))
    out = tmp_path / "sheet.png"
    code, _, err = run_cli(capsys, "gallery", "--manifest", str(manifest), "-o", str(out), "--size", "8", "--spp", "1")
    assert code == 0, err
    assert "[2/2] green (8x6, 1 spp)" in err, f"progress per panel with its size: {err!r}"
    sheet = read_image(str(out))
    assert sheet.shape[0] > 50 and sheet.shape[1] > 100, f"a two-panel sheet, got {sheet.shape}"


def test_gallery_manifest_errors_name_the_entry(tmp_path, capsys):
    manifest = tmp_path / "gallery.json"
    manifest.write_text(json.dumps([{"scene": "scene.json", "lable": "typo"}]))
    code, _, err = run_cli(capsys, "gallery", "--manifest", str(manifest), "-o", str(tmp_path / "g.png"))
    assert code == 2 and "[0].lable: unknown key" in err, err
    assert not (tmp_path / "g.png").exists(), "no contact sheet on error"


def test_python_m_renderer_help_and_error_without_traceback(tmp_path):
    env = dict(os.environ, OMP_NUM_THREADS="1")
    help_ = subprocess.run([sys.executable, "-m", "renderer", "--help"], capture_output=True, text=True, env=env)
    assert help_.returncode == 0 and "render" in help_.stdout and "gallery" in help_.stdout, help_.stderr
    bad = tmp_path / "bad.json"
    bad.write_text('{"image": {"width": 4, "height": 4}, "camera": {"fov_deg": NaN}}')
    run = subprocess.run([sys.executable, "-m", "renderer", "render", str(bad), "-o", str(tmp_path / "x.png")],
                         capture_output=True, text=True, env=env)
    assert run.returncode == 2, run.stderr
    assert run.stderr.strip() == f"renderer: {bad}: camera.fov_deg: expected a finite number, got nan", run.stderr
    assert not (tmp_path / "x.png").exists(), "no output on error"
