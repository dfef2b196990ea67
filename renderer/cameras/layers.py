"""Mixed projections by multi-viewpoint layer composition (paper 000, Osa et al. 2005, section 3, eq. 12–20).

Scene-file `layers` entries (one per object group i):

| key | unit | default | meaning |
|---|---|---|---|
| `objects` | — | required | names of the scene objects drawn in this layer (an object belongs to at most one layer) |
| `alpha` | — | required | α(i), the inverted-perspective parameter of the layer |
| `pseudo_screen_center` | scene | required | c(i), centre of the pseudo-screen Ξ(i), scene frame |
| `move` | scene | [0, 0, 0] | f(i), pseudo-screen move vector, scene frame |
| `scale` | — | 1 | m(i), pseudo-screen magnification |
| `pseudo_viewpoint` | scene | camera position | s(i), the layer's own viewpoint, scene frame |
| `priority` | — | −\\|c(i) − d\\| | higher is drawn on top; by default the layer whose c(i) is nearer the viewpoint d |

Objects in no layer form a default layer seen by the scene camera and drawn first (`renderer.render`). A
layer's first ray sees only its own objects; shadow, reflection and refraction rays see all objects, so
shadows and refractions cross layers. Pixels whose first ray misses the layer's objects keep what lower
layers drew.

Frames. Σ' is the main camera's frame (main viewpoint d at the origin, main screen Π at z = q'3). The layer
frame Σ(i) has its origin at s(i) and e3(i) pointing from s(i) to c(i); e2(i) is the main camera's y axis
(down in the image) made orthogonal to e3(i), and e1(i) = e2(i) × e3(i). So the pseudo-screen's picture is
upright in the main image, and Σ(i) is Σ' moved to s(i) whenever e3(i) is the main view axis. A(i) = [e1 e2 e3]
(columns in Σ') rotates Σ(i) into Σ': x_Σ' = A(i) x_Σ + t(i) with t(i) = s(i) in Σ' (15).

Rays of pixel q' (all in Σ', then moved to the scene frame by the main camera's pose):
    (12) p' = (q'1/q'3, q'2/q'3, 1) · e3ᵀ[c + f]     the main ray's hit on the moved pseudo-screen Ξ'(i)
    (13) r = p' − f − c
    (14) p = A · diag(1/m, 1/m, 1) · r + c          back on the pseudo-screen Ξ(i)
    (16) p_Σ = A⁻¹ (p − t) = (r1/m, r2/m, |c − s|)
    (17) (18) v_Σ = α · diag(1, 1, 0) · p_Σ,  w_Σ = p_Σ − v_Σ   (the pseudo-screen distance is |c − s|)
    (19) (20) v' = A v_Σ + t,  w' = A w_Σ.
For a main camera other than the pinhole, (12) generalises to "where the main camera's ray meets the plane
z' = e3ᵀ[c + f]"; for the pinhole both are the same.

Note on (14): the paper writes A⁻¹ there. Step (14) undoes the rotation about c that turned Ξ(i) parallel to
Π, which takes e1(i), e2(i) onto e1', e2'; applied to the in-plane offset r, written in Σ' coordinates, its
inverse is A (r1 e1(i) + r2 e2(i)), which is what puts p on Ξ(i) for any s(i). Both read the same when
e3(i) is the main view axis (A = I), as in all the paper's experiments.

With α = 0, s = d, f = 0, m = 1 and c on the main view axis, the layer's rays are the main pinhole's rays.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from renderer.core.params import Param, SceneError, parse_params
from renderer.core.rays import Rays, normalize
from renderer.core.transforms import look_at_rotation
from .base import Camera
from .inverted_perspective import inverted_projection, inverted_rays

LAYER_PARAMS = [
    Param("objects", "list", doc="names of the objects drawn in this layer"),
    Param("alpha", "float", doc="α(i), inverted-perspective parameter"),
    Param("pseudo_screen_center", "vec3", doc="c(i), pseudo-screen centre, scene frame"),
    Param("move", "vec3", (0.0, 0.0, 0.0), "f(i), pseudo-screen move vector, scene frame"),
    Param("scale", "float", 1.0, "m(i), pseudo-screen magnification"),
    Param("pseudo_viewpoint", "vec3", None, "s(i), the layer's viewpoint, scene frame [camera position]"),
    Param("priority", "float", None, "higher is drawn on top [minus the distance from the viewpoint to c(i)]"),
]

# Below this sine of the angle between e3(i) and the main camera's y axis, e1(i) and e2(i) are undefined.
_MIN_SIN_TO_MAIN_Y = 1e-9


class LayerCamera(Camera):
    """The rays of one layer: main screen pixel -> pseudo-screen -> inverted-perspective ray from s(i).

    Shares the main camera's pose (Σ' to the scene frame) and screen, so a layer's image lies on the main
    image pixel for pixel.

    Attributes (float64 tensors in Σ', the main camera frame):
        main: the main camera.
        center_main: c(i) (3,); move_main: f(i) (3,); viewpoint_main: s(i) = t(i) (3,).
        main_from_layer: A(i) (3, 3), columns e1(i), e2(i), e3(i).
        alpha: α(i); scale: m(i); pseudo_screen_distance: |c(i) − s(i)|, scene units.
    """

    def __init__(self, main: Camera, pseudo_screen_center, alpha: float, move=(0.0, 0.0, 0.0), scale: float = 1.0,
                 pseudo_viewpoint=None):
        """Args are in the scene frame, scene units; `pseudo_viewpoint` defaults to the main viewpoint.

        Raises:
            ValueError whose message starts with the offending parameter's name.
        """
        super().__init__(main.transform, main.screen)
        self.main = main
        self.uses_lens_samples = main.uses_lens_samples
        if not scale > 0:
            raise ValueError(f"scale: expected a positive number, got {scale}")
        pose = main.transform
        c_world = torch.as_tensor(pseudo_screen_center, dtype=torch.float64)
        s_world = pose.position if pseudo_viewpoint is None else torch.as_tensor(pseudo_viewpoint, dtype=torch.float64)
        self.center_main = pose.points_to_camera(c_world)
        self.viewpoint_main = pose.points_to_camera(s_world)
        self.move_main = torch.as_tensor(move, dtype=torch.float64) @ pose.world_from_camera
        self.alpha, self.scale = float(alpha), float(scale)
        self.pseudo_screen_distance = float(torch.linalg.vector_norm(self.center_main - self.viewpoint_main))
        if not self.pseudo_screen_distance > 0:
            raise ValueError("pseudo_screen_center: must differ from the pseudo-viewpoint "
                             f"{tuple(s_world.tolist())}")
        e3 = (self.center_main - self.viewpoint_main) / self.pseudo_screen_distance
        if math.sqrt(max(0.0, 1.0 - float(e3[1]) ** 2)) < _MIN_SIN_TO_MAIN_Y:
            raise ValueError("pseudo_screen_center: the pseudo-viewpoint looks along the camera's up direction, "
                             "so the pseudo-screen's axes are undefined")
        self.main_from_layer = look_at_rotation(self.viewpoint_main, self.center_main, (0.0, -1.0, 0.0))
        depth = float((self.center_main + self.move_main)[2])
        if not depth > 0:
            raise ValueError(f"move: the moved pseudo-screen centre c + f must lie in front of the camera "
                             f"(depth along the view axis > 0), got depth {depth}")
        self.moved_depth = depth

    def _tensors(self, like: torch.Tensor):
        def cast(t):
            return t.to(device=like.device, dtype=like.dtype)

        return cast(self.center_main), cast(self.move_main), cast(self.viewpoint_main), cast(self.main_from_layer)

    def rays_in_camera(self, uv_px: torch.Tensor, lens_uv: torch.Tensor) -> Rays:
        """Rays in Σ' for pixels (..., 2) and lens samples (..., 2), eq. (12)–(20)."""
        main = self.main.rays_in_camera(uv_px, lens_uv)
        c, f, t, A = self._tensors(main.origin)
        o, u = main.origin, main.direction
        ahead = u[..., 2] > 0
        u_z = torch.where(ahead, u[..., 2], torch.ones_like(u[..., 2]))
        p_moved = o + u * ((self.moved_depth - o[..., 2]) / u_z)[..., None]  # (12)
        r = p_moved - f - c  # (13)
        p3 = torch.full_like(r[..., 0], self.pseudo_screen_distance)
        p_layer = torch.stack([r[..., 0] / self.scale, r[..., 1] / self.scale, p3], -1)  # (14), (16)
        v_layer, w_layer = inverted_rays(p_layer, self.alpha)  # (17), (18)
        origin = v_layer @ A.transpose(-1, -2) + t  # (19)
        direction = normalize(w_layer @ A.transpose(-1, -2))  # (20)
        return Rays(origin, direction, main.valid & ahead, main.weight)

    def project(self, p_world: torch.Tensor) -> torch.Tensor:
        """(..., 3) scene points -> (..., 2) main-image pixels; +inf where the point has no image.

        The point goes into Σ(i), onto the pseudo-screen by (4), (5) with α(i) and p3 = |c − s|, is scaled by m
        and moved by f onto Ξ'(i) (inverse of (13), (14)), and is projected by the main camera.
        """
        c, f, t, A = self._tensors(p_world)
        pose = self.main.transform
        a_layer = (pose.points_to_camera(p_world) - t) @ A
        x, has_image = inverted_projection(a_layer, self.alpha, self.pseudo_screen_distance)
        r = torch.cat([x * self.scale, torch.zeros_like(x[..., :1])], -1)
        p_moved_main = r + f + c
        p_moved_world = p_moved_main @ pose.world_from_camera.to(p_world).transpose(-1, -2) + pose.position.to(p_world)
        uv_px = self.main.project(p_moved_world)
        return torch.where(has_image[..., None], uv_px, torch.full_like(uv_px, float("inf")))


@dataclass(frozen=True)
class Layer:
    """One layer of the composition.

    Attributes:
        camera: the layer's rays (a LayerCamera on the main camera's screen).
        object_ids: indices into the scene's objects seen by the layer's first rays.
        priority: higher is drawn later, on top.
    """

    camera: Camera
    object_ids: frozenset[int]
    priority: float


def _object_ids(path: str, names, scene_object_names: list[str], owner: dict[str, int], i: int) -> frozenset[int]:
    if not names:
        raise SceneError(f"{path}: expected a non-empty list of object names, got {names!r}")
    index = {n: k for k, n in enumerate(scene_object_names)}
    ids = set()
    for name in names:
        if not isinstance(name, str):
            raise SceneError(f"{path}: expected object names (strings), got {name!r}")
        if name not in index:
            raise SceneError(f"{path}: unknown object {name!r} (expected one of: {', '.join(scene_object_names)})")
        if name in owner:
            where = "this layer" if owner[name] == i else f"layers[{owner[name]}]"
            raise SceneError(f"{path}: object {name!r} is already in {where}; an object belongs to one layer")
        owner[name] = i
        ids.add(index[name])
    return frozenset(ids)


def build_layers(path: str, cfgs, scene_object_names: list[str], main_camera: Camera,
                 main_cfg: dict | None = None) -> list[Layer]:
    """Validate the scene file's `layers` list and build one Layer per entry.

    Args:
        path: where the list sits in the file ("layers"), used in messages.
        cfgs: the list of layer dicts (see the table at the top of this module).
        scene_object_names: the scene's object names in scene order (their indices are the object ids).
        main_camera: the scene camera; its pose is the main viewpoint d and Σ', its screen the main screen.
        main_cfg: the scene's `camera` section; accepted for the loader's convenience, not needed (the
            default pseudo-viewpoint, the camera position, is read from `main_camera`).
    Returns:
        Layers in file order (the renderer sorts them by priority).
    Raises:
        SceneError naming the field, e.g. "layers[1].objects: unknown object 'cube' ...".
    """
    if not isinstance(cfgs, list):
        raise SceneError(f"{path}: expected a list of layers, got {cfgs!r}")
    owner: dict[str, int] = {}
    layers = []
    d_world = main_camera.transform.position
    for i, cfg in enumerate(cfgs):
        where = f"{path}[{i}]"
        parsed = parse_params(where, cfg, LAYER_PARAMS)
        ids = _object_ids(f"{where}.objects", parsed["objects"], scene_object_names, owner, i)
        try:
            camera = LayerCamera(main_camera, parsed["pseudo_screen_center"], parsed["alpha"], parsed["move"],
                                 parsed["scale"], parsed["pseudo_viewpoint"])
        except ValueError as e:
            raise SceneError(f"{where}.{e}") from None
        priority = parsed["priority"]
        if priority is None:
            c_world = torch.tensor(parsed["pseudo_screen_center"], dtype=torch.float64)
            priority = -float(torch.linalg.vector_norm(c_world - d_world))
        layers.append(Layer(camera, ids, priority))
    return layers
