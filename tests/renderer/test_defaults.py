"""What `render(scene)` picks without flags: `intersector="auto"` and `workers=None` (issue 11).

- auto takes Embree (Mitsuba 3's llvm variant) for float32 CPU renders where it loads, and our own tracer
  otherwise, silently: Mitsuba missing or its llvm variant not running (loader monkeypatched here), float64,
  a scene tensor that needs gradients, another Mitsuba variant chosen by someone else; the fallback image is
  ours bit for bit.
- workers=None starts worker processes only for float32 CPU renders of >= AUTO_WORKERS_MIN_RAYS rays without
  gradients, and not from a script's top level outside `if __name__ == "__main__":`; where workers fail to
  start anyway, one warning and the image from this process (subprocess test).
"""
from __future__ import annotations

import os
import subprocess
import sys

import pytest
import torch

from renderer import render
from renderer.mitsuba import intersect as mi_intersect
from renderer.scene.file import load_scene

RENDER = sys.modules["renderer.tracing.render"]
ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
CFG = {
    "image": {"width": 24, "height": 16, "spp": 2, "max_depth": 1},
    "camera": {"type": "thin_lens", "position": [0, 0, -5], "look_at": [0, 0, 0], "w": 1, "U": 5, "d": 0.2,
               "sensor_size": [0.8, 0.6], "theta_F_deg": 5},
    "lights": [{"type": "point", "position": [2, -3, -4], "intensity": [20, 20, 20]}],
    "objects": [
        {"name": "ball", "shape": {"type": "sphere", "center": [0, 0, 0], "radius": 1},
         "material": {"color": [0.8, 0.3, 0.2]}},
        {"name": "cube", "shape": {"type": "box", "center": [1.5, 0.5, 0.5], "size": [1, 1, 1]},
         "material": {"color": [0.2, 0.6, 0.3]}},
        {"name": "floor", "shape": {"type": "plane", "point": [0, 1, 0], "normal": [0, -1, 0]},
         "material": {"color": [0.5, 0.5, 0.5]}},
    ],
}


def _llvm_runs() -> bool:
    try:
        from renderer.mitsuba.variants import jit_variant_runs

        return jit_variant_runs("llvm_ad_rgb")
    except ImportError:
        return False


needs_llvm = pytest.mark.skipif(not _llvm_runs(), reason="mitsuba's llvm_ad_rgb variant does not run here")


def fresh_process_variant(monkeypatch):
    """Make an already imported Mitsuba look as in a fresh process (no variant set), so `auto` probes instead of
    leaving another test's variant alone; the real variant stays as it was."""
    mi = sys.modules.get("mitsuba")
    if mi is None:
        return
    monkeypatch.setattr(mi, "variant", lambda: None)
    monkeypatch.setattr(mi, "set_variant", lambda v: None)  # the probe's scalar fallback must not stick


def test_hiding_the_jit_variants_makes_auto_use_our_tracer(monkeypatch):
    """RENDERER_HIDE_MITSUBA_JIT (how CI runs the suite a second time, as on a machine without libLLVM >= 16)
    hides the llvm variant from the probe, so auto traces with our own code; unset, the probe answers again."""
    from renderer.mitsuba import variants

    pytest.importorskip("mitsuba")  # imported before fresh_process_variant, so the probe cannot set a variant
    monkeypatch.setattr(variants, "_LLVM_RUNS", {})
    monkeypatch.setenv(variants.HIDE_JIT_ENV, "1")
    assert not variants.jit_variant_runs("llvm_ad_rgb"), "a hidden llvm variant should not run"
    assert variants.jit_variant_runs("scalar_rgb"), "scalar variants are never hidden"
    monkeypatch.setattr(mi_intersect, "_LLVM", [])
    fresh_process_variant(monkeypatch)
    scene = load_scene(CFG)
    assert mi_intersect.auto_engine(scene, "cpu", torch.float32) is None, "auto should not take Embree when hidden"
    assert mi_intersect._LLVM == [False], f"the probe should say no: {mi_intersect._LLVM}"
    monkeypatch.setenv(variants.HIDE_JIT_ENV, "0")
    assert not variants.jit_hidden(), "0 should mean not hidden"


