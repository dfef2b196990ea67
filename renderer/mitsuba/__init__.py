"""Mitsuba 3 interop: export a scene to a Mitsuba scene dict (`export`), and our unusual cameras as Mitsuba
sensor plugins (`sensors`). Mitsuba is optional (`pip install -e '.[test]'` or `'.[bench]'`) and imported
on first use.
"""
from .export import develop, load_mitsuba, to_mitsuba  # noqa: F401
