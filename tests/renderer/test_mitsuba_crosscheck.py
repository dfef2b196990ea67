"""Our untilted thin lens against Mitsuba 3's `thinlens` sensor (the small version of
benchmarks/renderer/bench_thin_lens.py): the same rays, and the same defocused image to within 1 % of the mean.

Runs on Mitsuba's `scalar_rgb` variant, which needs no LLVM (mitsuba is in the `test` extra; the benchmark
itself uses `llvm_ad_rgb` where it runs). Skipped only where mitsuba is not installed.
"""
import hashlib
import importlib.util
import inspect
import json
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.usefixtures("restore_mitsuba_variant")  # conftest: no variant left behind

mi = pytest.importorskip("mitsuba")


def _bench():
    """benchmarks/renderer/bench_thin_lens.py as a module (benchmarks/ is not a package)."""
    path = Path(__file__).resolve().parents[2] / "benchmarks" / "renderer" / "bench_thin_lens.py"
    spec = importlib.util.spec_from_file_location("bench_thin_lens", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def bench():
    mi.set_variant("scalar_rgb")
    mi.set_log_level(mi.LogLevel.Error)
    return _bench()


def test_rays_match_mitsuba_thinlens(bench):
    """(Vectorised sensor calls: needs a JIT variant; skipped where llvm_ad_rgb cannot run here.)
    Same film position: Mitsuba's rays meet the plane of focus where our chief rays do; its aperture
    sample maps to our lens point rotated by 180° (same disc distribution, different sample map)."""
    from renderer.mitsuba.variants import jit_variant_runs

    if not jit_variant_runs("llvm_ad_rgb"):
        pytest.skip("mitsuba's llvm_ad_rgb variant does not run here (needs LLVM >= 16)")
    mi.set_variant("llvm_ad_rgb")
    r = bench.ray_agreement(33, 21)
    assert r["focus_point_max_err_mm"] < 1e-3, f"focus points differ by {r['focus_point_max_err_mm']} mm"
    assert r["lens_point_max_err_mm"]["rotate_180"] < 1e-4, f"lens points: {r['lens_point_max_err_mm']}"


# Mitsuba's image of the defocused scene (8192 spp on scalar_rgb: the peer's time) kept with the fingerprint of
# what makes it (the sources of the benchmark, which builds Mitsuba's scene and sensor, of the transforms it uses
# and of `_mitsuba_render`; the scene; the samples and seed; Mitsuba's version) and rendered again wherever it
# differs. Ours is rendered in the test. `python tests/renderer/test_mitsuba_crosscheck.py` writes it afresh.
MI_CACHE = Path(__file__).resolve().parent / "mitsuba_defocused_40x27.json"
MI_SPP, SEED = 8192, 5


def _mitsuba_key(bench, cfg):
    import renderer.core.transforms as transforms  # the benchmark turns Mitsuba's shapes with its euler_xyz_deg

    source = Path(bench.__file__).read_bytes() + Path(transforms.__file__).read_bytes()
    source += inspect.getsource(_mitsuba_render).encode()
    return hashlib.sha256(repr((source, cfg, MI_SPP, SEED, mi.__version__, mi.variant())).encode()).hexdigest()


def _mitsuba_render(bench, cfg):
    return bench.mitsuba_high_spp(cfg, bench.mitsuba_scene(cfg), MI_SPP, seed=SEED)


def mitsuba_image(bench, cfg):
    """Mitsuba's image of `cfg` at MI_SPP and SEED, from MI_CACHE where it holds this fingerprint's."""
    try:
        saved = json.loads(MI_CACHE.read_text())
    except (OSError, ValueError):
        saved = {}
    if saved.get("sha256") == _mitsuba_key(bench, cfg):
        return np.array(saved["image"], np.float64)
    return _mitsuba_render(bench, cfg)


def test_defocused_image_matches_mitsuba(bench):
    """Untilted thin lens, blur of several pixels in front of and behind the plane of focus: mean absolute
    difference below 1 % of the mean intensity, and far below what a mirrored image gives."""
    mi.set_variant("scalar_rgb")
    cfg = bench.scene_config(40, 27)
    diff = bench.image_difference(cfg, spp=512, mi_spp=MI_SPP, seed=SEED, mitsuba_image=mitsuba_image(bench, cfg))
    assert diff["as_is"] < 0.01, f"mean |ours - Mitsuba| = {100 * diff['as_is']:.2f} % of the mean (limit 1 %)"
    assert min(diff["flip_x"], diff["flip_y"]) > 10 * diff["as_is"], f"a flipped image should differ far more: {diff}"
    assert np.isfinite(list(diff.values())).all()


if __name__ == "__main__":  # writes MI_CACHE: Mitsuba's image of the defocused scene
    mi.set_variant("scalar_rgb")
    mi.set_log_level(mi.LogLevel.Error)
    module = _bench()
    scene_cfg = module.scene_config(40, 27)
    MI_CACHE.write_text(json.dumps({"sha256": _mitsuba_key(module, scene_cfg),
                                    "image": _mitsuba_render(module, scene_cfg).tolist()}) + "\n")
    print(f"wrote {MI_CACHE}")
