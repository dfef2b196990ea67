"""The one sensor model (renderer.cameras.sensor): fall-off, noise statistics, 8-bit sRGB, and that the capture
simulations use it."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from renderer import Lens, Sensor
from renderer.cameras.sensor import SensorResponse, decode_srgb8, encode_srgb8, radial_falloff


def test_falloff_is_one_at_the_centre_and_one_minus_v_at_the_corners():
    W, H, v = 9, 5, 0.2
    x = np.array([4.0, 0.0, 8.0, 0.0, 8.0, 8.0])
    y = np.array([2.0, 0.0, 0.0, 4.0, 4.0, 2.0])
    got = radial_falloff(x, y, W, H, v)
    # The last point is mid-right: ρ² = 4² / (4² + 2²) = 0.8.
    want = np.array([1.0, 1 - v, 1 - v, 1 - v, 1 - v, 1 - v * 0.8])
    assert np.allclose(got, want, atol=1e-15), f"fall-off {got}, want {want}"


def test_falloff_on_tensors_is_differentiable_in_v():
    v = torch.tensor(0.1, dtype=torch.float64, requires_grad=True)
    x = torch.tensor([0.0, 3.0, 6.0], dtype=torch.float64)
    f = radial_falloff(x, torch.zeros(3, dtype=torch.float64), 7, 7, v)
    f.sum().backward()
    rho2 = ((x - 3.0) ** 2 + 9.0) / 18.0
    assert torch.allclose(v.grad, -rho2.sum()), f"d/dv {float(v.grad)} vs {-float(rho2.sum())}"
    assert np.allclose(f.detach().numpy(), radial_falloff(x.numpy(), np.zeros(3), 7, 7, 0.1)), "numpy == torch"


@pytest.mark.parametrize("level", [0.05, 0.4])
def test_noise_has_the_stated_mean_and_variance(level):
    s = SensorResponse(gain=0.9, black=0.01, read_noise=0.004, full_well=2000.0)
    flat = np.full((400, 500), level)
    out = s.expose(flat, np.random.default_rng(3))
    signal = 0.9 * level + 0.01
    var = 0.004**2 + signal / 2000.0
    n = out.size
    assert abs(out.mean() - signal) < 4 * np.sqrt(var / n), f"mean {out.mean():.6f}, want {signal:.6f}"
    # The sample variance of n normals has relative σ sqrt(2/n) (0.3 % here): 2 % either way fails.
    assert abs(out.var() / var - 1) < 0.02, f"variance {out.var():.3g}, want {var:.3g}"


def test_vignetting_darkens_the_corners_of_an_image_and_keeps_channels():
    s = SensorResponse(vignetting=0.3)
    img = np.ones((5, 7, 3))
    out = s.signal(img)
    assert out.shape == (5, 7, 3)
    assert out[2, 3].tolist() == [1.0, 1.0, 1.0], "centre untouched"
    assert np.allclose(out[0, 0], 0.7) and np.allclose(out[4, 6], 0.7), "corners at 1 − v"
    shifted = s.signal(img[..., 0], centre=(0.0, 0.0))
    assert shifted[0, 0] == 1.0 and shifted[4, 6] < 0.7, "a principal point moves the fall-off"


def test_srgb8_levels_and_round_trip():
    lin = np.array([0.0, 1.0, 0.5, 0.0031308, 2.0, -1.0])
    enc = encode_srgb8(lin)
    assert enc.dtype == np.uint8
    # sRGB(0.5) = 1.055 · 0.5^(1/2.4) − 0.055 = 0.7354 -> 187.5 -> 188; the knee 0.0031308 -> 0.04045 -> 10.3.
    assert enc.tolist() == [0, 255, 188, 10, 255, 0], f"levels {enc.tolist()}"
    levels = np.arange(256)
    back = encode_srgb8(decode_srgb8(levels))
    assert np.array_equal(back, levels), "decode then encode gives every level back"


def test_srgb8_table_matches_the_formula_to_the_last_bit():
    """`encode_srgb8` reads large arrays from a table: the same codes as round(255 · sRGB(v)) everywhere, the 2,000
    floats either side of every code's threshold and values outside [0, 1] (-0.0 included) among them."""
    from camio.files import _encode_srgb8_formula, _srgb8_table

    nxt = _srgb8_table()[1]
    thresholds = np.unique(nxt[np.isfinite(nxt)])
    assert thresholds.size == 255, f"{thresholds.size} thresholds, one per code above 0"
    near = (thresholds.view(np.int64)[:, None] + np.arange(-2000, 2000)[None]).view(np.float64).ravel()
    rng = np.random.default_rng(3)
    v = np.concatenate([near, rng.random(100_000) ** 4, rng.normal(0.5, 1.0, 100_000), [-0.0, 0.0, 1.0, 5e-324]])
    got, want = encode_srgb8(v), _encode_srgb8_formula(np.clip(v, 0.0, 1.0))
    assert got.dtype == np.uint8 and np.array_equal(got, want), f"{int((got != want).sum())} codes differ"
    img = rng.random((300, 200)).astype(np.float32)
    assert np.array_equal(encode_srgb8(img), _encode_srgb8_formula(img.astype(np.float64))), "float32 image"


