"""Mitsuba 3 interop: export a scene to a Mitsuba scene dict and develop Mitsuba's render into our image
(`export`), our unusual cameras as Mitsuba sensor plugins (`sensors`) and our Phong shading as a BSDF plugin
(`bsdfs`). Mitsuba is optional (`pip install -e '.[test]'` or `'.[bench]'`) and imported on first use.
"""
from .export import develop, load_mitsuba, to_mitsuba  # noqa: F401
