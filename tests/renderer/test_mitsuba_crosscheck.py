"""Our untilted thin lens against Mitsuba 3's `thinlens` sensor (the small version of
benchmarks/renderer/bench_thin_lens.py): the same rays, and the same defocused image to within 1 % of the mean.

Runs on Mitsuba's `scalar_rgb` variant, which needs no LLVM (mitsuba is in the `test` extra; the benchmark
itself uses `llvm_ad_rgb` where it runs). Skipped only where mitsuba is not installed.
"""
import importlib.util
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


def test_defocused_image_matches_mitsuba(bench):
    """Untilted thin lens, blur of several pixels in front of and behind the plane of focus: mean absolute
    difference below 1 % of the mean intensity, and far below what a mirrored image gives."""
    mi.set_variant("scalar_rgb")
    cfg = bench.scene_config(40, 27)
    diff = bench.image_difference(cfg, spp=512, mi_spp=8192)
    assert diff["as_is"] < 0.01, f"mean |ours - Mitsuba| = {100 * diff['as_is']:.2f} % of the mean (limit 1 %)"
    assert min(diff["flip_x"], diff["flip_y"]) > 10 * diff["as_is"], f"a flipped image should differ far more: {diff}"
    assert np.isfinite(list(diff.values())).all()
