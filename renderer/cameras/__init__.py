"""Cameras, registered by name and built from plain dicts (the scene file's `camera` section).

Each camera module declares its parameters (`PARAMS`, a list of `renderer.core.params.Param`) and a builder
`from_config(cfg, transform, width, height) -> Camera`, and registers them with `register_camera`.
`build_camera(path, cfg, width, height)` validates a dict and builds the camera it names (both in
`registry`, which the camera modules import: they never import this package).

Public API (what `tiltfit` and users import from here): the camera classes, `LensCamera` (the one fitted and
rendered camera model: pose, lens, distortion and sensor as a torch module over V views; `lens_model`), its
stored lens vector decoded in one place (`lens_values`, `stored_from_lens`, `stored_lens_sigma`; `lens_vector`),
`project_pinhole` and its inverse (the one pinhole projection; `projection`), OpenCV's tilted model's angles
(`opencv_tilt`, `lens_tilt_from_opencv`, `tilt_rotation`: the frame of a distortion about a tilted lens's axis),
`concentric_disk` (lens samples
to the aperture disc) and the registry (`CAMERAS`, `build_camera`).
"""
from __future__ import annotations

from .base import Camera, Screen, screen_from_config  # noqa: F401  (re-exported)
from .registry import CAMERAS, POSE_PARAMS, SCREEN_PARAMS, build_camera, register_camera  # noqa: F401

# Registration happens on import of each camera module.
from renderer.cameras import pinhole  # noqa: F401
from renderer.cameras import orthographic  # noqa: F401
from renderer.cameras import inverted_perspective  # noqa: F401
from renderer.cameras import thin_lens  # noqa: F401
from renderer.cameras import accumulation  # noqa: F401

from .lens import (DISTORTION_CENTRES, EOS_6D, Lens, Sensor, lens_tilt_from_opencv, opencv_tilt,  # noqa: F401
                   tilt_rotation)
from .lens_model import LensCamera, distortion_parameter_names  # noqa: F401
from .lens_vector import (APERTURE_SCALE_MM, LENS_PARAMETERS, U_from_stored, d_from_stored, lens_values,  # noqa: F401
                          stored_from_lens, stored_lens_sigma, w_from_stored)
from .projection import (camera_matrix, image_centre_px, normalised_from_pixels, pixels_from_normalised,  # noqa: F401
                         project_pinhole)
from .thin_lens import ThinLensCamera, concentric_disk  # noqa: F401