def test_srgb8_float32_table_matches_the_formula_to_the_last_bit():
    """float32 images are read from their own table (no float64 copy, no clipping): the same codes as the formula
    on the values made float64, the 3,000 float32 values either side of every threshold, values outside [0, 1], and
    the first and last value of every one of the table's 65,536 bins (NaN's aside)."""
    from camio.files import _encode_srgb8_formula, _srgb8_table32, _srgb8_thresholds

    assert np.isfinite(_srgb8_table32()[1]).sum() > 0 and _srgb8_table32()[1].dtype == np.float32
    t = _srgb8_thresholds().astype(np.float32)
    near = (t.view(np.int32)[:, None] + np.arange(-3000, 3000, dtype=np.int32)[None]).view(np.float32).ravel()
    rng = np.random.default_rng(4)
    v = np.concatenate([near, (rng.random(100_000) ** 4).astype(np.float32),
                        rng.normal(0.5, 1.0, 100_000).astype(np.float32),
                        np.array([-0.0, 0.0, 1.0, 1e-45, np.inf, -np.inf], np.float32)])
    ends = (np.arange(1 << 16, dtype=np.uint32)[:, None] << 16) + np.array([0, 0xFFFF], np.uint32)
    ends = ends.view(np.float32).ravel()
    v = np.concatenate([v, ends[~np.isnan(ends)]])
    got, want = encode_srgb8(v), _encode_srgb8_formula(np.clip(v.astype(np.float64), 0.0, 1.0))
    assert got.dtype == np.uint8 and np.array_equal(got, want), f"{int((got != want).sum())} codes differ"
    with_nan = v.copy()
    with_nan[7] = np.nan
    with np.errstate(invalid="ignore"):  # the formula casts NaN to a code
        want = _encode_srgb8_formula(np.clip(with_nan.astype(np.float64), 0, 1))
        assert np.array_equal(encode_srgb8(with_nan), want), "NaN takes the formula"


def test_quantised_output_and_decode():
    s = SensorResponse(encoding="srgb8")
    out = s.expose(np.array([[0.2, 0.8]]))
    assert out.dtype == np.uint8
    assert np.allclose(s.decode(out), [[0.2, 0.8]], atol=0.004), "decoded within half a level"
    lin8 = SensorResponse(encoding="linear8").expose(np.array([[0.5]]))
    assert lin8.tolist() == [[128]], "linear 8-bit: round(255 · 0.5)"


@pytest.mark.parametrize("kwargs, field", [({"encoding": "jpeg"}, "encoding"), ({"full_well": 0.0}, "full_well"),
                                           ({"read_noise": -1.0}, "read_noise")])
