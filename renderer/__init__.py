"""renderer: a batched PyTorch ray tracer for unusual cameras.

Public API:
    load_scene(path_or_dict, overrides) -> Scene     (scene files as in docs/conventions.md)
    render(scene, spp, sampler, device=...) -> RenderResult(image (H, W, 3) linear, coverage (H, W))
    read_image / write_image                          (OpenImageIO; sRGB for 8-bit files)
and the building blocks, one folder per concept: `core/` (rays, transforms, parameters), `cameras/` (every
camera, the lens, optics closed forms, the sensor), `scene/` (scenes, materials, scene files), `shapes/`,
`tracing/` (the render loop, samplers, the integrator), `beam/` (beam tracing of mirror polyhedra), `mitsuba/`
(Mitsuba 3 as a peer and intersector) and `cli/` (the `renderer` command). Files, checks and errors shared with
`tiltfit` are in `camio`. The one camera model for rendering and
fitting is `LensCamera` (renderer/cameras/lens_model.py): `view_camera(v)` gives the `ThinLensCamera` that
renders view v with gradients reaching its parameters; `project_pinhole` is the one pinhole projection and
`axis_angle_to_matrix` / `matrix_to_axis_angle` / `CameraTransform` the one owner of rotations and poses.

Importing it raises glibc's mmap and trim thresholds (`renderer.core.memory`; RENDERER_MALLOPT=0 opts out).
The names above are imported on first use (module `__getattr__`), so `import renderer` and the `renderer`
command's --help and argument errors do not load torch (docs/speed.md, start-up).
"""
import importlib

from renderer.core.memory import tune_allocator

tune_allocator()

#: Public name -> the submodule that owns it (imported when the name is first used).
_EXPORTS = {
    **dict.fromkeys(["Lens", "LensCamera", "Sensor", "ThinLensCamera", "project_pinhole"], "renderer.cameras"),
    **dict.fromkeys(["read_image", "write_image"], "camio.files"),
    **dict.fromkeys(["CheckerTexture", "GridTexture", "ImageTexture", "Material"], "renderer.scene.materials"),
    "SceneError": "renderer.core.params",
    **dict.fromkeys(["Hit", "Rays"], "renderer.core.rays"),
    **dict.fromkeys(["RenderResult", "render"], "renderer.tracing.render"),
    **dict.fromkeys(["ImageSettings", "Light", "Scene", "SceneObject"], "renderer.scene.model"),
    "load_scene": "renderer.scene.file",
    **dict.fromkeys(["CameraTransform", "axis_angle_to_matrix", "matrix_to_axis_angle"], "renderer.core.transforms"),
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    """A public name (`_EXPORTS`) or a submodule (`renderer.cameras`), imported on first use."""
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
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

