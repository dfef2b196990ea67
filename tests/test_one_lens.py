"""One lens type: only `renderer.cameras.lens.Lens` holds a thin lens's parameters (w, U, d, θF and their
spellings); every other class holds a `Lens`. The fitted `LensCamera` stores the lens's fit parametrisation
(log w, 1/U, d/10 mm, θF) as torch parameters and gives them back as a `Lens` (`LensCamera.lens`).

The scan reads the source (AST): a dataclass field or a `self.NAME = …` assignment of a lens parameter in any
class of renderer/ or tiltfit/ other than those two fails the test, so a tenth holder cannot creep back in.
"""
from __future__ import annotations

import ast
import math
import subprocess
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
    ("renderer/tracing/fused.py", "_CameraConstants"): "the compiled path's constants (Python numbers baked into the "
                                                       "compiled code), read from the camera's Lens on every batch",
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


# ------------------------------------------------------------------------------- one decoding, one centre, one focal
# Forms a second copy of the lens's arithmetic takes, each found by reading the source (AST), each with a planted
# example below that the scan must catch.

#: Where the stored lens vector (log w, 1/U, d in cm, θF) is decoded: `renderer.cameras.lens_vector`.
LENS_VECTOR_OWNER = "renderer/cameras/lens_vector.py"
#: Where the image centre ((W − 1)/2, (H − 1)/2) is written: `renderer.cameras.projection.image_centre_px`.
CENTRE_OWNER = "renderer/cameras/projection.py"
#: Where a CALIB dict's w becomes a focal length in pixels: the calibration object (`lens_from_calib`, `Calibration`).
FOCAL_OWNERS = ("tiltfit/files/calib_lens.py", "tiltfit/files/calibrated.py")
#: Files allowed a form anyway, and why.
INDEPENDENT = {
    "tiltfit/experiments/exact_capture.py": "the independent capture generator: it shares no code with the lens it "
                                            "checks (issue 30 §4), its pixel centre included",
}


def _text(node) -> str:
    return ast.unparse(node)


def _names_key(node, key: str) -> bool:
    """Whether `node` reads `key` from a mapping: x["key"] or x.get("key", ...)."""
    for n in ast.walk(node):
        if isinstance(n, ast.Subscript) and isinstance(n.slice, ast.Constant) and n.slice.value == key:
            return True
        if (isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute) and n.func.attr == "get" and n.args
                and isinstance(n.args[0], ast.Constant) and n.args[0].value == key):
            return True
    return False


def _by_position(node) -> bool:
    """Whether `node` is (a float of) a subscript by a small constant index: v[0], float(lens[1])."""
    if isinstance(node, ast.Call) and node.args and _text(node.func) in ("float", "abs"):
        node = node.args[0]
    if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "abs":
        node = node.func.value
    return isinstance(node, ast.Subscript) and isinstance(node.slice, ast.Constant) and node.slice.value in (0, 1, 2, 3)


