"""The compiled direct-light path for Embree renders (`renderer.tracing.fused`, `render(intersector="mitsuba",
compile=True)`) against the eager path with the same intersector: the same samples, camera rays and shading
formulas, so the images agree to float rounding (Inductor may contract or reorder float operations; a ray
grazing an edge could then change its hit, hence the small allowance for a few pixels).

The compared scene exercises what `fused.applies` admits beyond the issue-11 speed scene (a tilted lens on a
turned camera, a turned and an aligned checkered rectangle, a plane, a turned box, a sphere, two point lights
and an ambient one, a background); the speed scene itself is checked for taking the path.
Skipped where Mitsuba's llvm variant cannot run.
"""
from __future__ import annotations

import os

import pytest
import torch

pytest.importorskip("mitsuba")
from renderer.mitsuba.variants import jit_variant_runs  # noqa: E402

if not jit_variant_runs("llvm_ad_rgb"):
    pytest.skip("mitsuba's llvm_ad_rgb variant does not run here (needs LLVM >= 16)", allow_module_level=True)

from renderer.tracing import fused
from renderer import render  # noqa: E402
from renderer.scene.model import TraceOptions  # noqa: E402
from renderer.scene.file import build_scene, load_scene  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SPEED = os.path.join(ROOT, "benchmarks", "scenes", "speed_thin_lens.json")
FUSED = TraceOptions(intersector="mitsuba", compile=True)


def _speed(size=24, spp=4):
    return load_scene(SPEED, [f"image.width={size}", f"image.height={size}", f"image.spp={spp}"])


def _mixed():
    checker = {"type": "checker", "size": 0.4, "colors": [[0.9, 0.8, 0.6], [0.2, 0.3, 0.7]]}
    return build_scene({
        "image": {"width": 16, "height": 16, "spp": 4, "max_depth": 0, "background": [0.1, 0.2, 0.3]},
        "camera": {"type": "thin_lens", "position": [0.3, -0.6, 0.0], "look_at": [0.0, 0.0, 4.0], "w": 1.0,
                   "U": 4.0, "d": 0.1, "theta_F_deg": 20, "sensor_size": [1.2, 1.0]},
        "lights": [{"type": "point", "position": [-1.5, -1.5, -1.0], "intensity": [40, 50, 60]},
                   {"type": "point", "position": [2.0, -2.0, 1.0], "intensity": [20, 10, 5]},
                   {"type": "ambient", "intensity": [0.1, 0.1, 0.1]}],
        "objects": [
            {"name": "plate", "shape": {"type": "rectangle", "center": [0, 0, 5.0], "size": [5.0, 5.0], "rotation_deg": [10, 20, 5]},
             "material": {"color": [0.8, 0.8, 0.8], "texture": checker}},
            {"name": "tile", "shape": {"type": "rectangle", "center": [1.0, 0.6, 3.0], "size": [1.0, 0.8]},
             "material": {"color": [0.7, 0.7, 0.7], "texture": {**checker, "size": 0.25}}},
            {"name": "floor", "shape": {"type": "plane", "point": [0, 1.5, 0], "normal": [0, -1, 0]}, "material": {"color": [0.5, 0.6, 0.5]}},
            {"name": "box", "shape": {"type": "box", "center": [-0.8, 0.2, 4.0], "size": [0.6, 0.7, 0.8], "rotation_deg": [0, 30, 10]},
             "material": {"color": [0.8, 0.15, 0.1]}},
            {"name": "ball", "shape": {"type": "sphere", "center": [0.7, -0.3, 3.5], "radius": 0.5}, "material": {"color": [0.2, 0.7, 0.3]}},
        ]})


def test_applies_only_when_asked():
    scene = _speed()
    assert fused.applies(scene, FUSED, "cpu", torch.float32), "the speed scene should take the fused path"
    assert fused.applies(_mixed(), FUSED, "cpu", torch.float32), "the mixed scene should take the fused path"
    for options, dtype in [(TraceOptions(intersector="mitsuba"), torch.float32),  # eager: the defaults' path
                           (TraceOptions(intersector="torch", compile=True), torch.float32),
                           (FUSED, torch.float64)]:
        assert not fused.applies(scene, options, "cpu", dtype), f"fused path taken for {options}, {dtype}"
    specular = load_scene(SPEED, ["image.width=8", "image.height=8", "objects.1.material.specular=0.5"])
    assert not fused.applies(specular, FUSED, "cpu", torch.float32), "a Phong lobe is not in the fused shading"


