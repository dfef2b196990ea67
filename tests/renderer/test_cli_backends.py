"""`renderer render --backend mitsuba` and `--cluster` (renderer/backends.py)."""
import os

import pytest

pytest.importorskip("mitsuba")

from renderer import render  # noqa: E402
from renderer.cli import main  # noqa: E402
from renderer.io import read_image  # noqa: E402
from renderer.scenefile import load_scene  # noqa: E402

SCENE = os.path.join(os.path.dirname(__file__), "..", "..", "benchmarks", "scenes", "speed_thin_lens.json")
SMALL = ["--set", "image.width=24", "--set", "image.height=24", "--set", "camera.theta_F_deg=15"]


def test_backend_mitsuba_renders_our_image(tmp_path, capsys):
    """The Mitsuba render of the tilted-lens scene has our mean intensity (within 1 % at 256 spp) and the
    one-line report of what was not mapped (here: the ambient light)."""
    out = str(tmp_path / "m.exr")
    extra = ["--set", 'lights=[{"type": "point", "position": [-1.5, -1.5, -1.0], "intensity": [70, 70, 70]},'
                      '{"type": "ambient", "intensity": [0.0, 0.0, 0.0]}]']
    rc = main(["render", SCENE, "-o", out, "--spp", "256", "--backend", "mitsuba", *SMALL, *extra])
    assert rc == 0, f"exit status {rc}"
    err = capsys.readouterr().err
    assert "not mapped: lights[1]: type ambient" in err, f"stderr: {err!r}"
    theirs = read_image(out)[..., :3]
    scene = load_scene(SCENE, [v for v in SMALL[1::2]] + [extra[1]])
    ours = render(scene, spp=256, intersector="torch").image.numpy()  # our tracer against Mitsuba
    assert theirs.shape == ours.shape, f"image shape {theirs.shape} vs ours {ours.shape}"
    rel = abs(float(theirs.mean()) / float(ours.mean()) - 1)
    assert rel < 0.01, f"mean intensity Mitsuba {theirs.mean():.5f} vs ours {ours.mean():.5f}"


def test_cluster_with_mitsuba_is_a_usage_error(tmp_path, capsys):
    rc = main(["render", SCENE, "-o", str(tmp_path / "x.exr"), "--backend", "mitsuba", "--cluster", "auto", *SMALL])
    assert rc == 2, f"exit status {rc}"
    assert "--cluster works with the torch backend only" in capsys.readouterr().err, "one-line message expected"


def test_unreachable_cluster_is_a_one_line_error(tmp_path, capsys):
    """A cluster address where nothing listens fails fast (Ray itself would retry for minutes), exit 2."""
    pytest.importorskip("ray")
    out = tmp_path / "x.exr"
    rc = main(["render", SCENE, "-o", str(out), "--cluster", "127.0.0.1:9", *SMALL])
    err = capsys.readouterr().err
    assert rc == 2, f"exit status {rc}"
    assert "--cluster 127.0.0.1:9: cannot reach" in err and err.count("\n") == 1, f"stderr: {err!r}"
    assert not out.exists(), "no output file on error"