def decoding_forms(source: str, path: str) -> list[str]:
    """'path:line what' for each hand decoding of the stored lens vector in `source`: exp of log w (by name or
    position), 1000 / (1/U), the aperture scale of d_scaled."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Name) and node.id == "APERTURE_SCALE_MM" and isinstance(node.ctx, ast.Load):
            found.append(f"{path}:{node.lineno} d_scaled's scale (APERTURE_SCALE_MM)")
        elif isinstance(node, ast.Call) and _text(node.func).split(".")[-1] == "exp" and node.args:
            arg = node.args[0]
            if "log_w" in _text(arg) or _by_position(arg):
                found.append(f"{path}:{node.lineno} w = exp(log w): {_text(node)}")
        elif (isinstance(node, ast.BinOp) and isinstance(node.op, ast.Div) and isinstance(node.left, ast.Constant)
              and node.left.value == 1000 and ("inv_U" in _text(node.right) or _by_position(node.right))):
            found.append(f"{path}:{node.lineno} U = 1000 / (1/U): {_text(node)}")
    return found


def calib_focal_forms(source: str, path: str) -> list[str]:
    """'path:line' for each focal length computed from a CALIB dict: a division whose numerator reads "w_mm" from a
    mapping (calib["w_mm"] / pitch, sigma.get("w_mm") / p)."""
    return [f"{path}:{n.lineno} {_text(n)}" for n in ast.walk(ast.parse(source))
            if isinstance(n, ast.BinOp) and isinstance(n.op, ast.Div) and _names_key(n.left, "w_mm")]


_SIZE_WORDS = ("width", "height", "size")


def _image_size(node) -> bool:
    """Whether `node` names an image size: W, H, W0, width_px, cam.height, size[0] ..."""
    text = _text(node)
    last = text.split(".")[-1]
    return last.rstrip("0123456789_px") in ("W", "H") or any(w in text.lower() for w in _SIZE_WORDS)


def centre_forms(source: str, path: str) -> list[str]:
    """'path:line' for each image centre written out: (W − 1) / 2 (or · 0.5) of an image size."""
    found = []
    for n in ast.walk(ast.parse(source)):
        if not (isinstance(n, ast.BinOp) and isinstance(n.left, ast.BinOp) and isinstance(n.left.op, ast.Sub)
                and isinstance(n.left.right, ast.Constant) and n.left.right.value == 1
                and isinstance(n.right, ast.Constant)):
            continue
        halves = (isinstance(n.op, ast.Div) and n.right.value == 2) or (isinstance(n.op, ast.Mult) and n.right.value == 0.5)
        if halves and _image_size(n.left.left):
            found.append(f"{path}:{n.lineno} {_text(n)}")
    return found


def _scan(form, owners) -> list[str]:
    found = []
    for package in PACKAGES:
        for file in sorted((ROOT / package).rglob("*.py")):
            rel = file.relative_to(ROOT).as_posix()
            if rel in owners or rel in INDEPENDENT:
                continue
            found += form(file.read_text(encoding="utf-8"), rel)
    return found


def test_the_lens_vector_is_decoded_in_one_place():
    found = _scan(decoding_forms, (LENS_VECTOR_OWNER,))
    assert not found, ("the stored lens vector decoded by hand (call renderer.cameras.lens_vector.lens_values / "
                       "stored_from_lens / stored_lens_sigma): " + "; ".join(found))


def test_only_the_calibration_object_turns_calib_w_into_a_focal_length():
    found = _scan(calib_focal_forms, FOCAL_OWNERS)
    assert not found, ("a CALIB dict's w divided by hand (use tiltfit.files.calibrated.Calibration.focal_px / "
                       "sigma_focal_px, or lens_from_calib(...).focal_px / .K): " + "; ".join(found))


def test_the_image_centre_is_written_once():
    found = _scan(centre_forms, (CENTRE_OWNER,))
    assert not found, "(W − 1)/2 written out (use renderer.cameras.image_centre_px): " + "; ".join(found)


def test_the_scans_find_their_planted_forms(tmp_path):
    """Each form above, planted in a temporary file, is caught; the owners' own spellings and look-alikes are not."""
    planted = tmp_path / "planted.py"
    planted.write_text(
        "import math, torch\n"
        "def decode(p, lens, cam, params):\n"
        "    w, U = torch.exp(p[0]), 1000.0 / p[1]\n"                                # 3: two forms
        "    d = APERTURE_SCALE_MM * abs(float(lens[2]))\n"                           # 4
        "    w2 = math.exp(float(cam.log_w_mm))\n"                                   # 5
        "    U2 = 1000.0 / params['inv_U_per_m']\n"                                  # 6
        "    return torch.exp(-x[..., 0] ** 2), 1000.0 / n_views\n"                    # 7: look-alikes
        "def focal(calib, sig, p):\n"
        "    F = calib['w_mm'] / calib['pixel_pitch_mm']\n"                          # 9
        "    sF = sig.get('w_mm') / p\n"                                              # 10
        "    return F, calib['w_mm'] * 2, w_mm / p\n"                                 # 11: look-alikes
        "def centre(W, H, cam, kernel):\n"
        "    c = ((W - 1) / 2, (H - 1) / 2.0)\n"                                      # 13: two
        "    x = (cam.width - 1) * 0.5\n"                                              # 14
        "    return (kernel - 1) / 2, (len(kernel) - 1) // 2\n")                      # 15: look-alikes
    src, rel = planted.read_text(), "planted.py"
    lines = lambda found: [int(f.split(":")[1].split()[0]) for f in found]  # noqa: E731
    assert sorted(lines(decoding_forms(src, rel))) == [3, 3, 4, 5, 6], decoding_forms(src, rel)
    assert sorted(lines(calib_focal_forms(src, rel))) == [9, 10], calib_focal_forms(src, rel)
    assert sorted(lines(centre_forms(src, rel))) == [13, 13, 14], centre_forms(src, rel)
    owner = (ROOT / LENS_VECTOR_OWNER).read_text(encoding="utf-8")
    assert decoding_forms(owner, LENS_VECTOR_OWNER), "the owner itself decodes (the scan would see it if it moved)"
    assert centre_forms((ROOT / CENTRE_OWNER).read_text(encoding="utf-8"), CENTRE_OWNER), "the centre's owner writes it"
    for rel in INDEPENDENT:
        assert (ROOT / rel).exists(), f"{rel}: allowed but gone (drop it from INDEPENDENT)"


