"""One lens type: only `renderer.cameras.lens.Lens` holds a thin lens's parameters (w, U, d, θF and their
spellings); every other class holds a `Lens`. The fitted `LensCamera` stores the lens's fit parametrisation
(log w, 1/U, d/10 mm, θF) as torch parameters and gives them back as a `Lens` (`LensCamera.lens`).

The scan reads the source (AST): a dataclass field or a `self.NAME = …` assignment of a lens parameter in any
class of renderer/ or tiltfit/ other than those two fails the test, so a tenth holder cannot creep back in.
"""
from __future__ import annotations

import ast
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from renderer import Lens, LensCamera, Sensor

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("renderer", "tiltfit")

#: Names a class would store a thin lens's parameters under (as found in the nine holders this replaced).
LENS_NAMES = frozenset({
    "w", "U", "d", "f", "theta_F", "theta_L", "inv_U",
    "w_mm", "U_mm", "U0_mm", "d_mm", "f_mm", "theta_F_rad", "theta_F_deg", "theta_L_deg", "theta_L_rad",
    "inv_U_per_m", "log_w_mm", "d_scaled", "aperture_mm", "focus_mm",
})

#: (file, class) allowed to store them, and why.
ALLOWED = {
    ("renderer/cameras/lens.py", "Lens"): "the one lens type",
    ("renderer/cameras/lens_model.py", "LensCamera"): "the fitted parametrisation of a Lens (its `lens` property)",
    ("renderer/beam/segment.py", "Node"): "not a lens: U, V are the in-plane axes of mirror faces",
    ("tiltfit/experiments/exact_capture.py", "ExactLens"): "the independent capture generator's own lens: it must "
                                                             "share no code with the lens it checks (issue 30 §4)",
    ("tiltfit/solve/blocks.py", "SchurNormal"): "not a lens: w holds the robust weights of the residuals",
}


def lens_holders(source: str, path: str) -> list[str]:
    """'path:line Class.name' for every class in `source` that stores a lens parameter."""
    found = []
    for cls in (n for n in ast.walk(ast.parse(source)) if isinstance(n, ast.ClassDef)):
        if (path, cls.name) in ALLOWED:
            continue
        for stmt in cls.body:  # dataclass fields and class attributes
            if isinstance(stmt, ast.AnnAssign) and isinstance(stmt.target, ast.Name) and stmt.target.id in LENS_NAMES:
                found.append(f"{path}:{stmt.lineno} {cls.name}.{stmt.target.id}")
        for node in ast.walk(cls):  # self.NAME = … in any method
            targets = node.targets if isinstance(node, ast.Assign) else [node.target] if isinstance(
                node, (ast.AnnAssign, ast.AugAssign)) else []
            for t in (e for tgt in targets for e in (tgt.elts if isinstance(tgt, ast.Tuple) else [tgt])):
                if (isinstance(t, ast.Attribute) and isinstance(t.value, ast.Name) and t.value.id == "self"
                        and t.attr in LENS_NAMES):
                    found.append(f"{path}:{t.lineno} {cls.name}.{t.attr}")
    return found


def test_only_the_lens_type_holds_lens_parameters():
    found = []
    for package in PACKAGES:
        for file in sorted((ROOT / package).rglob("*.py")):
            rel = file.relative_to(ROOT).as_posix()
            found += lens_holders(file.read_text(encoding="utf-8"), rel)
    assert not found, "a second class holds lens parameters (hold a renderer.Lens instead): " + "; ".join(found)


def test_the_scan_finds_a_second_holder():
    src = ("from dataclasses import dataclass\n@dataclass\nclass Cam:\n    w_mm: float\n"
           "class Other:\n    def __init__(self, lens):\n        self.w, self.U = lens.w, lens.U\n"
           "class Fine:\n    def __init__(self, lens):\n        self.lens = lens\n")
    assert lens_holders(src, "x.py") == ["x.py:4 Cam.w_mm", "x.py:7 Other.w", "x.py:7 Other.U"]
    assert lens_holders("class Lens:\n    w: float\n", "renderer/cameras/lens.py") == [], "the lens type itself"


# ------------------------------------------------------------------------------------------ the lens type

def test_hinge_and_scheimpflug_rules_from_tilt():
    """Lens.from_tilt: U = f w / (w cos θL − f) (hinge rule), tan θF = (U + w) tan θL / w (Scheimpflug); the
    derived f and θL give the inputs back."""
    w, f, tl = 55.39, 50.84, math.radians(5.0)
    lens = Lens.from_tilt(w, f, tl, 18.81)
    assert lens.U == pytest.approx(f * w / (w * math.cos(tl) - f), rel=1e-14), "hinge rule"
    assert math.tan(lens.theta_F) == pytest.approx((lens.U + w) * math.tan(tl) / w, rel=1e-14), "Scheimpflug"
    assert lens.f == pytest.approx(f, rel=1e-13) and lens.theta_L == pytest.approx(tl, rel=1e-13), "round trip"
    assert 648 < lens.U < 649 and 48.0 < math.degrees(lens.theta_F) < 48.1, "the paper's lens at 5°: U 648.4, θF 48°"
    with pytest.raises(ValueError, match="f"):
        Lens.from_tilt(w, 60.0, tl, 18.81)  # f > w cos θL: no real plane of focus


def test_paper_camera_and_binning():
    lens = Lens.paper()
    assert (lens.w, lens.U, lens.d) == (55.39, 618.4, 18.81) and lens.sensor.size_px == (5472, 3648)
    small = lens.binned(16)
    assert small.sensor.size_px == (342, 228) and small.sensor.pixel_pitch == pytest.approx(0.00654 * 16)
    assert small.focal_px == pytest.approx(lens.focal_px / 16), "the focal length in pixels scales with binning"
    assert small.K[0, 2] == pytest.approx((342 - 1) / 2), "principal point at the binned image's centre"


