"""renderer.cameras.base: the map of the inverse distortion where `Camera.undistort_pixels` starts Newton's method
for a render's many pixels (`_undistortion_start`), on a strongly distorted wide-angle camera whose image corners
lie beyond where the distortion can be inverted (a GoPro's calibration, scaled to 640 x 480)."""
import torch

from renderer import Lens, Sensor, ThinLensCamera
from renderer.cameras.base import UNDISTORTION_MAP_MIN_POINTS
from renderer.cameras.distortion import undistort

#: A HERO4's opencv5 distortion as calibrated from data/real/gopro_wide (k1, k2, p1, p2, k3).
GOPRO = (-0.2453, 0.0748, -7.15e-4, 3.5e-5, -0.01146)
W, H = 640, 480


def _camera():
    lens = Lens(0.8747, 1000.0, 1e-6, 0.0, Sensor(W, H, 0.0031), (325.7, 251.1), GOPRO)
    return ThinLensCamera.from_calibration(lens, torch.eye(3, dtype=torch.float64),
                                           torch.tensor([0.0, 0.0, 500.0], dtype=torch.float64))


def _pixels(n=20000):
    """Jittered pixels over the image and 2 px beyond its edges."""
    u = torch.rand(n, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    return u * torch.tensor([W + 4.0, H + 4.0], dtype=torch.float64) - 2.0


def test_the_map_starts_near_the_root_and_changes_no_pixel():
    """Started from the map, the ideal positions are those Newton's method reaches from the distorted pixel itself
    (1e-9 px) and the same pixels are valid, but for a few skipped at the edge of the invertible region (all four
    of their nodes without an inverse: 2 of 20,000 here, as since the map came); the start is within a small
    fraction of a pixel of the root for most pixels where it is a number (median 0.045, 90 % within 0.15 px; up to
    10 px next to the fold, where Newton's steps take over)."""
    cam, uv = _camera(), _pixels()
    assert len(uv) >= UNDISTORTION_MAP_MIN_POINTS, "enough pixels for the map"
    ideal, ok = cam.undistort_pixels(uv)
    plain = undistort(cam._normalised(uv), GOPRO)        # no start: Newton from the distorted point
    ok_plain = torch.isfinite(plain).all(-1)
    assert 0.02 < float((~ok).float().mean()) < 0.5, "the corners beyond the inverse are in the test"
    err = (ideal - cam._from_normalised(plain))[ok].abs().max()
    assert float(err) < 1e-9, f"ideal pixels moved by {float(err):.2g} px"

    start, skip = cam._undistortion_start(uv)
    assert not bool((ok & ~ok_plain).any()), "a pixel without an inverse came out valid"
    lost = ok_plain & ~ok
    assert bool(skip[lost].all()) and int(lost.sum()) <= 5, f"{int(lost.sum())} pixels with an inverse lost"
    started = torch.isfinite(start).all(-1)
    assert bool(skip.any()) and bool((~started & ~skip).any()), "both kinds of start-less pixels are in the test"
    off = (cam._from_normalised(start) - ideal)[started & ok].norm(dim=-1)
    median, q90 = (float(off.quantile(q)) for q in (0.5, 0.9))
    assert median < 0.1 and q90 < 0.5, f"the interpolated start is {median:.3g} px (90 %: {q90:.3g}) from the root"
