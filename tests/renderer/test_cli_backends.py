"""`renderer render --backend mitsuba` and `--cluster` (renderer/cli/backends.py)."""
import os

import numpy as np
import pytest

pytest.importorskip("mitsuba")

from renderer import render  # noqa: E402
from renderer.cli.main import main  # noqa: E402
from camio.files import read_image  # noqa: E402
from renderer.scene.file import load_scene  # noqa: E402

pytestmark = pytest.mark.usefixtures("restore_mitsuba_variant")  # conftest: no variant left behind

SCENE = os.path.join(os.path.dirname(__file__), "..", "..", "benchmarks", "scenes", "speed_thin_lens.json")
SMALL = ["--set", "image.width=24", "--set", "image.height=24", "--set", "camera.theta_F_deg=15"]


@pytest.mark.slow  # about 8 s in Mitsuba's scalar variant (the tilted lens is a Python plugin there)
def test_backend_mitsuba_renders_our_image(tmp_path, capsys):
    """The Mitsuba render of the tilted-lens scene with an ambient light and a background has our mean
    intensity (within 1 % at 256 spp: both are composited from Mitsuba's albedo and alpha), and the one-line
    report names only the sampler."""
    out = str(tmp_path / "m.exr")
    extra = ["--set", 'lights=[{"type": "point", "position": [-1.5, -1.5, -1.0], "intensity": [70, 70, 70]},'
                      '{"type": "ambient", "intensity": [0.1, 0.1, 0.1]}]', "--set", "image.background=[0.2,0.3,0.4]"]
    rc = main(["render", SCENE, "-o", out, "--spp", "256", "--backend", "mitsuba", *SMALL, *extra])
    assert rc == 0, f"exit status {rc}"
    err = capsys.readouterr().err
    assert "not mapped: sampler sobol (Mitsuba's independent sampler used)\n" in err, f"stderr: {err!r}"
    theirs = read_image(out)[..., :3]
    scene = load_scene(SCENE, [v for v in SMALL[1::2]] + extra[1::2])
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


DISTORTED = ["--set", 'camera.distortion={"model": "brown_conrady", "coefficients": [-0.3, 0.1, 0, 0, 0]}']
# Barrel distortion too strong to invert at the image's corners: our camera gives samples there no ray.
UNINVERTIBLE = ["--set", 'camera.distortion={"model": "brown_conrady", "coefficients": [-0.6, 0, 0, 0, 0]}']
TINY = ["--set", "image.width=32", "--set", "image.height=24", "--spp", "1"]
BEYOND = ("camera.distortion beyond its invertible zone (ours averages a pixel's valid samples, Mitsuba counts the "
          "others black)")


def _mitsuba_line(err: str) -> str:
    lines = [line for line in err.splitlines() if line.startswith("renderer: mitsuba")]
    assert len(lines) == 1, f"expected one 'renderer: mitsuba' line on stderr, got {err!r}"
    return lines[0]


def test_export_maps_a_distortion_and_names_where_it_does_not_invert():
    """to_mitsuba carries a camera.distortion over (our sensor plugin traces each pixel through its undistorted
    position), naming it only where the distortion does not invert over the whole image; an all-zero one or
    none adds nothing."""
    from renderer.mitsuba import to_mitsuba

    zero = ['camera.distortion={"model": "brown_conrady", "coefficients": [0, 0, 0, 0, 0]}']
    for overrides, expected in ((DISTORTED[1::2], []), (UNINVERTIBLE[1::2], [BEYOND]), (zero, []), ([], [])):
        _, dropped = to_mitsuba(load_scene(SCENE, ["image.width=8", "image.height=8", *overrides]), 1)
        assert dropped == expected, f"overrides {overrides}: dropped {dropped}, expected {expected}"


