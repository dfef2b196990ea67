"""Multi-viewpoint layer composition (paper 000, section 3): geometry of the layer rays, the paper's Fig. 8/9
configuration rendered, and validation of the scene file's `layers` list.
"""
from __future__ import annotations

import pytest
import torch

from renderer import CheckerTexture, ImageSettings, Light, Material, Scene, SceneError, SceneObject
from renderer import render
from renderer.cameras import build_camera
from renderer.cameras.layers import Layer, LayerCamera, build_layers
from renderer.tracing.render import render_passes
from renderer.shapes import build_shape

W, H = 61, 45  # odd, non-square
SCREEN_SIZE = (1.22, 0.90)  # pitch 0.02 at q3 = 1
# A moved and tilted main camera for the geometry checks.
POSE = dict(position=[0.3, -0.2, -1.0], look_at=[0.1, 0.0, 4.0], up=[0.1, -1.0, 0.05])


def main_camera(pose=None):
    return build_camera("camera", dict(type="pinhole", screen_size=list(SCREEN_SIZE), **(pose or {})), W, H)


def some_pixels(dtype=torch.float64, shape=(4, 6)):
    g = torch.Generator().manual_seed(2)
    return (torch.rand(*shape, 2, generator=g, dtype=torch.float64) * torch.tensor([W - 1.0, H - 1.0])).to(dtype)


def general_layer(alpha=1.5, scale=1.7):
    """A layer with every parameter away from its default: c off axis, f ≠ 0, m ≠ 1, s ≠ d."""
    return LayerCamera(main_camera(POSE), pseudo_screen_center=(0.6, 0.4, 3.0), alpha=alpha, move=(0.1, -0.2, 0.3),
                       scale=scale, pseudo_viewpoint=(-0.8, 0.8, 0.0))


def points(t):
    return torch.tensor(t, dtype=torch.float64)


# --- geometry of the layer rays --------------------------------------------------------------------------------

@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_layer_rays_are_unit_valid_and_batched(dtype):
    cam = general_layer()
    uv = some_pixels(dtype, (2, 3, 4))
    rays = cam.generate_rays(uv)
    assert rays.origin.shape == (2, 3, 4, 3) and rays.direction.shape == (2, 3, 4, 3), "(..., 2) -> (..., 3)"
    assert rays.valid.shape == (2, 3, 4) and bool(rays.valid.all()), f"every pixel has a layer ray: {rays.valid}"
    assert rays.direction.dtype == dtype and rays.origin.dtype == dtype, "dtype follows the pixels"
    norm = torch.linalg.vector_norm(rays.direction, dim=-1)
    tol = 1e-6 if dtype == torch.float32 else 1e-12
    assert torch.allclose(norm, torch.ones_like(norm), atol=tol), f"directions not unit: {norm}"


@pytest.mark.parametrize("alpha", [0.0, 0.5, 1.0, 2.0])
def test_layer_project_inverts_rays(alpha):
    cam = general_layer(alpha)
    uv = some_pixels()
    rays = cam.generate_rays(uv)
    for t in (1.0, 3.0, 6.0):
        err = (cam.project(rays.origin + t * rays.direction) - uv).abs().max()
        assert err < 1e-9, f"α={alpha}: a point at t={t} on a layer ray projects {float(err)} px off its pixel"


def test_layer_frame_follows_the_main_camera_up():
    cam = general_layer()
    A = cam.main_from_layer
    assert torch.allclose(A.T @ A, torch.eye(3, dtype=torch.float64), atol=1e-12), "A(i) must be a rotation"
    assert abs(float(torch.linalg.det(A)) - 1) < 1e-12, "A(i) must be proper (right-handed Σ(i))"
    e3 = (cam.center_main - cam.viewpoint_main) / cam.pseudo_screen_distance
    assert torch.allclose(A[:, 2], e3, atol=1e-12), "e3(i) must point from s(i) to c(i)"
    assert abs(float(A[1, 0])) < 1e-12, "e1(i) must be orthogonal to the main camera's y axis (no roll)"
    assert float(A[1, 1]) > 0, "e2(i) must point down in the main image, like the main camera's y"


