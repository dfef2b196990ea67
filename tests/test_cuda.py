"""The CUDA path against the CPU reference (skipped where no GPU is present; CI has none).

Camera samples are the same numbers on every device (integer hashing; checked bit for bit below), so a
float64 render on CUDA should be the CPU image up to rounding, except on the few pixels where a ray grazes an edge and the two devices' rounding
takes different sides. Run on a GPU machine with `pytest tests/test_cuda.py`.
"""
from __future__ import annotations

import glob
import math
import os

import numpy as np
import pytest
import torch

from renderer.cameras import EOS_6D
from renderer import load_scene
from renderer import render

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")

SCENES = sorted(p for p in glob.glob(os.path.join(os.path.dirname(__file__), "..", "renderer", "scenes", "*.json"))
                if not p.endswith("gallery.json"))  # gallery.json is a list of views, rendered by `renderer gallery`


def _small(path):
    return load_scene(path, ["image.width=64", "image.height=48"])


@pytest.mark.parametrize("path", SCENES, ids=[os.path.basename(p) for p in SCENES])
def test_cuda_render_equals_cpu(path):
    scene = _small(path)
    cpu = render(scene, spp=4, dtype=torch.float64).image
    gpu = render(scene, spp=4, dtype=torch.float64, device="cuda").image
    assert gpu.device.type == "cuda", "the image should stay on the device it was rendered on"
    diff = (gpu.cpu() - cpu).abs().amax(-1)
    off = float((diff > 1e-6).double().mean())
    assert off <= 0.01, f"{os.path.basename(path)}: {off:.2%} of pixels differ by more than 1e-6"
    assert float(diff.mean()) <= 2e-3, f"{os.path.basename(path)}: mean |cuda - cpu| = {float(diff.mean()):.3g}"
    assert float(cpu.std()) > 0.01, "the scene should not render flat"


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cuda_float32_and_compile_paths(dtype):
    scene = _small(os.path.join(os.path.dirname(__file__), "..", "renderer", "scenes", "fig6.json"))
    cpu = render(scene, spp=2, dtype=torch.float64).image
    gpu = render(scene, spp=2, dtype=dtype, device="cuda", culling=False).image.cpu().double()
    mean = float((gpu - cpu).abs().mean())
    assert mean <= (2e-3 if dtype == torch.float32 else 1e-6), f"{dtype}: mean |cuda - cpu| = {mean:.3g}"


def test_cuda_thin_lens_gradients_equal_cpu():
    from renderer import CameraTransform
    from renderer.cameras import Lens
    from renderer.cameras.thin_lens import ThinLensCamera

    def grads(device):
        p = [torch.tensor(v, dtype=torch.float64, device=device, requires_grad=True)
             for v in (50.0, 600.0, 20.0, math.radians(30.0))]
        cam = ThinLensCamera(CameraTransform(torch.eye(3, dtype=torch.float64, device=device),
                                             torch.zeros(3, dtype=torch.float64, device=device)), Lens(*p), (9, 7),
                             (4.5, 3.5))
        g = torch.Generator().manual_seed(3)
        uv = (torch.rand(16, 2, generator=g, dtype=torch.float64) * 6).to(device)
        lens = (0.15 + 0.7 * torch.rand(16, 2, generator=g, dtype=torch.float64)).to(device)
        rays = cam.generate_rays(uv, lens)
        (rays.origin.sum() + (rays.direction ** 2).sum()).backward()
        return torch.stack([q.grad.cpu() for q in p])

    cpu, gpu = grads("cpu"), grads("cuda")
    assert torch.allclose(cpu, gpu, rtol=1e-9, atol=1e-12), f"cpu {cpu} vs cuda {gpu}"
    assert float(cpu.abs().max()) > 0, "the gradients should not vanish"


