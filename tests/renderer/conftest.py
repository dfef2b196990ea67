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