#: What a camera holding a `Lens` must read from it rather than keep beside it (the Screen at w, the distortion).
LENS_DERIVED = frozenset({"screen", "distortion", "principal_point_px", "center_px", "focal_px", "distance"})


def lens_copies(source: str, path: str) -> list[str]:
    """'path:line Class.name' for each class that holds a lens (`self.lens = …`) and also stores something its
    lens determines (`LENS_DERIVED`: a Screen at w, the distortion, the principal point)."""
    found = []
    for cls in (n for n in ast.walk(ast.parse(source)) if isinstance(n, ast.ClassDef)):
        # attributes set on self or on a camera the class builds (cam.distortion = … in a classmethod)
        stored = [(t.value.id, t.attr, t.lineno) for node in ast.walk(cls) if isinstance(node, ast.Assign)
                  for tgt in node.targets for t in (tgt.elts if isinstance(tgt, ast.Tuple) else [tgt])
                  if isinstance(t, ast.Attribute) and isinstance(t.value, ast.Name)]
        if not any(owner == "self" and name == "lens" for owner, name, _ in stored):
            continue
        found += [f"{path}:{line} {cls.name}.{name}" for _, name, line in stored if name in LENS_DERIVED]
        for call in (n for n in ast.walk(cls) if isinstance(n, ast.Call)):  # super().__init__(transform, screen)
            if (isinstance(call.func, ast.Attribute) and call.func.attr == "__init__"
                    and any(isinstance(a, ast.Name) and a.id in LENS_DERIVED for a in call.args)):
                found.append(f"{path}:{call.lineno} {cls.name}.screen (given to the base class)")
    return found


def test_a_camera_with_a_lens_keeps_no_copy_of_it():
    found = []
    for package in PACKAGES:
        for file in sorted((ROOT / package).rglob("*.py")):
            rel = file.relative_to(ROOT).as_posix()
            found += lens_copies(file.read_text(encoding="utf-8"), rel)
    assert not found, "a camera keeps lens state beside its Lens (read it from the lens): " + "; ".join(found)


def test_the_copy_scan_finds_a_screen_beside_a_lens():
    src = ("class Cam:\n    def __init__(self, screen, lens):\n        self.lens = lens\n        self.screen = screen\n"
           "        self.distortion = lens.distortion\n"
           "class Pinhole:\n    def __init__(self, screen):\n        self.screen = screen\n"
           "class Thin(Camera):\n    def __init__(self, transform, screen, lens):\n"       # 9: the form this replaced
           "        super().__init__(transform, screen)\n        self.lens = lens\n"
           "    @classmethod\n    def of(cls, lens):\n        cam = cls(None, None, lens)\n"
           "        cam.distortion = lens.distortion\n        return cam\n")
    assert sorted(lens_copies(src, "x.py")) == ["x.py:11 Thin.screen (given to the base class)", "x.py:16 Thin.distortion",
                                                "x.py:4 Cam.screen", "x.py:5 Cam.distortion"], lens_copies(src, "x.py")
    old = subprocess.run(["git", "show", "c4c7693:renderer/cameras/thin_lens.py"], cwd=ROOT, capture_output=True,
                         text=True)
    if old.returncode == 0:  # the camera before issue 31 §2 kept a Screen at w and its own distortion
        assert lens_copies(old.stdout, "thin_lens.py"), "the scan finds the old ThinLensCamera's copies"
