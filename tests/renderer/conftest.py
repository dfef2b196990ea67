import sys

import pytest


@pytest.fixture
def calls(monkeypatch):
    """Counts of the Mitsuba intersector's nearest-hit and shadow calls (so a silent fallback fails)."""
    from renderer.mitsuba import intersect as mi_intersect

    count = {"nearest": 0, "visible": 0}
    for name in count:
        fn = getattr(mi_intersect.MitsubaIntersector, name)

        def counted(self, *args, _fn=fn, _name=name, **kwargs):
            count[_name] += 1
            return _fn(self, *args, **kwargs)

        monkeypatch.setattr(mi_intersect.MitsubaIntersector, name, counted)
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