@pytest.mark.parametrize("alpha", [0.0, 1.0, 2.0])
def test_pseudo_screen_centre_stays_at_the_moved_centre(alpha):
    """The pixel whose main ray meets c + f sees c, whatever α, s, m are (Fig. 10: the object stays in place)."""
    cam = general_layer(alpha)
    c, f = points([0.6, 0.4, 3.0]), points([0.1, -0.2, 0.3])
    uv0 = cam.main.project(c + f)
    assert torch.allclose(cam.project(c), uv0, atol=1e-9), f"c projects to {cam.project(c)}, not to {uv0}"
    rays = cam.generate_rays(uv0)
    to_c = c - rays.origin
    miss = torch.linalg.vector_norm(to_c - (to_c @ rays.direction) * rays.direction)
    assert miss < 1e-9, f"the ray of the centre pixel misses c by {float(miss)}"


def test_layer_ray_meets_the_pseudo_screen_at_the_unscaled_offset():
    """(12)–(14): the ray crosses Ξ(i) at distance |p' − c − f| / m from c, with p' on the moved screen Ξ'(i)."""
    cam = general_layer(alpha=0.7, scale=1.7)
    uv = some_pixels()
    rays = cam.generate_rays(uv)
    c, f = points([0.6, 0.4, 3.0]), points([0.1, -0.2, 0.3])
    R, d = cam.main.transform.world_from_camera, cam.main.transform.position
    e3 = R @ cam.main_from_layer[:, 2]
    t = ((c - rays.origin) @ e3) / (rays.direction @ e3)
    p = rays.origin + t[..., None] * rays.direction
    main = cam.main.generate_rays(uv)
    depth = float((c + f - d) @ R[:, 2])
    p_moved = main.origin + main.direction * (depth / (main.direction @ R[:, 2]))[..., None]
    got = torch.linalg.vector_norm(p - c, dim=-1)
    want = torch.linalg.vector_norm(p_moved - c - f, dim=-1) / 1.7
    assert torch.allclose(got, want, atol=1e-12), f"offsets on Ξ(i) {got} should be those on Ξ'(i) / m {want}"


def test_alpha0_layer_rays_start_at_the_pseudo_viewpoint():
    cam = general_layer(alpha=0.0)
    rays = cam.generate_rays(some_pixels())
    s = points([-0.8, 0.8, 0.0])
    assert torch.allclose(rays.origin, s.expand_as(rays.origin), atol=1e-12), "α=0: every ray starts at s(i)"


def test_default_layer_rays_equal_the_main_pinhole():
    """α = 0, s = d, f = 0, m = 1, c on the main axis: the main camera's own rays."""
    main = main_camera(POSE)
    d, axis = main.transform.position, main.transform.world_from_camera[:, 2]
    cam = LayerCamera(main, (d + 3.5 * axis).tolist(), alpha=0.0)
    for dtype, tol in ((torch.float64, 1e-12), (torch.float32, 1e-6)):
        uv = some_pixels(dtype)
        a, b = cam.generate_rays(uv), main.generate_rays(uv)
        assert torch.allclose(a.origin, b.origin, atol=tol), f"{dtype}: origins differ from the pinhole's"
        assert torch.allclose(a.direction, b.direction, atol=tol), f"{dtype}: directions differ from the pinhole's"


def test_singular_depth_projects_to_inf():
    cam = LayerCamera(main_camera(), (0.0, 0.0, 2.0), alpha=2.0)
    uv = cam.project(points([[0.3, 0.1, 4.0], [0.0, 0.0, 4.0], [0.3, 0.1, 3.0]]))  # apex depth 2·2/(2−1) = 4
    assert not bool(uv.isnan().any()), f"NaN at the singular depth: {uv}"
    assert bool(uv[:2].isinf().all()) and bool(uv[2].isfinite().all()), f"inf only at the singular depth: {uv}"


# --- the paper's Fig. 8/9 configuration ------------------------------------------------------------------------

LIGHT = (-1.2, -0.3, 0.0)
FRONT_CENTER = (0.0, 0.0, 2.0)