@pytest.mark.parametrize("failure", ["not installed", "scalar only"])
def test_auto_falls_back_to_our_tracer_where_mitsuba_does_not_load(monkeypatch, failure):
    def missing(variant):
        raise ImportError("mitsuba is not installed")

    class ScalarOnly:  # what load_mitsuba returns where the llvm variant cannot run
        @staticmethod
        def variant():
            return "scalar_rgb"

    monkeypatch.setattr(mi_intersect, "load_mitsuba", missing if failure == "not installed" else lambda v: ScalarOnly)
    monkeypatch.setattr(mi_intersect, "_LLVM", [])  # probe again, through the broken loader
    fresh_process_variant(monkeypatch)
    scene = load_scene(CFG)
    auto = render(scene, seed=2).image
    ours = render(scene, seed=2, intersector="torch").image
    assert mi_intersect._LLVM == [False], f"{failure}: the probe should say no, got {mi_intersect._LLVM}"
    assert torch.equal(auto, ours), f"{failure}: auto should give our own image bit for bit"
    assert float(ours.mean()) > 0.01, "the image should not be black"


@needs_llvm
def test_auto_takes_embree_for_float32_and_ours_otherwise(calls):
    scene = load_scene(CFG)
    auto = render(scene, seed=1).image
    assert calls["nearest"] > 0 and calls["visible"] > 0, f"float32 on the CPU should go to Embree: {calls}"
    explicit = render(scene, seed=1, intersector="mitsuba").image
    assert torch.equal(auto, explicit), "auto should be intersector='mitsuba' here"
    ours = render(scene, seed=1, intersector="torch").image
    off = float(((auto - ours).abs().amax(-1) > 1e-3).double().mean())
    assert off < 0.01, f"{100 * off:.2f} % of pixels differ by > 1e-3 between Embree and ours (limit 1 %)"
    before = dict(calls)
    f64 = render(scene, seed=1, dtype=torch.float64).image
    assert calls == before, f"float64 should stay with our tracer: {before} -> {calls}"
    assert torch.equal(f64, render(scene, seed=1, dtype=torch.float64, intersector="torch").image), "float64 changed"
    scene.objects[0].shape.radius = torch.tensor(1.0, requires_grad=True)
    assert scene.requires_grad(), "a shape parameter that requires grad should be seen"
    render(scene, seed=1)
    assert calls == before, f"a scene that needs gradients should stay with our tracer: {before} -> {calls}"


@needs_llvm
def test_auto_leaves_someone_elses_mitsuba_variant_alone(calls):
    import mitsuba as mi

    previous = mi.variant()
    mi.set_variant("scalar_rgb")
    try:
        scene = load_scene(CFG)
        image = render(scene, seed=3).image
        assert mi.variant() == "scalar_rgb", f"render switched Mitsuba's variant to {mi.variant()}"
        assert calls["nearest"] == 0, f"with another variant set, auto should use our tracer: {calls}"
        assert torch.equal(image, render(scene, seed=3, intersector="torch").image), "expected our own image"
    finally:
        if previous is not None:
            mi.set_variant(previous)


@needs_llvm
def test_renders_follow_a_moved_shape():
    """What is cached from a scene's shapes (the Embree scene, the direct path's normal tables, the culling
    spheres and extent, each shape's converted parameters) follows a shape replaced (how one moves it) or
    edited in place: both tracers then render what a scene built with the shape there renders."""
    import copy

    from renderer.shapes.base import geometry_key
    from renderer.shapes.sphere import Sphere

    cfg = {**CFG, "image": {**CFG["image"], "width": 96, "height": 64}}  # packets big enough to be culled
    moved_cfg = {**cfg, "objects": [{**cfg["objects"][0], "shape": {"type": "sphere", "center": [-1.5, -0.6, 0.5],
                                                                       "radius": 0.5}}, *cfg["objects"][1:]]}
    fresh = {i: render(load_scene(moved_cfg), seed=4, intersector=i).image for i in ("torch", "mitsuba")}
    scene = load_scene(cfg)
    before = {i: render(scene, seed=4, intersector=i).image for i in ("torch", "mitsuba")}
    scene.objects[0] = copy.copy(scene.objects[0])
    scene.objects[0].shape = Sphere([-1.5, -0.6, 0.5], 0.5)
    for i in ("torch", "mitsuba"):
        moved = render(scene, seed=4, intersector=i).image
        assert (moved - before[i]).abs().max() > 0.05, f"{i}: moving the ball should change the image"
        assert torch.equal(moved, fresh[i]), \
            f"{i}: the replaced ball, {float((moved - fresh[i]).abs().max()):.3g} off the scene built with it there"
    # Moved by editing its tensors in place (radius too, through a shape that keeps it as a number: replaced).
    edited = load_scene(cfg)
    for i in ("torch", "mitsuba"):
        render(edited, seed=4, intersector=i)
    key = geometry_key(edited)
    edited.objects[0].shape.center.copy_(torch.tensor([-1.5, -0.6, 0.5], dtype=torch.float64))
    assert geometry_key(edited) != key, "an in-place edit should change the geometry key"
    edited.objects[0].shape.radius = 0.5
    for i in ("torch", "mitsuba"):
        got = render(edited, seed=4, intersector=i).image
        assert torch.equal(got, fresh[i]), f"{i}: the ball edited in place, {float((got - fresh[i]).abs().max()):.3g} off"


