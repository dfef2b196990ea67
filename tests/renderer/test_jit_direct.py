"""The default path of Embree renders for direct-light thin-lens scenes (`renderer.tracing.jit_direct`): the whole
batch as Dr.Jit kernels beside Embree.

- It is taken by `render(scene)` (defaults) for the speed scene and the mixed scene of tests/renderer/test_fused.py
  (turned camera and tilted lens, checkered rectangles turned and aligned, a plane, a turned box, a sphere, two
  point lights and an ambient one, a background), with Phong lobes, a checkered plane and image textures, and
  not where its formulas do not reach (a mirror, a grid texture, compile=True, our own intersector, float64).
- Its Sobol samples are `Sampler.pixel_block`'s bit for bit; its images equal our own tracer's (different
  intersection code, torch shading) to float rounding for every sampler.
- `workers=None` on it starts no worker processes and runs Dr.Jit's pool on the cores during the render only;
  the image does not depend on the threads, the workers or the batch size.
Skipped where Mitsuba's llvm variant cannot run.
"""
from __future__ import annotations

import os
import signal
import sys

import pytest
import torch

pytest.importorskip("mitsuba")
from renderer.mitsuba.variants import jit_variant_runs  # noqa: E402

if not jit_variant_runs("llvm_ad_rgb"):
    pytest.skip("mitsuba's llvm_ad_rgb variant does not run here (needs LLVM >= 16)", allow_module_level=True)

from renderer import render  # noqa: E402
from renderer.scene.file import build_scene, load_scene  # noqa: E402
from renderer.scene.model import TraceOptions  # noqa: E402
from renderer.tracing import jit_direct  # noqa: E402
from renderer.tracing.sampling import Sampler, camera_samples  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from test_fused import SPEED, _mixed, _speed  # noqa: E402

RENDER = sys.modules["renderer.tracing.render"]
EMBREE = TraceOptions(intersector="mitsuba")


def _phong():
    """The mixed scene with Phong lobes (one with exponent 0: 0^0 = 1) and a checkered floor plane."""
    scene = _mixed()
    from dataclasses import replace

    from renderer.scene.materials import CheckerTexture

    floor, box, ball = scene.objects[2], scene.objects[3], scene.objects[4]
    box.material = replace(box.material, specular=0.4, shininess=40.0)
    ball.material = replace(ball.material, specular=0.3, shininess=0.0)
    floor.material = replace(floor.material, texture=CheckerTexture(0.3, ((0.9, 0.9, 0.8), (0.2, 0.2, 0.3))))
    scene.refresh()
    return scene


def test_applies_to_the_defaults_scenes_only():
    assert jit_direct.applies(_speed(), EMBREE, "cpu", torch.float32), "the speed scene should take the Dr.Jit path"
    assert jit_direct.applies(_mixed(), EMBREE, "cpu", torch.float32), "the mixed scene should take the Dr.Jit path"
    assert jit_direct.applies(_phong(), EMBREE, "cpu", torch.float32), "Phong lobes and a checkered plane too"
    assert jit_direct.applies(_images(), EMBREE, "cpu", torch.float32), "and image textures on flat shapes"
    for options, dtype in [(TraceOptions(intersector="mitsuba", compile=True), torch.float32),  # fused: opt-in
                           (TraceOptions(intersector="torch"), torch.float32),
                           (TraceOptions(intersector="mitsuba", fast_paths=False), torch.float32),
                           (TraceOptions(intersector="mitsuba", jit_kernels=False), torch.float32),  # eager
                           (EMBREE, torch.float64)]:
        assert not jit_direct.applies(_speed(), options, "cpu", dtype), f"Dr.Jit path taken for {options}, {dtype}"
    tensors = _speed(size=16, spp=2)  # numbers as tensors cannot be the kernel's constants
    tensors.camera.lens = tensors.camera.lens.with_(principal_point_px=(torch.tensor(8.0), torch.tensor(8.0)))
    assert not jit_direct.applies(tensors, EMBREE, "cpu", torch.float32), "a principal point given as tensors"
    assert float(render(tensors).image.mean()) > 0.1, "renders on the eager path"
    mirror = load_scene(SPEED, ["image.width=8", "image.height=8", "objects.1.material.reflect=0.5"])
    assert not jit_direct.applies(mirror, EMBREE, "cpu", torch.float32), "a mirror needs the bounces"