def paper_objects(with_front=True, only_front=False):
    """Fig. 6/8 in small: a patterned plate at depth 5, objects of size 0.8 and a small cube at depth 4
    (object 1), and a transparent refracting cube of size 0.8 at depth 2 (object 2)."""
    def obj(name, shape, **material):
        return SceneObject(name, build_shape(f"objects.{name}", shape), Material(**material))

    back = [
        # The checker is offset so that no pixel centre falls on a cell edge, where rounding would decide.
        obj("plate", dict(type="plane", point=[0.13, 0.07, 5], normal=[0, 0, -1]),
            texture=CheckerTexture(0.5, ((0.9, 0.9, 0.9), (0.25, 0.25, 0.25)))),
        obj("ball", dict(type="sphere", center=[1.0, -1.0, 4.0], radius=0.4), color=(0.9, 0.3, 0.2)),
        obj("mirror_ball", dict(type="sphere", center=[-1.0, -1.0, 4.0], radius=0.4), reflect=0.6),
        obj("block", dict(type="box", center=[-1.0, 0.8, 4.0], size=[0.8, 0.8, 0.8]), color=(0.2, 0.7, 0.3)),
        # The paper's small cube is 0.12; 0.25 keeps it a few pixels wide at this resolution.
        obj("small", dict(type="box", center=[0.0, 0.0, 4.0], size=[0.25, 0.25, 0.25]), color=(0.9, 0.9, 0.1)),
    ]
    front = obj("front", dict(type="box", center=list(FRONT_CENTER), size=[0.8, 0.8, 0.8]),
                color=(0.95, 0.95, 1.0), transmit=0.8, ior=1.5)
    if only_front:
        return [front]
    return back + [front] if with_front else back


def paper_scene(objects, layer_cfgs=None):
    cam = main_camera()
    lights = [Light("point", (40.0, 40.0, 40.0), LIGHT), Light("ambient", (0.05, 0.05, 0.05))]
    layers = [] if layer_cfgs is None else build_layers("layers", layer_cfgs, [o.name for o in objects], cam)
    return Scene(objects, lights, cam, ImageSettings(W, H, spp=1, max_depth=4, sampler="center"), layers)


def fig8_layers(alpha2=2.0, **layer2):
    back = ["plate", "ball", "mirror_ball", "block", "small"]
    return [dict(objects=back, alpha=0.0, pseudo_screen_center=[0, 0, 4]),
            dict(objects=["front"], alpha=alpha2, pseudo_screen_center=list(FRONT_CENTER), **layer2)]


def draw(scene):
    return render(scene, dtype=torch.float64).image


def silhouette(camera, shape):
    """(H, W) bool: pixel centres whose first ray (of `camera`) hits `shape`."""
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    rays = camera.generate_rays(torch.stack([xs, ys], -1).reshape(-1, 2))
    t, _ = shape.intersect(rays.origin, rays.direction, 1e-9)
    return t.isfinite().reshape(H, W)


@pytest.fixture(scope="module")
def fig8():
    scene = paper_scene(paper_objects(), fig8_layers())
    front_shape = scene.objects[-1].shape
    layer2 = max(scene.layers, key=lambda layer: layer.priority)
    return dict(
        layered=draw(scene),
        perspective=draw(paper_scene(paper_objects())),
        no_front=draw(paper_scene(paper_objects(with_front=False))),
        front_alone=draw(paper_scene(paper_objects(only_front=True), [fig8_layers()[1]])),
        front_in_layer=silhouette(layer2.camera, front_shape),
        front_in_perspective=silhouette(scene.camera, front_shape),
        scene=scene,
    )


def test_fig8_front_layer_is_drawn_on_top_and_inverted(fig8):
    scene = fig8["scene"]
    prios = [layer.priority for layer in scene.layers]
    assert prios == [-4.0, -2.0], f"default priorities should be minus the distance d→c: {prios}"
    passes = render_passes(scene)
    assert passes[-1][0] is scene.layers[1].camera, "the nearer pseudo-screen's layer must be drawn last"
    inl, inp = fig8["front_in_layer"], fig8["front_in_perspective"]
    assert int(inl.sum()) > 50, f"test set-up: the front cube should cover many pixels, got {int(inl.sum())}"
    # Inverted perspective: the cube's far face is drawn larger than its near face, unlike in perspective.
    near, far = points([0.4, 0.4, 1.6]), points([0.4, 0.4, 2.4])
    layer_uv = scene.layers[1].camera.project(torch.stack([near, far]))
    persp_uv = scene.camera.project(torch.stack([near, far]))
    assert float(layer_uv[1, 0]) > float(layer_uv[0, 0]), f"layer 2: far corner not outside the near one {layer_uv}"
    assert float(persp_uv[1, 0]) < float(persp_uv[0, 0]), f"perspective: far corner not inside the near one {persp_uv}"


