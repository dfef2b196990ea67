"""renderer.cameras.distortion: OpenCV's Brown–Conrady model, its inverse, and distorted cameras in scenes."""

import cv2
import numpy as np
import pytest
import torch

from renderer.cameras.distortion import BrownConrady, distort, distortion_from_config, undistort
from renderer.core.params import SceneError

COEFFS = {
    "opencv5": [-0.21, 0.05, 0.0027, 0.0007, -0.0055],
    "rational": [0.073, -0.105, -0.00097, 0.000086, -0.0024, 0.34, -0.14, -0.016],
}


def _grid(n=9, half=0.9):
    g = torch.linspace(-half, half, n, dtype=torch.float64)
    y, x = torch.meshgrid(g, 0.75 * g, indexing="ij")
    return torch.stack([x.reshape(-1), y.reshape(-1)], -1)


@pytest.mark.parametrize("name", sorted(COEFFS))
def test_distort_matches_cv2_project_points(name):
    xy = _grid()
    pts = torch.cat([xy, torch.ones(len(xy), 1, dtype=torch.float64)], -1).numpy()
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), np.eye(3), np.array(COEFFS[name]))
    ours = distort(xy, COEFFS[name]).numpy()
    assert np.abs(ours - ref.reshape(-1, 2)).max() < 1e-12, "same normalised coordinates as OpenCV"


@pytest.mark.parametrize("name", sorted(COEFFS))
def test_undistort_inverts_distort_and_agrees_with_cv2(name):
    xy = _grid()
    xd = distort(xy, COEFFS[name])
    back = undistort(xd, COEFFS[name])
    assert (back - xy).abs().max() < 1e-10, "undistort ∘ distort = identity"
    cv = cv2.undistortPoints(xd.numpy().reshape(-1, 1, 2), np.eye(3), np.array(COEFFS[name]),
                             criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14))
    assert np.abs(cv.reshape(-1, 2) - xy.numpy()).max() < 1e-6, "agrees with cv2.undistortPoints"


def test_undistort_is_differentiable_exactly():
    xd = (0.5 * _grid(4)).requires_grad_(True)
    k = torch.tensor(COEFFS["opencv5"], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b: undistort(a, b), (xd, k)), "implicit-function gradients"


def test_distort_is_identity_without_coefficients():
    xy = _grid()
    assert torch.equal(distort(xy, [0.0] * 5), xy), "zero coefficients change nothing"


def test_config_parsing_names_the_field():
    d = distortion_from_config("camera.distortion", {"model": "brown_conrady", "coefficients": [-0.2, 0.05]})
    assert d.coefficients[:3] == (-0.2, 0.05, 0.0) and len(d.coefficients) == 8, "padded to 8"
    with pytest.raises(SceneError, match="camera.distortion.coefficients"):
        distortion_from_config("camera.distortion", {"model": "brown_conrady", "coefficients": [1] * 9})
    with pytest.raises(SceneError, match="camera.distortion.model"):
        distortion_from_config("camera.distortion", {"model": "fisheye", "coefficients": [0.1]})


def test_scene_camera_with_distortion_matches_opencv_and_traces_through_undistorted_pixels():
    from renderer.scene.file import build_scene

    W, H, f_px = 321, 241, 250.0
    cfg = {"image": {"width": W, "height": H},
           "camera": {"type": "pinhole", "screen_distance": 1.0, "screen_size": [W / f_px, H / f_px],
                      "distortion": {"model": "brown_conrady", "coefficients": COEFFS["opencv5"]}},
           "objects": []}
    cam = build_scene(cfg).camera
    assert isinstance(cam.distortion, BrownConrady), "camera.distortion parsed"
    # World points seen by the default camera (frame = scene frame): project and compare with OpenCV.
    p = torch.tensor([[0.3, -0.2, 2.0], [-0.5, 0.4, 3.0], [0.0, 0.0, 1.0], [0.6, 0.45, 1.5]], dtype=torch.float64)
    uv = cam.project(p)
    K = np.array([[f_px, 0, (W - 1) / 2], [0, f_px, (H - 1) / 2], [0, 0, 1]])
    ref, _ = cv2.projectPoints(p.numpy(), np.zeros(3), np.zeros(3), K, np.array(COEFFS["opencv5"]))
    assert np.abs(uv.numpy() - ref.reshape(-1, 2)).max() < 1e-9, "projection equals cv2.projectPoints"
    # The ray generated at a point's distorted pixel passes through the point.
    rays = cam.generate_rays(uv.to(torch.float64))
    d = p / p.norm(dim=-1, keepdim=True)
    assert rays.valid.all(), "valid rays"
    assert (rays.direction.to(torch.float64) - d).abs().max() < 1e-6, "ray through the distorted pixel hits the point"


def test_thin_lens_with_distortion_focuses_the_distorted_pixel_on_its_point():
    """Every lens sample's ray at the distorted pixel of a point on the plane of focus passes through it."""
    from renderer.scene.file import build_scene

    W, H, w, U, pitch = 201, 151, 50.0, 600.0, 0.05
    cfg = {"image": {"width": W, "height": H},
           "camera": {"type": "thin_lens", "w": w, "U": U, "d": 20.0, "sensor_size": [W * pitch, H * pitch],
                      "distortion": {"model": "brown_conrady", "coefficients": [-0.3, 0.1]}},
           "objects": []}
    cam = build_scene(cfg).camera
    p = torch.tensor([[120.0, -80.0, U]], dtype=torch.float64)  # on the plane of focus (θF = 0)
    uv = cam.project(p).to(torch.float64)
    K = np.array([[w / pitch, 0, (W - 1) / 2], [0, w / pitch, (H - 1) / 2], [0, 0, 1]])
    ref, _ = cv2.projectPoints(p.numpy(), np.zeros(3), np.zeros(3), K, np.array([-0.3, 0.1, 0, 0, 0]))
    assert np.abs(uv.numpy() - ref.reshape(-1, 2)).max() < 1e-9, "chief ray projects as OpenCV"
    lens = torch.rand(64, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    rays = cam.generate_rays(uv.expand(64, 2), lens)
    o, d = rays.origin.to(torch.float64), rays.direction.to(torch.float64)
    t = (p[0, 2] - o[:, 2]) / d[:, 2]
    hit = o + t[:, None] * d
    assert rays.valid.all(), "valid rays"
    assert (hit - p).norm(dim=-1).max() < 1e-3, f"rays meet at the point: {(hit - p).norm(dim=-1).max():.2g} mm"


@pytest.mark.parametrize("k", [[-0.1, 0.02], [0.05], [-0.3, 0.1, 0.001, 0.001]])
def test_undistort_converges_in_float32(k):
    """The renderer traces in float32: no pixel may be left unconverged (a hole) where float64 converges."""
    grid = torch.stack(torch.meshgrid(torch.linspace(-0.7, 0.7, 101), torch.linspace(-0.55, 0.55, 81),
                                      indexing="ij"), -1).reshape(-1, 2)
    u64 = undistort(grid.to(torch.float64), k)
    u32 = undistort(grid.to(torch.float32), k)
    assert not bool(torch.isnan(u64).any()), "float64 converges on this grid"
    assert float(torch.isnan(u32).any(-1).float().mean()) == 0.0, "float32 pixels left unconverged"
    assert float((u32.double() - u64).abs().max()) < 1e-5, "float32 agrees with float64"
