"""Improved beam tracing (Koyama & Okada; method and steps in docs/beam_tracing.md): recursive screen segmentation of
scenes of mirror and diffuse polyhedra, reused as the viewpoint moves along the view direction.

    tracer = BeamTracer(scene)              # step (1): polygons, once
    frame = tracer.frame(camera)            # steps (2)-(4): regions, reusing the previous frame's nodes
    image = tracer.render(frame)            # shade every region along its beam

Modules: `polygons` (CSG to polygons), `segment` (recursive segmentation and its reuse), `shade`
(rendering from regions, shadows from light beams). Only pinhole cameras; objects must be `polyhedron` or
`csg` shapes with opaque materials (`reflect` makes a mirror).
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from renderer.core.params import SceneError
from .polygons import Face, scene_faces
from .segment import Region, ScreenCamera, Segmenter, Timing
from .shade import label_pixels, lit_regions, render_regions

__all__ = ["BeamTracer", "Frame", "Face", "Region", "ScreenCamera"]


@dataclass
class Frame:
    """One segmented frame.

    Attributes:
        camera: the ScreenCamera. regions: the screen regions.
        seconds: segmentation time (steps (1)-(3); step (1) only in the tracer's first frame).
        polygon_seconds, determine_seconds, project_seconds: its parts.
        redetermined: whether the eye crossed the infinite plane of a real polygon since the last frame, so
            that step (2) was redone (for the nodes with a candidate plane crossed, the root among them;
            always True for a first frame or without reuse).
        crossed: face ids of those planes.
    """

    camera: ScreenCamera
    regions: list[Region]
    seconds: float
    polygon_seconds: float
    determine_seconds: float
    project_seconds: float
    redetermined: bool
    crossed: list[int]
    timing: Timing


class BeamTracer:
    """Segments and renders one scene for a sequence of camera positions (see the module docstring).

    Args:
        scene: a `renderer.scene.model.Scene` with a pinhole camera, polyhedron/csg objects.
        reuse: keep step (2) between frames (False: every frame from scratch, for comparison).
    """

    def __init__(self, scene, reuse: bool = True):
        ScreenCamera.of(scene.camera)  # refuses cameras the segmentation cannot model, with the field named
        if scene.layers:
            raise SceneError("layers: beam tracing renders one perspective view; remove the layers")
        self.scene = scene
        self.reuse = reuse
        t0 = time.perf_counter()
        self.faces: list[Face] = scene_faces(scene)
        self.polygon_seconds = time.perf_counter() - t0
        self.materials = [scene.objects[f.object_id].material for f in self.faces]
        self.reflect = np.array([m.reflect for m in self.materials])
        self.segmenter = Segmenter(self.faces, self.reflect, scene.image.max_depth, scene.extent)
        self._lit = None
        self._last: ScreenCamera | None = None
        self._first = True

    def frame(self, camera=None) -> Frame:
        """Segment the screen for `camera` (a renderer camera or a ScreenCamera) [the scene's camera]."""
        cam = camera if isinstance(camera, ScreenCamera) else ScreenCamera.of(camera or self.scene.camera)
        start = time.perf_counter()
        crossed = []
        if not self.reuse or self._last is None:
            self.segmenter.nodes.clear()
        else:
            # Every node re-determines itself when the eye crossed one of its own candidate planes (the root's
            # candidates are the real polygons); `crossed` names the real planes for the report.
            crossed = self.segmenter.crossed(self._last.eye, cam.eye).tolist()
        regions = self.segmenter.segment(cam)
        seconds = time.perf_counter() - start
        polygon = self.polygon_seconds if self._first or not self.reuse else 0.0
        self._first = False
        t = self.segmenter.timing
        redetermined = self._last is None or not self.reuse or bool(crossed)
        self._last = cam
        return Frame(cam, regions, seconds + polygon, polygon, t.determine, t.project, redetermined, crossed, t)

    @property
    def lit(self):
        """Lit polygons per face and light (computed on first use; they do not depend on the viewpoint)."""
        if self._lit is None:
            self._lit = lit_regions(self.faces, self.scene.lights)
        return self._lit

    def render(self, frame: Frame) -> np.ndarray:
        """(H, W, 3) float64 linear RGB image of a segmented frame, one sample at each pixel centre."""
        cam = frame.camera
        labels = label_pixels(frame.regions, cam.width, cam.height)
        return render_regions(frame.regions, labels, cam, self.faces, self.materials, self.scene.lights, self.lit,
                              self.scene.image.background, self.scene.ray_epsilon)