def test_not_for_a_grid_texture():
    # A grid texture has a palette (the fused path indexes it with searchsorted) but no formula here.
    from dataclasses import replace

    from renderer.scene.materials import GridTexture

    scene = _speed(size=8, spp=1)
    plate = scene.objects[0]
    grid = GridTexture([-3.0, 0.0, 3.0], [-3.0, 3.0], [[0, 1]], ((0.9, 0.9, 0.9), (0.1, 0.1, 0.1)))
    plate.material = replace(plate.material, texture=grid)
    scene.refresh()
    assert not jit_direct.applies(scene, EMBREE, "cpu", torch.float32), "a grid texture is not shaded here"
    assert jit_direct.applies(_speed(size=8, spp=1), EMBREE, "cpu", torch.float32), "the checkered plate is"


@pytest.mark.parametrize("intersector", ["auto", "torch", "mitsuba"])
def test_an_empty_scene_renders_its_background(intersector):
    # Neither fast path has tables to gather from without objects (both had failed with an IndexError).
    scene = build_scene({"image": {"width": 8, "height": 6, "spp": 2, "background": [0.1, 0.2, 0.3]},
                         "camera": {"type": "thin_lens", "w": 1.0, "U": 4.0, "d": 0.05, "sensor_size": [1.0, 0.8]},
                         "lights": [{"type": "point", "position": [0, 0, 0], "intensity": [1, 1, 1]}], "objects": []})
    assert not jit_direct.applies(scene, EMBREE, "cpu", torch.float32), "no objects: not the Dr.Jit path"
    image = render(scene, intersector=intersector).image
    want = torch.tensor([0.1, 0.2, 0.3]).expand_as(image)
    assert torch.equal(image, want), f"expected the background everywhere, got {image.mean((0, 1)).tolist()}"


def test_follows_a_replaced_camera_and_lights():
    # A caller may replace the camera or the lights between renders (the objects are what `Scene.refresh` sees).
    from dataclasses import replace

    from renderer.scene.model import Light

    scene = _mixed()
    render(scene, seed=3)
    scene.lights = [Light("point", (30.0, 10.0, 5.0), (1.0, -2.0, 1.0))]
    scene.image = replace(scene.image, background=(0.5, 0.0, 0.0))
    got = render(scene, seed=3).image
    ours = render(scene, seed=3, intersector="torch").image
    assert (got - ours).abs().max() < 1e-3, f"new lights and background: {float((got - ours).abs().max()):.3g} off ours"
    distorted = scene.camera.lens.with_(distortion=(0.05, 0.0, 0.0, 0.0, 0.0))
    scene.camera = scene.camera.with_lens(distorted)
    assert not jit_direct.applies(scene, EMBREE, "cpu", torch.float32), "a distorted lens is not the kernels' camera"


def test_sobol_samples_are_the_samplers():
    scene = _mixed()
    kernel = jit_direct._kernel(scene)
    sampler = Sampler("sobol", 4, seed=3)
    pixel = torch.arange(scene.camera.width * scene.camera.height).flip(0)  # any order, as tiles give
    got = jit_direct._samples(kernel, sampler, pixel, scene.camera.width)
    uv_px, lens_uv = camera_samples(sampler, pixel, scene.camera.width, torch.float32)
    for name, g, want in zip("xyuv", got, (uv_px[:, 0], uv_px[:, 1], lens_uv[:, 0], lens_uv[:, 1])):
        assert torch.equal(g.torch(), want.contiguous()), f"sample row {name} differs from Sampler.pixel_block"