def test_scene_derived_data_follows_the_geometry_and_stays_out_of_pickles():
    """`Scene.derived` (the one cache of what is built from a scene's objects: material tables, the Embree
    scene, the fast paths' tables) keeps a value until `refresh` sees an object change; a pickled scene
    (what worker processes get) carries none of it, a shallow copy (same objects) shares it."""
    import copy
    import pickle

    from renderer.shapes.sphere import Sphere

    scene = load_scene(CFG)
    built = []
    first = scene.derived("test", lambda: built.append(1) or object())
    assert scene.derived("test", lambda: built.append(1) or object()) is first and built == [1], "kept while unchanged"
    scene.refresh()
    assert scene.derived("test", lambda: built.append(1) or object()) is first, "refresh without a change keeps it"
    table = scene.materials(torch.zeros(1))
    unpickled = pickle.loads(pickle.dumps(scene))
    assert unpickled._derived == {}, f"a pickled scene should carry no derived data: {sorted(unpickled._derived)}"
    assert torch.equal(unpickled.materials(torch.zeros(1)).color, table.color), "it rebuilds its material table"
    shallow = copy.copy(scene)  # shares the objects (render_accumulation's passes): shares what is derived
    assert shallow.materials(torch.zeros(1)) is table, "a shallow copy should share the material tables"
    scene.objects[0].shape = Sphere([0.5, 0.0, 0.0], 1.0)
    scene.refresh()
    again = scene.derived("test", lambda: built.append(1) or object())
    assert again is not first and built == [1, 1], "a replaced shape should rebuild what was derived"
    assert scene.materials(torch.zeros(1)) is not table, "and the material tables with it"
    shallow.refresh()  # its object list is the scene's: it sees the new ball too
    assert shallow.materials(torch.zeros(1)) is not table, "the shallow copy should rebuild after its refresh"


def test_auto_workers_only_for_large_float32_cpu_renders(monkeypatch):
    monkeypatch.setattr(RENDER, "_cores", lambda: 2)
    monkeypatch.setattr(RENDER, "_AUTO_WORKERS_OFF", [])
    scene = load_scene(CFG)
    big = RENDER.AUTO_WORKERS_MIN_RAYS
    pick = RENDER.auto_workers
    assert pick(scene, big, "cpu", torch.float32) == 2, "a large float32 CPU render should use both cores"
    assert pick(scene, big - 1, "cpu", torch.float32) == 1, "a small render should stay in this process"
    assert pick(scene, big, "cpu", torch.float64) == 1, "float64 renders should stay in this process"
    assert pick(scene, big, "cuda", torch.float32) == 1, "GPU renders have no CPU workers"
    monkeypatch.setattr(RENDER, "_AUTO_WORKERS_OFF", ["broken"])
    assert pick(scene, big, "cpu", torch.float32) == 1, "after a failed start, no more workers"
    monkeypatch.setattr(RENDER, "_AUTO_WORKERS_OFF", [])
    scene.objects[0].shape.radius = torch.tensor(1.0, requires_grad=True)
    assert pick(scene, big, "cpu", torch.float32) == 1, "workers return no graph: gradients stay here"