@pytest.mark.slow
@pytest.mark.xdist_group("inductor")  # with test_render.py's compiled tracing: Inductor's set-up once a run
def test_fused_matches_eager():
    # One scene (each scene compiles its own stages: about 20 s with an empty Inductor cache); the speed scene's
    # image is compared at full size by benchmarks/renderer/bench_speed_mitsuba.py (image means).
    scene = _mixed()
    eager = render(scene, intersector="mitsuba", workers=1).image
    got = render(scene, intersector="mitsuba", compile=True, workers=1)
    image = got.image
    assert image.shape == eager.shape, f"shape {tuple(image.shape)} != {tuple(eager.shape)}"
    assert torch.equal(got.coverage, torch.ones_like(got.coverage)), "every thin-lens sample is valid"
    diff = (image - eager).abs().amax(-1)
    scale = float(eager.abs().max())
    assert 0.05 < float(eager.mean()) < 10, f"test scene too dark or bright to compare: mean {float(eager.mean())}"
    off = float((diff > 1e-5 * scale).float().mean())
    assert off <= 0.01, f"{off:.2%} of pixels differ by more than float rounding (max {float(diff.max()):.3g})"
    assert abs(float(image.mean() - eager.mean())) <= 1e-5 * scale, "mean intensity differs"
    # Batches of 128 of its 256 pixels: the image does not depend on the batch size.
    chunked = render(scene, intersector="mitsuba", compile=True, workers=1, chunk_rays=512).image
    assert torch.allclose(chunked, image, rtol=0, atol=1e-5 * scale), "image depends on the batch size"


def test_padding_repeats_the_last_pixel():
    """A short batch is padded to a power of two of pixels (at least 64) by its last pixel; the estimates
    of the real pixels come first (checked without compiling: `_padded` alone)."""
    pixel = torch.tensor([5, 9, 2])
    padded = fused._padded(pixel)
    assert padded.shape == (64,), f"padded to {tuple(padded.shape)}, expected (64,)"
    assert torch.equal(padded[:3], pixel) and bool((padded[3:] == 2).all()), "padding should repeat the last pixel"
    assert fused._padded(torch.arange(128)).shape == (128,), "a power of two is not padded"


def test_camera_and_lights_read_afresh():
    """A camera or light changed between renders is seen (the constants the compiled stages take)."""
    scene = _speed()
    tables, before = fused._state(scene)
    scene.camera.lens = scene.camera.lens.with_(U=5.0)
    scene.lights[0] = type(scene.lights[0])(type="point", position=(1.0, 2.0, 3.0), intensity=(1.0, 1.0, 1.0))
    tables_after, after = fused._state(scene)
    assert before[9] == 4.0 and after[9] == 5.0, f"focus distance U not read afresh: {before[9]} -> {after[9]}"
    assert tables_after is not tables and tables_after.lights[0][2] == [1.0, 2.0, 3.0], "lights not rebuilt"


def test_cli_compile_flag_reaches_render(tmp_path, monkeypatch):
    """`renderer render --compile` asks `render` for compile=True (the fused stages with the Embree
    intersector); without the flag the scene's own setting stands (compile=None)."""
    import sys

    from renderer.cli.main import main as cli_main

    render_module = sys.modules["renderer.tracing.render"]
    seen = []
    real = render_module.render

    def spy(scene, *args, **kwargs):
        seen.append(kwargs.get("compile"))
        return real(scene, *args, **{**kwargs, "compile": None})  # the flag's path, without compiling here

    monkeypatch.setattr(render_module, "render", spy)
    small = ["--set", "image.width=16", "--set", "image.height=16", "--set", "image.spp=1"]
    for flags, want in ((["--compile"], True), ([], None)):
        code = cli_main(["render", SPEED, "-o", str(tmp_path / "x.exr"), "--quiet", *small, *flags])
        assert code == 0 and seen and seen[-1] is want, f"flags {flags}: exit {code}, compile seen {seen}"


@pytest.mark.slow
@pytest.mark.xdist_group("inductor")  # with test_render.py's compiled tracing: Inductor's set-up once a run
def test_a_new_seed_does_not_compile_again():
    """The sampler's seed reaches the compiled stages as a tensor, not a constant: renders with new seeds
    (animation frames, repeats) reuse the compiled code. With the seed baked in, each seed compiled the stages
    again, and past torch's recompile limit they ran uncompiled (0.23 s against 0.14 s on the speed scene)."""
    from torch._dynamo.utils import counters

    scene = _mixed()
    first = render(scene, intersector="mitsuba", compile=True, workers=1, seed=0).image
    compiled = sum(counters["frames"].values())
    images = [render(scene, intersector="mitsuba", compile=True, workers=1, seed=s).image for s in (1, 2, 3)]
    assert sum(counters["frames"].values()) == compiled, \
        f"new seeds compiled again: frame counters {dict(counters['frames'])}, {compiled} before"
    assert not torch.equal(images[0], first) and not torch.equal(images[0], images[1]), "the seed changes the samples"
    eager = render(scene, intersector="mitsuba", workers=1, seed=2).image
    scale = float(eager.abs().max())
    assert torch.allclose(images[1], eager, rtol=0, atol=1e-4 * scale), "seed 2: fused differs from eager"