def _images():
    """The mixed scene with image textures (random texels, bilinear) on the turned rectangle and the floor plane."""
    import numpy as np
    from dataclasses import replace

    from renderer.scene.materials import ImageTexture

    scene = _mixed()
    texels = np.random.default_rng(0).random((5, 7, 3)).astype(np.float32)
    for index, size in [(0, (1.3, 0.9)), (2, (0.7, 0.7))]:
        item = scene.objects[index]
        item.material = replace(item.material, texture=ImageTexture("noise.exr", size, texels))
    scene.refresh()
    return scene


@pytest.mark.parametrize("sampler,make", [("sobol", _mixed), ("independent", _mixed), ("stratified", _mixed),
                                         ("center", _mixed), ("sobol", _phong), ("sobol", _images)],
                         ids=lambda v: getattr(v, "__name__", v))
def test_matches_our_tracer(sampler, make):
    scene = make()
    ours = render(scene, sampler=sampler, seed=2, intersector="torch", workers=1)
    got = render(scene, sampler=sampler, seed=2, intersector="mitsuba", workers=1)
    diff = (got.image - ours.image).abs()
    # Float rounding (Dr.Jit's sine and cosine, Embree's hit distances): a grazing ray may change its hit.
    assert (diff > 1e-4).sum() <= 2, f"{int((diff > 1e-4).sum())} pixels differ from our tracer by > 1e-4"
    assert diff.max() < 0.05, f"largest difference {diff.max():.3g}"
    assert float((got.image.mean() - ours.image.mean()).abs()) < 1e-5, "the image mean should agree"
    assert torch.equal(got.coverage, torch.ones_like(got.coverage)), "every thin-lens sample is valid"
    assert float(got.image.std()) > 0.05, "a scene with contrast (not a blank image agreeing with a blank one)"


def test_matches_the_eager_embree_path():
    # The same Embree scene, shaded in torch between the Embree calls (`jit_kernels=False`, the defaults before).
    from dataclasses import replace

    scene = _mixed()
    got = render(scene, seed=4, workers=1).image
    scene.options = replace(scene.options, jit_kernels=False)
    assert not jit_direct.applies(scene, replace(scene.options, intersector="mitsuba"), "cpu", torch.float32)
    eager = render(scene, seed=4, workers=1).image
    diff = (got - eager).abs()
    assert (diff > 1e-4).sum() <= 2, f"{int((diff > 1e-4).sum())} pixels differ from the eager path by > 1e-4"
    assert float((got.mean() - eager.mean()).abs()) < 1e-5, "the image mean should agree"


def test_detects_a_wrong_texel():
    scene = _images()
    ours = render(scene, intersector="torch", workers=1).image
    kernel = jit_direct._kernel(scene)
    obj, tex, origin, axes, offset, texels = kernel.images[0]
    kernel.images[0] = (obj, tex, origin, axes, offset, texels[::-1])  # channels swapped: red and blue
    got = render(scene, intersector="mitsuba", workers=1).image
    assert (got - ours).abs().max() > 0.05, "swapped texel channels should show"


def test_detects_a_wrong_shading():
    # The comparison above must be able to fail: a light twice as bright in the Dr.Jit tables only.
    scene = _mixed()
    ours = render(scene, intersector="torch", workers=1).image
    kernel = jit_direct._kernel(scene)
    kernel.lights = [(kind, [2 * v for v in intensity], position) for kind, intensity, position in kernel.lights]
    got = render(scene, intersector="mitsuba", workers=1).image
    assert (got - ours).abs().max() > 0.01, "a doubled light should show"