def test_bad_settings_are_refused(kwargs, field):
    with pytest.raises(ValueError, match=field):
        SensorResponse(**kwargs)


def test_noisy_sensor_needs_an_rng():
    with pytest.raises(ValueError, match="rng"):
        SensorResponse(read_noise=0.01).expose(np.zeros((2, 2)))


def test_capture_simulations_use_the_sensor_model():
    """tiltfit's simulated camera and synthetic views expose through this model: the same numbers for the
    same settings and noise draws."""
    from tiltfit.experiments import synth
    from tiltfit.experiments import reproduce
    from tiltfit.target.layout import Target

    cam = reproduce.SimulatedCamera()
    rad = np.random.default_rng(0).random((30, 40, 3)) * 0.9
    want = SensorResponse(vignetting=cam.vignetting, read_noise=cam.read_noise, full_well=cam.full_well,
                          encoding="srgb8").expose(rad, np.random.default_rng(7))
    assert np.array_equal(cam.expose(rad, np.random.default_rng(7)), want), "reproduce's photos"

    target = Target(tuple(20.0 * i for i in range(5)), tuple(20.0 * j for j in range(4)))
    sc = Lens(35, 900, 8, sensor=Sensor(64, 48, 0.05))
    R, T = synth.look_at_pose(target, (40.0, 30.0, -600.0))
    view = synth.render_view(target, sc, R, T, vignetting=0.2, noise_sigma=0.01, srgb8=True, seed=4)
    s = SensorResponse(vignetting=0.2, read_noise=0.01, encoding="srgb8")
    want = s.expose(view.clean.astype(np.float64), np.random.default_rng(4), centre=sc.center_px)
    assert np.array_equal(view.image_srgb8[..., 0], want), "synth's 8-bit views"


def test_a_tensor_is_exposed_like_an_array():
    """Noise-free, a tensor (exposed on its device) gives the numpy path's levels; with noise, the torch draw
    has the stated mean and variance."""
    s = SensorResponse(gain=0.9, black=0.01, vignetting=0.3, encoding="srgb8")
    rad = np.random.default_rng(5).random((40, 60, 3)) * 0.9
    want = s.expose(rad, centre=(20.0, 15.0))
    got = s.expose(torch.from_numpy(rad), centre=(20.0, 15.0))
    assert got.dtype == np.uint8 and np.array_equal(got, want), "noise-free levels equal numpy's"

    noisy = SensorResponse(read_noise=0.004, full_well=2000.0)
    flat = torch.full((400, 500), 0.3, dtype=torch.float64)
    out = noisy.expose(flat, torch.Generator().manual_seed(3))
    var = 0.004**2 + 0.3 / 2000.0
    assert abs(out.mean() - 0.3) < 4 * np.sqrt(var / out.size), f"mean {out.mean():.6f}"
    assert 0.97 < out.var() / var < 1.03, f"variance ratio {out.var() / var:.4f}"
    again = noisy.expose(flat, torch.Generator().manual_seed(3))
    assert np.array_equal(out, again), "the same generator seed gives the same draw"
    with pytest.raises(ValueError, match="torch.Generator"):
        noisy.expose(flat, np.random.default_rng(3))


def test_uint8_levels_are_written_unchanged(tmp_path):
    from camio.files import ImageIOError, read_image, write_image
    import OpenImageIO as oiio

    levels = np.random.default_rng(2).integers(0, 256, (7, 9, 3), dtype=np.uint8)
    path = str(tmp_path / "levels.png")
    write_image(path, levels)
    inp = oiio.ImageInput.open(path)
    stored = inp.read_image(format=oiio.UINT8)
    inp.close()
    assert np.array_equal(stored, levels), "the file holds the levels given"
    assert np.allclose(read_image(path), decode_srgb8(levels), atol=1e-6), "read back as sRGB-decoded linear"
    with pytest.raises(ImageIOError, match="8-bit format"):
        write_image(str(tmp_path / "levels.exr"), levels)
