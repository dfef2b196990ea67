"""Scene-file components from other installed packages, found through entry points.

A package adds cameras and shapes to scene files by naming a function in its metadata under the entry-point
group `renderer.scene.plugins` (pyproject.toml: `[project.entry-points."renderer.scene.plugins"] name = "pkg.mod:register"`).
The function takes no argument and registers its components with `renderer.cameras.register_camera` and
`renderer.shapes.register_shape`. Plugins load once, on the first scene-file type the built-in registries do not
know, so the renderer never imports them by name (tiltfit's `calibrated` camera and `target` shape come this way).
"""
from __future__ import annotations

_loaded = False


def load_plugins() -> bool:
    """Load every `renderer.scene.plugins` entry point once; returns whether any was loaded now."""
    global _loaded
    if _loaded:
        return False
    _loaded = True
    from importlib.metadata import entry_points

    found = False
    for ep in entry_points(group="renderer.scene.plugins"):
        ep.load()()
        found = True
    return found
