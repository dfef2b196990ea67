"""Mitsuba 3 interop. Mitsuba is optional (`pip install -e '.[test]'` or `'.[bench]'`) and imported on first use.

Modules:
    variants    import Mitsuba and choose a variant that runs here (`load_mitsuba`, the JIT probe)
    export      a scene as a Mitsuba scene dict (`to_mitsuba`) and Mitsuba's render as our image (`develop`)
    shapes      Mitsuba shape dicts of a scene's objects and their BSDFs, our textures mapped onto their uv
    tessellate  our shapes as triangles, and an infinite plane as finite rectangles (`plane_pieces`)
    sensors     our unusual cameras as Mitsuba sensor plugins
    bsdfs       our Phong shading as a BSDF plugin
    intersect   Embree (through Mitsuba) as the ray-shape intersector of our tracer
"""
from .export import develop, to_mitsuba  # noqa: F401
from .variants import load_mitsuba  # noqa: F401
