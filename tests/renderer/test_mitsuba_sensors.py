"""Our cameras inside Mitsuba 3 (renderer/mitsuba): the sensor plugins produce our rays, and a scene exported
with them renders to our image (mean intensity within 1 %), tilted and untilted, and through the inverted
perspective. Runs on Mitsuba's `scalar_rgb` variant, which needs no LLVM (mitsuba is in the `test` extra).
"""
import json
import os

import numpy as np
import pytest
import torch

mi = pytest.importorskip("mitsuba")

from renderer import render  # noqa: E402
from renderer.mitsuba import load_mitsuba, to_mitsuba  # noqa: E402
from renderer.mitsuba.sensors import register, sensor_dict  # noqa: E402
from renderer.scene.file import load_scene  # noqa: E402

pytestmark = pytest.mark.usefixtures("restore_mitsuba_variant")  # conftest: no variant left behind

SCENE = os.path.join(os.path.dirname(__file__), "..", "..", "benchmarks", "scenes", "speed_thin_lens.json")
INVERTED = {"type": "inverted_perspective", "alpha": 2.0, "pseudo_screen_distance": 4.0, "screen_distance": 1.0,
            "screen_size": [1.2, 1.2]}
CASES = {"untilted": [], "tilted": ["camera.theta_F_deg=25", "camera.d=0.15"],
         "tilt axis turned": ["camera.theta_F_deg=25", "camera.d=0.15", "camera.tilt_axis_deg=60"],
         "inverted": ["camera=" + json.dumps(INVERTED)]}
# Rays only (the image check's 256 spp on scalar_rgb is slow): a calibrated tilt-shift lens, its distortion about
# the tilted lens's axis (OpenCV's tilted model; the calibrated camera of such a calibration).
RAY_CASES = {**CASES, "distortion about the lens axis": [
    "camera.theta_F_deg=25", "camera.d=0.15", "camera.tilt_axis_deg=60",
    "camera.distortion=" + json.dumps({"model": "brown_conrady", "coefficients": [-0.3, 0.05], "centre": "lens_axis"})]}


@pytest.fixture(scope="module")
def scalar():
    mi_ = load_mitsuba("scalar_rgb")
    assert mi_.variant() == "scalar_rgb", "the cross-check runs on scalar_rgb"
    mi_.set_log_level(mi_.LogLevel.Error)
    register(mi_)
    return mi_


def _scene(case, size=24, pose=()):
    return load_scene(SCENE, [f"image.width={size}", f"image.height={size}", *RAY_CASES[case], *pose])


@pytest.mark.parametrize("case", sorted(RAY_CASES))
def test_plugin_rays_are_our_rays(scalar, case):
    """For film positions at pixel centres, the plugin's world ray is ours (position and direction to 1e-5),
    at the lens centre and off it, under a turned and moved camera pose."""
    scene = _scene(case, 9, ["camera.position=[0.3,-0.2,0.5]", "camera.look_at=[0.1,0.0,4.0]"])
    cam = scene.camera
    sensor = scalar.load_dict(sensor_dict(scalar, cam, 1))
    W, H = cam.width, cam.height
    for px, py in [(0, 0), (8, 0), (4, 4), (2, 7), (8, 8)]:
        ours = cam.generate_rays(torch.tensor([[px, py]], dtype=torch.float64),
                                 torch.tensor([[0.5, 0.5]], dtype=torch.float64))
        ray, weight = sensor.sample_ray(0.0, 0.5, scalar.Point2f((px + 0.5) / W, (py + 0.5) / H),
                                        scalar.Point2f(0.5, 0.5))
        o, d = np.array(ray.o), np.array(ray.d)
        assert np.allclose(o, ours.origin[0].numpy(), atol=1e-5), f"{case} pixel {(px, py)}: origin {o} vs ours"
        assert np.allclose(d, ours.direction[0].numpy(), atol=1e-5), f"{case} pixel {(px, py)}: direction {d}"
        assert float(weight[0]) == 1.0, f"weight {weight}"
        for lens in [(0.1, 0.2), (0.9, 0.6), (0.3, 0.95)]:
            # Off-centre lens samples: Mitsuba's concentric map is the same as ours, so the rays agree too.
            ours = cam.generate_rays(torch.tensor([[px, py]], dtype=torch.float64),
                                     torch.tensor([lens], dtype=torch.float64))
            ray, _ = sensor.sample_ray(0.0, 0.5, scalar.Point2f((px + 0.5) / W, (py + 0.5) / H),
                                       scalar.Point2f(*lens))
            o, d = np.array(ray.o), np.array(ray.d)
            assert np.allclose(o, ours.origin[0].numpy(), atol=1e-5), f"{case} {(px, py)} lens {lens}: origin {o}"
            assert np.allclose(d, ours.direction[0].numpy(), atol=1e-5), f"{case} {(px, py)} lens {lens}: dir {d}"


@pytest.mark.parametrize("case", sorted(CASES))
def test_exported_scene_renders_our_image(scalar, case):
    """Our image and Mitsuba's (our plugin sensor, `direct` integrator) at 256 spp: mean intensity within
    1 %, and the per-pixel difference far below that of a mirrored image (orientation)."""
    scene = _scene(case)
    ours = render(scene, spp=256, intersector="torch").image.numpy()  # our tracer against Mitsuba
    scene_dict, dropped = to_mitsuba(scene, spp=256, plugin_sensor=True)
    assert dropped == [], f"the speed scene should carry over exactly, dropped {dropped}"
    theirs = np.array(scalar.render(scalar.load_dict(scene_dict), seed=3))
    rel = abs(ours.mean() / theirs.mean() - 1)
    assert rel < 0.01, f"{case}: mean intensity ours {ours.mean():.5f} vs Mitsuba {theirs.mean():.5f} ({100 * rel:.2f} %)"
    diff = np.abs(ours - theirs).mean()
    flipped = min(np.abs(ours - theirs[::-1]).mean(), np.abs(ours - theirs[:, ::-1]).mean())
    assert diff < 0.5 * flipped, f"{case}: per-pixel difference {diff:.4f} not far below a mirrored one {flipped:.4f}"


def test_unmappable_parts_are_named(scalar):
    """What Mitsuba cannot express is listed (mirror reflection, refraction), not silently lost; the
    background, the ambient light and a Phong highlight carry over."""
    scene = load_scene(SCENE, ["image.width=8", "image.height=8", "image.background=[0.1,0.1,0.1]",
                               'lights=[{"type": "ambient", "intensity": [0.1, 0.1, 0.1]}]',
                               "objects.sphere_top.material.specular=0.5", "objects.sphere_left.material.reflect=0.5",
                               "objects.sphere_right.material.transmit=0.2"])
    _, dropped = to_mitsuba(scene, spp=1)
    expected = ["sphere_left: reflect", "sphere_right: transmit"]
    assert dropped == expected, f"dropped {dropped}, expected {expected}"