@pytest.mark.slow  # about 9 s in Mitsuba's scalar variant (the undistortion runs per sample in Python there)
def test_distorted_camera_renders_our_image():
    """A distorted tilted thin lens (through our plugin) and a distorted pinhole: Mitsuba's mean intensity is
    ours within 1 %, and pixel by pixel far closer than without the distortion."""
    from renderer.cli.backends import render_mitsuba

    for camera in (["camera.theta_F_deg=15"], ['camera={"type": "pinhole", "fov_deg": 50}']):
        size = ["image.width=24", "image.height=24", *camera]
        scene = load_scene(SCENE, size + DISTORTED[1::2])
        ours = render(scene, spp=64, intersector="torch").image.numpy()
        theirs = render_mitsuba(scene, 64, "independent", progress=False).image.numpy()
        plain = render_mitsuba(load_scene(SCENE, size), 64, "independent", progress=False).image.numpy()
        rel = theirs.mean() / ours.mean() - 1
        assert abs(rel) < 0.01, f"{camera}: mean Mitsuba {theirs.mean():.5f} vs ours {ours.mean():.5f}"
        diff, undistorted = np.abs(theirs - ours).mean(), np.abs(plain - ours).mean()
        assert diff < 0.5 * undistorted, f"{camera}: per-pixel {diff:.4f}, without the distortion {undistorted:.4f}"


def test_mitsuba_line_names_distortion_sampler_and_ignored_options(tmp_path, capsys):
    """A distortion that does not invert at the corners, the scene-default sobol sampler and
    --intersector/--compile given: all named in the one line (even with --quiet), and the image records the
    sampler Mitsuba used."""
    from camio.files import image_metadata

    out = str(tmp_path / "m.exr")
    rc = main(["render", SCENE, "-o", out, "--backend", "mitsuba", "--quiet", "--intersector", "torch", "--compile",
               *TINY, *UNINVERTIBLE])
    assert rc == 0, f"exit status {rc}"
    err = capsys.readouterr().err
    line = _mitsuba_line(err)
    assert err.count("\n") == 1, f"--quiet: only the one line expected, got {err!r}"
    for item in (BEYOND, "sampler sobol (Mitsuba's independent sampler used)",
                 "--intersector torch ignored", "--compile ignored"):
        assert item in line, f"{item!r} missing from {line!r}"
    meta = image_metadata(out)
    assert (meta.get("sampler"), meta.get("backend")) == ("independent", "mitsuba"), f"metadata {meta}"


def test_mitsuba_line_lists_nothing_for_an_exact_scene(tmp_path, capsys):
    """Undistorted camera, --sampler independent, no torch-only options: 'not mapped: nothing', and with
    --quiet not even that."""
    out = str(tmp_path / "m.exr")
    rc = main(["render", SCENE, "-o", out, "--backend", "mitsuba", "--sampler", "independent", *TINY])
    assert rc == 0, f"exit status {rc}"
    line = _mitsuba_line(capsys.readouterr().err)
    assert line.endswith("not mapped: nothing"), f"stderr line {line!r}"
    rc = main(["render", SCENE, "-o", out, "--backend", "mitsuba", "--sampler", "independent", "--quiet", *TINY])
    err = capsys.readouterr().err
    assert rc == 0 and err == "", f"exit status {rc}, stderr {err!r} (expected silence)"


def test_compile_with_cluster_is_named(monkeypatch, tmp_path, capsys):
    """--compile with --cluster: the cluster traces uncompiled, and one stderr line says so."""
    import renderer.tracing.distributed as distributed

    seen = {}

    def fake_render_on_ray(scene, spp, sampler, **kw):
        seen["called"] = True
        return render(scene, spp=1)

    monkeypatch.setattr(distributed, "render_on_ray", fake_render_on_ray)
    rc = main(["render", SCENE, "-o", str(tmp_path / "c.exr"), "--cluster", "auto", "--compile", "--quiet", *TINY])
    err = capsys.readouterr().err
    assert rc == 0 and seen.get("called"), f"exit status {rc}, render_on_ray called: {seen}"
    assert err == "renderer: --compile ignored with --cluster (the workers trace uncompiled)\n", f"stderr {err!r}"


def test_device_with_mitsuba_is_named(capsys):
    """Mitsuba renders on its own (CPU) variant: a --device other than cpu is named as ignored."""
    from renderer.cli.backends import render_with

    scene = load_scene(SCENE, ["image.width=8", "image.height=8"])
    result = render_with("mitsuba", None, scene, 1, "independent", device="cuda", seed=0, progress=False)
    line = _mitsuba_line(capsys.readouterr().err)
    assert result.image.shape == (8, 8, 3), f"image shape {tuple(result.image.shape)}"
    assert line.endswith("not mapped: --device cuda ignored"), f"stderr line {line!r}"