def test_fig8_layer1_pixels_outside_the_front_cube_are_the_perspective_image(fig8):
    outside = ~fig8["front_in_layer"] & ~fig8["front_in_perspective"]
    diff = (fig8["layered"] - fig8["perspective"]).abs().amax(-1)
    assert int(outside.sum()) > 0.7 * W * H, "test set-up: most pixels lie outside the front cube"
    worst = float(diff[outside].max())
    assert worst < 1e-9, f"layer 1 changed by up to {worst} where the front cube is not drawn"


def test_fig8_front_cube_still_shadows_layer1(fig8):
    # The shadow of the cube's centre on the plate, seen from the main camera, away from the cube's silhouette.
    light, center = points(LIGHT), points(FRONT_CENTER)
    on_plate = center + (center - light) * ((5.0 - center[2]) / (center[2] - light[2]))
    x, y = (round(v) for v in fig8["scene"].camera.project(on_plate).tolist())
    assert not bool(fig8["front_in_layer"][y, x]), "test set-up: the shadow pixel must be outside the front cube"
    lit, shaded = float(fig8["no_front"][y, x].sum()), float(fig8["layered"][y, x].sum())
    assert shaded < 0.9 * lit, f"no shadow of the front cube on layer 1 at pixel ({x}, {y}): {shaded} vs {lit}"


def yellow(image):
    """(H, W) bool: pixels showing the small yellow cube (red and green well above blue)."""
    return (image[..., 0] > 1.5 * image[..., 2]) & (image[..., 1] > 1.5 * image[..., 2])


def test_fig8_objects_behind_are_seen_through_the_front_cube(fig8):
    inside = fig8["front_in_layer"]
    assert float(fig8["front_alone"][~inside].abs().max()) == 0.0, "test set-up: the front cube alone is over black"
    diff = (fig8["layered"] - fig8["front_alone"]).abs().amax(-1)[inside]
    # Rays entering the side faces end in total internal reflection and stay dark in both images.
    assert float((diff > 0.02).float().mean()) > 0.4, \
        f"inside the front cube the refracted background should show; mean change only {float(diff.mean())}"
    cy, cx = (H - 1) // 2, (W - 1) // 2
    assert bool(yellow(fig8["layered"])[cy, cx]), f"the small cube should show at the centre: {fig8['layered'][cy, cx]}"
    assert not bool(yellow(fig8["front_alone"])[cy, cx]), "test set-up: without it the centre is not yellow"


def test_fig8_object_seen_through_is_drawn_larger(fig8):
    """Paper: the small cube seen through the front cube grows with α(2), being farther than the pseudo-screen."""
    layered = int((yellow(fig8["layered"]) & fig8["front_in_layer"]).sum())
    perspective = int((yellow(fig8["perspective"]) & fig8["front_in_perspective"]).sum())
    assert perspective > 0, "test set-up: in perspective the small cube shows through the front cube"
    assert layered > 2 * perspective, f"α(2) = 2 should magnify the small cube: {layered} px vs {perspective} px"


def test_alpha0_layers_compose_to_the_perspective_image(fig8):
    """Both layers at α = 0, s = d, f = 0, m = 1 with c on the axis: exactly the plain perspective image."""
    img = draw(paper_scene(paper_objects(), fig8_layers(alpha2=0.0)))
    d = float((img - fig8["perspective"]).abs().max())
    assert d < 1e-9, f"α(i) = 0 layers differ from the perspective image by {d}"


def test_unlisted_objects_form_the_default_perspective_layer(fig8):
    img = draw(paper_scene(paper_objects(), [fig8_layers()[1]]))
    d = float((img - fig8["layered"]).abs().max())
    assert d < 1e-9, f"listing only the front cube should give the same image as listing both layers; diff {d}"


# --- validation ------------------------------------------------------------------------------------------------

NAMES = ["plate", "ball", "front"]


def good(**changes):
    cfg = dict(objects=["front"], alpha=2.0, pseudo_screen_center=[0, 0, 2])
    cfg.update(changes)
    return cfg