@pytest.mark.slow
def test_auto_workers_give_the_one_process_image(monkeypatch):
    monkeypatch.setattr(RENDER, "_cores", lambda: 2)
    monkeypatch.setattr(RENDER, "_AUTO_WORKERS_OFF", [])
    monkeypatch.setattr(RENDER, "AUTO_WORKERS_MIN_RAYS", 1)
    scene = load_scene(CFG)
    # Our own tracer: Embree renders of this scene take the Dr.Jit path, which uses no worker processes.
    reference = render(scene, seed=6, workers=1, chunk_rays=64, intersector="torch")
    result = render(scene, seed=6, chunk_rays=64, intersector="torch")
    assert 2 in RENDER._POOL, f"workers=None on 2 cores should start two worker processes: {list(RENDER._POOL)}"
    assert torch.equal(result.image, reference.image), "workers=None should give the one-process image"
    assert torch.equal(result.coverage, reference.coverage), "coverage changed with workers"


UNGUARDED = """
import sys, warnings
import torch
import renderer.tracing.render  # noqa: F401
from renderer.scene.file import load_scene
render_module = sys.modules["renderer.tracing.render"]
render_module.AUTO_WORKERS_MIN_RAYS = 1  # every render would start workers,
render_module._cores = lambda: 2  # two of them, on any machine
scene = load_scene({cfg!r})
ours = dict(intersector="torch")  # Embree renders of this scene take the Dr.Jit path, without worker processes
alone = render_module.render(scene, seed=4, workers=1, **ours).image
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    image = render_module.render(scene, seed=4, **ours).image  # the script's top level: no workers
    print("TOP", len(caught), len(render_module._POOL), torch.equal(image, alone))
    render_module._spawn_safe = lambda: True  # as if called later, from a thread: workers start, then fail
    image = render_module.render(scene, seed=4, **ours).image
    print("FORCED", sum("failed to start" in str(w.message) for w in caught), bool(render_module._AUTO_WORKERS_OFF),
          torch.equal(image, alone))
"""


def _run(tmp_path, text):
    script = tmp_path / "script.py"
    script.write_text(text)
    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""), OMP_NUM_THREADS="1")
    return subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300, env=env)


def test_spawn_safe_reads_the_main_guard(tmp_path):
    lines = RENDER._main_guards(__file__)
    assert lines == [], f"this test file has no main guard, found {lines}"
    script = tmp_path / "guarded.py"
    script.write_text("import os\nx = 1\nif __name__ == '__main__':\n    y = 2\n    z = 3\nw = 4\n")
    assert RENDER._main_guards(str(script)) == [(3, 5)], "the guard spans lines 3-5"


EDITED = """
import os, sys
import renderer.tracing.render  # noqa: F401
render_module = sys.modules["renderer.tracing.render"]


def safe():
    return render_module._spawn_safe()


if __name__ == "__main__":
    before = safe()
    with open(__file__) as f:
        text = f.read()
    with open(__file__, "w") as f:  # the script edited while it runs: its guard moves 40 lines down
        f.write("\\n" * 40 + text)
    os.utime(__file__, (0, 10**9))
    print("SAFE", before, safe())
"""


def test_spawn_safe_keeps_its_answer_when_the_script_is_edited(tmp_path):
    out = _run(tmp_path, EDITED)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "SAFE True True" in out.stdout, f"a render under the guard should stay spawn-safe after an edit: {out.stdout}"


@pytest.mark.slow
def test_an_unguarded_script_renders_in_its_own_process(tmp_path):
    """spawn runs the main script again in each worker: from a script's unguarded top level, workers=None
    stays in the process; where workers start anyway, render stops their reruns at their first render and
    the script's render traces in its process after one warning."""
    out = _run(tmp_path, UNGUARDED.format(cfg=CFG))
    assert out.returncode == 0, f"exit {out.returncode}: {out.stderr[-2000:]}"
    lines = [line for line in out.stdout.splitlines() if line.startswith(("TOP", "FORCED"))]
    assert lines == ["TOP 0 0 True", "FORCED 1 True True"], (
        f"expected no workers and no warning at the top level, then one warning and the same image: {lines}")
    assert "guard the script's work with" in out.stderr, "the workers' error should say how to fix the script"