def test_cuda_photometric_target_render_equals_cpu():
    from tiltfit.experiments import reproduce
    from renderer import Lens, ThinLensCamera, axis_angle_to_matrix
    from tiltfit.photometric import hammersley_disc_samples, render_target
    from tiltfit.target.layout import Target

    board = Target(tuple(50.0 * i for i in range(7)), tuple(50.0 * j for j in range(5)), (0, 0), 25.0)
    sensor = EOS_6D.binned(16)
    R, T = reproduce.target_pose(board, 30.0, 5.0, 600.0)
    import cv2

    def run(device):
        t = lambda v: torch.tensor(v, dtype=torch.float64, device=device)  # noqa: E731
        uv = torch.stack(torch.meshgrid(torch.arange(120.0, 220.0, 3.0), torch.arange(80.0, 140.0, 3.0),
                                        indexing="xy"), -1).reshape(-1, 2).to(device, torch.float64)
        lens_uv = hammersley_disc_samples(16).to(device)
        rvec = t(cv2.Rodrigues(R)[0].reshape(3))
        lens = Lens(t(55.0), 1000.0 / t(1.4), t(30.0), t(math.radians(40)), sensor)
        cam = ThinLensCamera.from_calibration(lens, axis_angle_to_matrix(rvec), t(T))
        return render_target(board, cam, uv, lens_uv, t(0.8), t(0.06), t(0.05))

    cpu, gpu = run("cpu"), run("cuda")
    assert gpu.device.type == "cuda"
    assert torch.allclose(cpu, gpu.cpu(), atol=1e-9), f"max diff {float((cpu - gpu.cpu()).abs().max()):.3g}"
    assert float(cpu.max() - cpu.min()) > 0.3, "the pixels should see the board's edges"


def test_cuda_cli_render(tmp_path):
    from renderer.cli.main import main
    from camio.files import read_image

    scene = os.path.join(os.path.dirname(__file__), "..", "renderer", "scenes", "tilt_fig9a.json")
    common = [scene, "--set", "image.width=48", "--set", "image.height=32", "--spp", "2", "--quiet",
              "--encoding", "linear"]
    for device in ("cpu", "cuda"):
        assert main(["render", *common, "--device", device, "-o", str(tmp_path / f"{device}.exr")]) in (0, None)
    a, b = read_image(str(tmp_path / "cpu.exr")), read_image(str(tmp_path / "cuda.exr"))
    assert np.abs(a - b).mean() <= 2e-3, "CLI render on CUDA should match the CPU"


def test_cuda_default_chunk_is_large_and_changes_nothing():
    from renderer.tracing.render import CPU_CHUNK_RAYS, default_chunk_rays

    assert default_chunk_rays("cuda") > CPU_CHUNK_RAYS, "a GPU should trace more rays per batch than the CPU"
    assert default_chunk_rays("cpu") == CPU_CHUNK_RAYS
    scene = load_scene(os.path.join(os.path.dirname(__file__), "..", "benchmarks", "scenes", "speed_thin_lens.json"),
                       ["image.width=96", "image.height=80"])
    big = render(scene, spp=4, device="cuda", dtype=torch.float64).image
    small = render(scene, spp=4, device="cuda", dtype=torch.float64, chunk_rays=1 << 12).image
    assert float((big - small).abs().max()) <= 1e-9, "the image should not depend on the batch size"


@pytest.mark.parametrize("name", ["independent", "stratified", "sobol", "center"])
def test_cuda_camera_samples_are_the_cpu_samples_bit_for_bit(name):
    from renderer.tracing.sampling import camera_samples as _camera_samples
    from renderer.tracing.sampling import Sampler

    pixel = torch.arange(0, 5000, 7)
    smp = Sampler(name, 16, seed=5)
    for dtype in (torch.float32, torch.float64):
        cpu = _camera_samples(smp, pixel, 97, dtype)
        gpu = _camera_samples(smp, pixel.cuda(), 97, dtype)
        for a, b in zip(cpu, gpu):
            assert b.device.type == "cuda"
            assert torch.equal(a, b.cpu()), f"{name} {dtype}: samples differ between devices"


def test_cuda_tilted_lens_with_distortion_about_its_axis_equals_cpu():
    """A thin lens tilted about a turned axis (φ = 30°) whose distortion is centred on its own axis (OpenCV's
    tilted model): the rays the CUDA path traces are the CPU's."""
    path = os.path.join(os.path.dirname(__file__), "..", "renderer", "scenes", "tilt_fig9b.json")
    scene = load_scene(path, ["image.width=64", "image.height=48", "camera.tilt_axis_deg=30",
                              'camera.distortion={"model": "brown_conrady", "coefficients": [-0.12, 0.02, 0, 0, 0], '
                              '"centre": "lens_axis"}'])
    assert scene.camera.lens.distortion_centre == "lens_axis", "the scene should carry the lens-axis centre"
    cpu = render(scene, spp=4, dtype=torch.float64).image
    gpu = render(scene, spp=4, dtype=torch.float64, device="cuda").image.cpu()
    diff = (gpu - cpu).abs().amax(-1)
    off = float((diff > 1e-6).double().mean())
    assert off <= 0.01, f"{off:.2%} of pixels differ by more than 1e-6"
    assert float(cpu.std()) > 0.01, "the scene should not render flat"
