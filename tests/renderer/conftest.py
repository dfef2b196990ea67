import sys

import pytest


@pytest.fixture
def calls(monkeypatch):
    """Counts of the Mitsuba intersector's nearest-hit and shadow queries (so a silent fallback fails): its
    Dr.Jit-level `jit_nearest` and `jit_visible`, which both the torch-facing `nearest` and `visible` and the
    Dr.Jit path (`renderer.tracing.jit_direct`) call."""
    from renderer.mitsuba import intersect as mi_intersect

    count = {"nearest": 0, "visible": 0}
    for name in count:
        fn = getattr(mi_intersect.MitsubaIntersector, "jit_" + name)

        def counted(self, *args, _fn=fn, _name=name, **kwargs):
            count[_name] += 1
            return _fn(self, *args, **kwargs)

        monkeypatch.setattr(mi_intersect.MitsubaIntersector, "jit_" + name, counted)
    return count


@pytest.fixture(scope="module")
def restore_mitsuba_variant():
    """Set Mitsuba's variant back after a module that switches it: as a fresh process would have it (the llvm
    variant where it runs) when none was set before. A variant left behind would turn `intersector="auto"`
    away from Embree in every later test of the same worker process."""
    yield
    mi = sys.modules.get("mitsuba")
    if mi is None:
        return
    from renderer.mitsuba.variants import DEFAULT_VARIANT, load_mitsuba

    if mi.variant() != DEFAULT_VARIANT:
        load_mitsuba(DEFAULT_VARIANT)
