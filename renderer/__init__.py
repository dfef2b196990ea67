"""renderer: a batched PyTorch ray tracer for unusual cameras.

Public API:
    load_scene(path_or_dict, overrides) -> Scene     (scene files as in docs/conventions.md)
    render(scene, spp, sampler, device=...) -> RenderResult(image (H, W, 3) linear, coverage (H, W))
    read_image / write_image                          (OpenImageIO; sRGB for 8-bit files)
and the building blocks: cameras, shapes, materials, Scene, trace. The one camera model for rendering and
fitting is `LensCamera` (renderer/cameras/lens_model.py): `view_camera(v)` gives the `ThinLensCamera` that
renders view v with gradients reaching its parameters; `project_pinhole` is the one pinhole projection and
`axis_angle_to_matrix` / `matrix_to_axis_angle` / `CameraTransform` the one owner of rotations and poses.

Importing it raises glibc's mmap and trim thresholds (`renderer.memory`; RENDERER_MALLOPT=0 opts out).
The names above are imported on first use (module `__getattr__`), so `import renderer` and the `renderer`
command's --help and argument errors do not load torch (docs/speed.md, start-up).
"""
import importlib
import sys
import types

from .memory import tune_allocator

tune_allocator()

#: Public name -> the submodule that owns it (imported when the name is first used).
_EXPORTS = {
    "Lens": "cameras", "LensCamera": "cameras", "Sensor": "cameras", "ThinLensCamera": "cameras",
    "project_pinhole": "cameras",
    "read_image": "io", "write_image": "io",
    "CheckerTexture": "materials", "GridTexture": "materials", "ImageTexture": "materials", "Material": "materials",
    "SceneError": "params",
    "Hit": "rays", "Rays": "rays",
    "RenderResult": "render", "render": "render",
    "ImageSettings": "scene", "Light": "scene", "Scene": "scene", "SceneObject": "scene",
    "load_scene": "scenefile",
    "CameraTransform": "transforms", "axis_angle_to_matrix": "transforms", "matrix_to_axis_angle": "transforms",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    """A public name (`_EXPORTS`) or a submodule (`renderer.cameras`), imported on first use."""
    if name in _EXPORTS:
        value = getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
        globals()[name] = value
        return value
    try:
        return importlib.import_module(f".{name}", __name__)
    except ModuleNotFoundError as e:
        if e.name != f"{__name__}.{name}":
            raise
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(__all__))


class _Package(types.ModuleType):
    """`renderer.render` is the function, as when the package imported it eagerly: importing the submodule
    `renderer.render` (which binds the submodule on the package) leaves the function there."""

    def __setattr__(self, name: str, value) -> None:
        if isinstance(value, types.ModuleType) and _EXPORTS.get(name) == name:
            value = getattr(value, name)
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package