def test_a_moved_camera_compiles_no_new_kernel():
    # The camera's numbers are kernel inputs: an animation's next frame reuses the compiled kernel (it had
    # compiled, and cached on disk, one kernel per frame).
    import drjit as dr

    from renderer.core.transforms import CameraTransform

    scene = _mixed()
    first = render(scene, seed=1).image
    R = scene.camera.transform.world_from_camera.T
    moved = CameraTransform.from_extrinsics(R, -R @ (scene.camera.transform.position + torch.tensor([0.05, 0.0, 0.1],
                                                                                             dtype=R.dtype)))
    scene.camera.transform = moved
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()  # cleared
        second = render(scene, seed=1).image
        jit = [e for e in dr.kernel_history() if e["type"] == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert (second - first).abs().max() > 0.01, "the camera moved"
    assert jit and all(e["cache_hit"] for e in jit), f"compiled again: {[e['hash'] for e in jit if not e['cache_hit']]}"


def test_defaults_trace_in_this_process_on_every_core(monkeypatch):
    monkeypatch.setattr(RENDER, "_cores", lambda: 2)
    monkeypatch.setattr(RENDER, "AUTO_WORKERS_MIN_RAYS", 1)
    import drjit as dr

    seen = []
    real = jit_direct.render_pixels
    monkeypatch.setattr(jit_direct, "render_pixels", lambda *a: seen.append(dr.thread_count()) or real(*a))
    pools = dict(RENDER._POOL)
    before = dr.thread_count()
    scene = _speed(size=32, spp=4)
    result = render(scene, seed=5)  # defaults: intersector auto, workers None
    assert seen and set(seen) == {2}, f"Dr.Jit's pool should run on both cores while tracing: {seen}"
    assert dr.thread_count() == before, "Dr.Jit's pool should be restored after the render"
    assert dict(RENDER._POOL) == pools, "no worker processes for the Dr.Jit path"
    one = render(scene, seed=5, workers=1, chunk_rays=64)  # one Dr.Jit thread, batches of 16 pixels
    assert torch.equal(result.image, one.image), "the image should not depend on threads or batch size"


@pytest.mark.slow
def test_explicit_workers_give_the_same_image(monkeypatch):
    monkeypatch.setattr(RENDER, "_AUTO_WORKERS_OFF", [])
    scene = _speed(size=32, spp=4)
    one = render(scene, seed=7, workers=1, chunk_rays=256)
    two = render(scene, seed=7, workers=2, chunk_rays=256)  # each worker: the Dr.Jit path on one thread
    assert 2 in RENDER._POOL, "workers=2 should start worker processes"
    assert torch.equal(one.image, two.image), "worker processes should give the one-process image"


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_interrupt_one_line_exit_130(tmp_path, sig):
    # A batch is one long Dr.Jit call (2^22 rays); the signal is acted on when it returns.
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    import fuzz_harness

    out = tmp_path / "out.exr"
    out.write_bytes(b"previous")
    rc, lines = fuzz_harness.interrupt_after_progress(
        ["renderer", "render", SPEED, "-o", str(out), "--spp", "256", "--set", "image.width=1024",
         "--set", "image.height=1024"], sig, "render")
    assert rc == 130, f"exit {rc}: {lines[-3:]}"
    assert [ln for ln in lines if ln.startswith("renderer:")] == ["renderer: interrupted"], f"one line: {lines[-3:]}"
    assert out.read_bytes() == b"previous", "the existing output survives an interrupt"


def test_defaults_compile_nothing_with_torch(monkeypatch):
    # The first render of the defaults must not wait for torch.compile (seconds on a new machine).
    def refuse(*args, **kwargs):
        raise AssertionError("torch.compile called by the defaults")

    monkeypatch.setattr(torch, "compile", refuse)
    render(_speed(size=16, spp=2), seed=1)


def test_a_mitsuba_variant_switched_by_another_caller_is_set_back():
    """Mitsuba's variant is process-wide: after another caller switched it (a `--backend mitsuba` render with
    `scalar_rgb`, say), the Dr.Jit path builds its tables, samples and rays with its own variant's types again
    and gives the same image, for a scene seen before and a new one."""
    import mitsuba as mi

    seen, new = _speed(size=8, spp=2), _speed(size=10, spp=2)
    ref_seen = render(seen, seed=3, intersector="mitsuba")
    variant = mi.variant()
    try:
        mi.set_variant("scalar_rgb")
        again = render(seen, seed=3, intersector="mitsuba")
        mi.set_variant("scalar_rgb")
        first_new = render(new, seed=3, intersector="mitsuba")
    finally:
        mi.set_variant(variant)
    assert torch.equal(again.image, ref_seen.image), "the same image after the variant was switched"
    assert torch.equal(first_new.image, render(new, seed=3, intersector="mitsuba").image), "a new scene's kernel too"
