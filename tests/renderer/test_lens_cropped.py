"""`Lens.cropped`: a window of the sensor is the same camera (its rays and its projection) shifted by the
window's origin; composite renders and the board-alignment check of a calibration render only windows."""
import math

import pytest
import torch

from renderer import Lens, Sensor, ThinLensCamera, axis_angle_to_matrix


def _lens(distortion_centre: str) -> Lens:
    # tilted about a turned axis, off-centre principal point, strong distortion: every term the crop must keep
    return Lens(4.0, 900.0, 1.2, math.radians(3.0), Sensor(97, 61, 0.004), (51.3, 27.8),
                (0.21, -0.03, 0.002, -0.001, 0.01, 0.4, 0.0, 0.0), math.radians(25.0), distortion_centre)


def _camera(lens: Lens) -> ThinLensCamera:
    R = axis_angle_to_matrix(torch.tensor([0.2, -0.3, 0.1], dtype=torch.float64))
    return ThinLensCamera.from_calibration(lens, R, torch.tensor([-20.0, 15.0, 700.0], dtype=torch.float64))


@pytest.mark.parametrize("centre", ["sensor", "lens_axis"])
def test_cropped_rays_and_projection_equal_the_full_sensor_shifted(centre):
    lens = _lens(centre)
    x0, y0 = 30, -4  # a window reaching past the top edge
    crop = lens.cropped(x0, y0, 20, 13)
    assert crop.sensor.size_px == (20, 13), f"window size {crop.sensor.size_px}"
    full, part = _camera(lens), _camera(crop)
    g = torch.Generator().manual_seed(1)
    uv = torch.rand(200, 2, generator=g, dtype=torch.float64) * torch.tensor([19.0, 12.0], dtype=torch.float64)
    lens_uv = torch.rand(200, 2, generator=g, dtype=torch.float64)
    a = full.generate_rays(uv + torch.tensor([x0, y0], dtype=torch.float64), lens_uv)
    b = part.generate_rays(uv, lens_uv)
    assert torch.allclose(a.origin, b.origin, atol=1e-9), "ray origins differ between the full and cropped sensor"
    assert torch.allclose(a.direction, b.direction, atol=1e-9), "ray directions differ between the full and cropped sensor"
    p = torch.tensor([[10.0, -5.0, 0.0], [-40.0, 30.0, 20.0]], dtype=torch.float64)
    shift = full.project(p) - part.project(p)
    assert torch.allclose(shift, torch.tensor([[x0, y0]] * 2, dtype=torch.float64), atol=1e-9), \
        f"projection moved by {shift.tolist()}, expected the window origin ({x0}, {y0})"


def test_cropped_refuses_fractional_windows():
    with pytest.raises(ValueError, match="window"):
        _lens("sensor").cropped(1.5, 0, 10, 10)