@pytest.mark.parametrize("cfgs, message", [
    ({"objects": ["front"]}, "layers: expected a list of layers"),
    ([good(), "front"], "layers[1]: expected an object, got 'front'"),
    ([good(objects=["front", "cube9"])], "layers[0].objects: unknown object 'cube9'"),
    ([good(objects=["ball"]), good(objects=["plate", "ball"])],
     "layers[1].objects: object 'ball' is already in layers[0]"),
    ([good(objects=["ball", "ball"])], "layers[0].objects: object 'ball' is already in this layer"),
    ([good(objects=[])], "layers[0].objects: expected a non-empty list of object names"),
    ([good(objects="front")], "layers[0].objects: expected a list, got 'front'"),
    ([good(objects=[3])], "layers[0].objects: expected object names (strings), got 3"),
    ([{"objects": ["front"], "pseudo_screen_center": [0, 0, 2]}], "layers[0].alpha: missing required key"),
    ([{"objects": ["front"], "alpha": 1}], "layers[0].pseudo_screen_center: missing required key"),
    ([good(alpha="two")], "layers[0].alpha: expected a number, got 'two'"),
    ([good(offset=[0, 0, 1])], "layers[0].offset: unknown key"),
    ([good(scale=0)], "layers[0].scale: expected a positive number, got 0"),
    ([good(move=[0, 0])], "layers[0].move: expected a list of 3 numbers"),
    ([good(pseudo_viewpoint=[0, 0, 2])], "layers[0].pseudo_screen_center: must differ from the pseudo-viewpoint"),
    ([good(pseudo_viewpoint=[0, -3, 2])], "layers[0].pseudo_screen_center: the pseudo-viewpoint looks along"),
    ([good(move=[0, 0, -3])], "layers[0].move: the moved pseudo-screen centre c + f must lie in front"),
    ([good(priority="top")], "layers[0].priority: expected a number, got 'top'"),
])
def test_bad_layers_name_the_field(cfgs, message):
    with pytest.raises(SceneError) as err:
        build_layers("layers", cfgs, NAMES, main_camera())
    assert message in str(err.value), f"message {str(err.value)!r} should contain {message!r}"


def test_layer_defaults_and_overrides():
    cam = main_camera(POSE)
    layers = build_layers("layers", [good(objects=["front", "plate"]), good(objects=["ball"], priority=7,
                                                                              pseudo_viewpoint=[1, 0, 0])],
                          NAMES, cam, {"type": "pinhole"})
    assert all(isinstance(layer, Layer) for layer in layers), "build_layers returns Layer records"
    assert layers[0].object_ids == frozenset({0, 2}), f"object ids follow the scene order: {layers[0].object_ids}"
    d = cam.transform.position
    want = -float(torch.linalg.vector_norm(points([0, 0, 2]) - d))
    assert abs(layers[0].priority - want) < 1e-12, f"default priority {layers[0].priority}, expected {want}"
    assert layers[1].priority == 7.0, "an explicit priority is kept"
    assert torch.allclose(layers[0].camera.viewpoint_main, torch.zeros(3, dtype=torch.float64), atol=1e-12), \
        "the default pseudo-viewpoint is the camera position"
    s_world = cam.transform.world_from_camera @ layers[1].camera.viewpoint_main + d
    assert torch.allclose(s_world, points([1, 0, 0]), atol=1e-12), "pseudo_viewpoint is read in the scene frame"


def test_scene_file_layers_reach_the_renderer():
    scenefile = pytest.importorskip("renderer.scene.file")
    cfg = {
        "image": {"width": 9, "height": 7},
        "camera": {"type": "pinhole", "fov_deg": 40},
        "objects": [{"name": "a", "shape": {"type": "sphere", "center": [0, 0, 4], "radius": 1}},
                    {"name": "b", "shape": {"type": "sphere", "center": [0, 0, 2], "radius": 0.3}}],
        "layers": [{"objects": ["b"], "alpha": 2, "pseudo_screen_center": [0, 0, 2]}],
    }
    scene = scenefile.load_scene(cfg)
    assert len(scene.layers) == 1 and scene.layers[0].object_ids == frozenset({1}), "layers built from the file"
    cfg["layers"][0]["objects"] = ["c"]
    with pytest.raises(SceneError, match=r"layers\[0\]\.objects: unknown object 'c'"):
        scenefile.load_scene(cfg)
