"""Commands that start at once (issue 32 §2): `--help` and bad input of `tiltfit` and `renderer` are answered
without importing torch (seconds of start-up), and `import renderer` alone loads none of it; each case runs in
a fresh interpreter and reads `sys.modules` after the command returns. The heavy libraries stay available: the
public names still resolve (and `renderer.render` is the function, as before)."""
from __future__ import annotations

import json
import os
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TARGET = os.path.join(ROOT, "data", "real", "industrial_ds1", "target.json")
HEAVY = ("torch", "kornia", "matplotlib", "cv2", "mitsuba")

RUN = """
import json, sys
from {package}.cli.main import main
try:
    rc = main({argv!r})
except SystemExit as e:
    rc = e.code
print(json.dumps({{"rc": rc, "loaded": [m for m in {heavy!r} if m in sys.modules]}}))
"""


def run_command(package: str, argv: list[str]) -> dict:
    """{rc, loaded}: the exit status of `package`'s command and the heavy libraries it imported."""
    code = RUN.format(package=package, argv=argv, heavy=HEAVY)
    p = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, f"the probe failed: {p.stderr[-2000:]}"
    return json.loads(p.stdout.strip().splitlines()[-1]) | {"stderr": p.stderr}


def cases(tmp):
    bad = os.path.join(tmp, "bad.json")
    with open(bad, "w", encoding="utf-8") as f:
        f.write('{"image": \n')
    missing = os.path.join(tmp, "nope.png")
    return [
        ("tiltfit", ["--help"], 0, None),
        ("tiltfit", ["calibrate", "--help"], 0, None),
        ("tiltfit", ["detect", missing, "--target", TARGET, "-o", os.path.join(tmp, "d.json")], 2, "no such file"),
        ("tiltfit", ["calibrate", missing, "--target", TARGET, "--pixel-pitch-mm", "0", "-o",
                     os.path.join(tmp, "c.json")], 2, "--pixel-pitch-mm"),
        ("tiltfit", ["calibrate", missing, "--target", TARGET, "--pixel-pitch-mm", "0.005", "-o",
                     os.path.join(tmp, "c.json")], 2, "no such file"),
        ("tiltfit", ["export", os.path.join(tmp, "nope.json"), "-o", os.path.join(tmp, "cam.yml")], 2, "no such file"),
        ("tiltfit", ["compare", bad, bad], 2, "not valid JSON"),
        ("tiltfit", ["target", "design", "--cols", "1", "--rows", "8", "--square-mm", "20", "--w-mm", "50",
                     "--distance-mm", "500", "-o", os.path.join(tmp, "t.json")], 2, "--cols"),
        ("renderer", ["--help"], 0, None),
        ("renderer", ["render", "--help"], 0, None),
        ("renderer", ["render", os.path.join(tmp, "nope.json"), "-o", os.path.join(tmp, "o.png")], 2,
         "cannot read scene file"),
        ("renderer", ["render", bad, "-o", os.path.join(tmp, "o.png")], 2, "not valid JSON"),
        ("renderer", ["render", "fig7", "-o", os.path.join(tmp, "o.xyz")], 2, "unsupported output format"),
        ("renderer", ["gallery", "--manifest", bad], 2, "not valid JSON"),
    ]


def test_help_and_bad_input_do_not_import_torch(tmp_path):
    """Each case exits as it should, with its one-line message, and imports none of torch, kornia, matplotlib,
    cv2, mitsuba (before the lazy imports every one of them loaded torch first)."""
    for package, argv, rc, message in cases(str(tmp_path)):
        got = run_command(package, argv)
        shown = f"{package} {' '.join(argv)}"
        assert got["rc"] == rc, f"{shown}: exit {got['rc']}, expected {rc}: {got['stderr'][-500:]}"
        if message:
            assert message in got["stderr"] and got["stderr"].count("\n") == 1, \
                f"{shown}: expected one line naming {message!r}, got {got['stderr']!r}"
        assert got["loaded"] == [], f"{shown}: imported {got['loaded']} before answering"
    assert not os.path.exists(tmp_path / "o.png") and not os.path.exists(tmp_path / "c.json"), "no output expected"


def test_import_renderer_is_light_and_its_names_resolve():
    """`import renderer` loads no torch; its public names load on first use, `renderer.render` stays the function
    after the submodule of the same name is imported, and a negative control (a name that is not there) still
    raises AttributeError."""
    code = """
import json, sys
import renderer
light = "torch" not in sys.modules
import renderer.tracing.render
fn = callable(renderer.render) and not isinstance(renderer.render, type(sys))
from renderer import load_scene, Scene, SceneError
from renderer import render
names = sorted(n for n in renderer.__all__ if not hasattr(renderer, n))
try:
    renderer.no_such_name
    missing = False
except AttributeError:
    missing = True
print(json.dumps({"light": light, "fn": fn and render is renderer.render, "unresolved": names, "missing": missing,
                  "torch": "torch" in sys.modules}))
"""
    p = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr[-2000:]
    got = json.loads(p.stdout.strip().splitlines()[-1])
    assert got["light"], "import renderer loaded torch"
    assert got["fn"], "renderer.render is not the render function after `import renderer.tracing.render`"
    assert got["unresolved"] == [], f"public names that do not resolve: {got['unresolved']}"
    assert got["missing"], "renderer.no_such_name did not raise AttributeError"
    assert got["torch"], "the public names resolved without loading torch: the check above would prove nothing"