@pytest.mark.parametrize("field, value", [("w", 0.0), ("w", math.inf), ("U", -1.0), ("d", -0.5),
                                          ("theta_F", math.pi / 2)])
def test_refuses_impossible_lenses(field, value):
    kwargs = {"w": 50.0, "U": 600.0, "d": 10.0, "theta_F": 0.0, field: value}
    with pytest.raises(ValueError, match=field):
        Lens(**kwargs)


def test_fitted_module_round_trips_its_lens_with_gradients():
    """LensCamera.from_lens(lens).lens is the same lens, and its tensors carry the module's gradients."""
    lens = Lens.from_theta_L(50.0, 700.0, 12.0, math.radians(-3.0), sensor=Sensor(640, 480, 0.01),
                             principal_point_px=(321.0, 238.5), distortion=(-0.1, 0.02))
    cam = LensCamera.from_lens(lens, 2)
    back = cam.lens
    for name in ("w", "U", "d", "theta_F", "theta_L", "f"):
        assert float(getattr(back, name).detach()) == pytest.approx(getattr(lens, name), rel=1e-12), name
    assert back.sensor == lens.sensor and tuple(float(c) for c in back.center_px) == (321.0, 238.5)
    assert [float(k) for k in back.distortion[:2]] == pytest.approx([-0.1, 0.02])
    back.U.backward()
    assert cam.inv_U_per_m.grad is not None and float(cam.inv_U_per_m.grad) != 0, "U's gradient reaches 1/U"
    uv = cam.project(torch.tensor([[10.0, -20.0, 0.0]], dtype=torch.float64), view=0).detach()
    p_cam = cam.to_camera(torch.tensor([[10.0, -20.0, 0.0]], dtype=torch.float64), view=0).detach()
    assert torch.allclose(torch.as_tensor(lens.project(p_cam.numpy())), uv, atol=1e-9), "Lens.project = module's"


# ------------------------------------------------------------------------------------ focus through three points

POINTS = np.array([[-120.0, 40.0, 560.0], [150.0, -30.0, 700.0], [20.0, 110.0, 640.0]])


@pytest.mark.parametrize("given", ["w", "f"])
def test_focus_through_three_points_puts_them_in_focus(given):
    """The plane of focus of Lens.focus_through holds the three points: each lies on z = U + y_φ tan θF and its
    blur spot (the exact thin-lens formula, `Lens.blur_px`) has zero size; given f, the lens has that f."""
    sensor = Sensor(1368, 912, 0.026)
    kw = {"w": 55.39} if given == "w" else {"f": 50.0}
    lens = Lens.focus_through(POINTS, 18.81, sensor=sensor, **kw)
    c, s = math.cos(lens.phi), math.sin(lens.phi)
    y_phi = POINTS[:, 1] * c - POINTS[:, 0] * s
    assert np.allclose(POINTS[:, 2], lens.U + y_phi * math.tan(lens.theta_F), atol=1e-9), "points on the plane"
    assert np.abs(lens.blur_px(POINTS)).max() < 1e-6, f"in focus: blur {lens.blur_px(POINTS)} px"
    off = POINTS + np.array([0.0, 0.0, 40.0])
    assert lens.blur_px(off).min() > 1.0, "points 40 mm behind the plane are blurred"
    assert abs(lens.phi) <= math.pi / 2 and abs(lens.theta_F) > 0.1 and abs(lens.phi) > 0.1, "a turned tilt"
    if given == "f":
        assert lens.f == pytest.approx(50.0, rel=1e-9), "the hinge rule gives the lens its focal length"
    else:
        assert lens.w == 55.39


@pytest.mark.parametrize("points, match", [
    ([[0, 0, 500], [10, 10, 600], [20, 20, 700]], "collinear"),
    ([[0, 0, 0], [100, 0, 500], [0, 100, 500]], "through or behind"),
    ([[50, 0, 400], [50, 100, 800], [50, -60, 500]], "parallel to the optical axis"),
    ([[0, 0, 500], [10, 10, 600]], "three finite points"),
])
def test_focus_through_refuses_impossible_points(points, match):
    with pytest.raises(ValueError, match=match):
        Lens.focus_through(points, 10.0, w=50.0)


def test_scene_file_focus_points():
    """A thin_lens camera with `focus_points` (world frame) focuses on them; conflicts and bad points are
    refused naming the field."""
    from renderer import SceneError
    from renderer.cameras import build_camera

    base = {"type": "thin_lens", "w": 55.39, "d": 18.81, "sensor_size": [36.0, 24.0],
            "position": [10.0, -200.0, -50.0], "look_at": [0.0, 0.0, 600.0]}
    world = [[-100.0, 0.0, 500.0], [120.0, 20.0, 650.0], [0.0, 90.0, 700.0]]
    cam = build_camera("camera", {**base, "focus_points": world}, 36, 24)
    p_cam = cam.transform.points_to_camera(torch.tensor(world, dtype=torch.float64)).numpy()
    lens = cam.lens.with_(sensor=Sensor(36, 24, 1.0))
    assert np.abs(lens.blur_px(p_cam)).max() < 1e-6, "the three world points are in focus"
    with pytest.raises(SceneError, match="camera: give focus_points or U"):
        build_camera("camera", {**base, "focus_points": world, "U": 600.0}, 36, 24)
    with pytest.raises(SceneError, match="camera.focus_points: .*collinear"):
        build_camera("camera", {**base, "focus_points": [[0, 0, 500], [1, 1, 600], [2, 2, 700]]}, 36, 24)
