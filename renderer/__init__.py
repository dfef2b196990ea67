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
"""
from .memory import tune_allocator

tune_allocator()

from .cameras import Lens, LensCamera, Sensor, ThinLensCamera, project_pinhole
from .io import read_image, write_image
from .materials import CheckerTexture, ImageTexture, Material
from .params import SceneError
from .rays import Hit, Rays
from .render import RenderResult, render
from .scene import ImageSettings, Light, Scene, SceneObject
from .scenefile import load_scene
from .transforms import CameraTransform, axis_angle_to_matrix, matrix_to_axis_angle

__all__ = [
    "CameraTransform", "CheckerTexture", "Hit", "ImageSettings", "ImageTexture", "Lens", "LensCamera", "Light", "Material",
    "Rays", "RenderResult", "Scene", "SceneError", "SceneObject", "Sensor", "ThinLensCamera", "axis_angle_to_matrix",
    "load_scene", "matrix_to_axis_angle", "project_pinhole", "read_image", "render", "write_image",
]
