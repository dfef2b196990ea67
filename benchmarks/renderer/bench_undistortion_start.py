"""Where `Camera.undistort_pixels` starts Newton's method for a render's pixels (`Camera._undistortion_start`): this
tree's against f794b97's (four advanced indexings and four `isfinite` a call; kept below as the reference), in one
process, alternating, 15 repeats, one torch thread. Checks that starts and skips are bit-identical.

    python benchmarks/renderer/bench_undistortion_start.py

Cameras: the round trip's 480 x 320 lens (k1, k2; tests/tiltfit/test_calibrated_round_trip.py) and a GoPro's opencv5
calibration at 1280 x 960 (corners beyond where it can be inverted); 131,072 pixels (a render's chunk), jittered
over the image and 2 px beyond. Figures: benchmarks/results/suite_time.md, "Session 39".
"""
from __future__ import annotations

import math
import os
import statistics
import sys
import time

import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))
import renderer.cameras.base as base  # noqa: E402
from renderer import Lens, Sensor, ThinLensCamera  # noqa: E402

CAMERAS = {
    "round trip 480x320 (k1, k2)": Lens(16.0, 540.0, 8.0, 0.0, Sensor(480, 320, 0.012), (236.4, 163.2), (-0.15, 0.02)),
    "GoPro 1280x960 (opencv5)": Lens(0.8747, 1000.0, 1e-6, 0.0, Sensor(1280, 960, 0.00155), (651.5, 502.1),
                                     (-0.2453, 0.0748, -7.15e-4, 3.5e-5, -0.01146)),
}


def reference_start(cam, uv_px):
    """f794b97's `_undistortion_start` (its own map attribute, so that the two do not share one)."""
    key = (cam.distortion, cam.focal_px, cam.screen.center_px, cam.width, cam.height, uv_px.dtype, uv_px.device)
    cached = getattr(cam, "_reference_map", None)
    if cached is None or cached[0] != key:
        step = base.UNDISTORTION_MAP_STEP_PX
        nx, ny = math.ceil(cam.width / step) + 1, math.ceil(cam.height / step) + 1
        gx = torch.arange(nx, dtype=uv_px.dtype) * step - 0.5
        gy = torch.arange(ny, dtype=uv_px.dtype) * step - 0.5
        nodes = torch.stack(torch.meshgrid(gx, gy, indexing="xy"), -1)
        cached = (key, cam.distortion.undistort(cam._normalised(nodes)))
        cam._reference_map = cached
    grid = cached[1]
    ny, nx = grid.shape[:2]
    fx = ((uv_px[..., 0].detach() + 0.5) / base.UNDISTORTION_MAP_STEP_PX).clamp(0, nx - 1 - 1e-9)
    fy = ((uv_px[..., 1].detach() + 0.5) / base.UNDISTORTION_MAP_STEP_PX).clamp(0, ny - 1 - 1e-9)
    i0, j0 = fx.floor().long().clamp(max=nx - 2), fy.floor().long().clamp(max=ny - 2)
    ax, ay = (fx - i0)[..., None], (fy - j0)[..., None]
    c00, c10 = grid[j0, i0], grid[j0, i0 + 1]
    c01, c11 = grid[j0 + 1, i0], grid[j0 + 1, i0 + 1]
    start = (1 - ay) * ((1 - ax) * c00 + ax * c10) + ay * ((1 - ax) * c01 + ax * c11)
    good = torch.stack([torch.isfinite(c).all(-1) for c in (c00, c10, c01, c11)])
    return start, ~good.any(0)


def main() -> None:
    torch.set_num_threads(1)
    gen = torch.Generator().manual_seed(0)
    for name, lens in CAMERAS.items():
        cam = ThinLensCamera.from_calibration(lens, torch.eye(3, dtype=torch.float64),
                                              torch.tensor([0.0, 0.0, 500.0], dtype=torch.float64))
        W, H = lens.sensor.width_px, lens.sensor.height_px
        uv = torch.rand(131072, 2, generator=gen, dtype=torch.float64) * torch.tensor([W + 4.0, H + 4.0]) - 2.0
        (s0, k0), (s1, k1) = reference_start(cam, uv), cam._undistortion_start(uv)
        same = torch.equal(k0, k1) and torch.equal(torch.isnan(s0), torch.isnan(s1)) and \
            torch.equal(torch.nan_to_num(s0), torch.nan_to_num(s1))
        before, after = [], []
        for _ in range(15):
            t = time.process_time(); reference_start(cam, uv); before.append(time.process_time() - t)
            t = time.process_time(); cam._undistortion_start(uv); after.append(time.process_time() - t)
        b, a = statistics.median(before), statistics.median(after)
        print(f"{name}: starts and skips bit-identical: {same}; {int(k1.sum())} skipped; median CPU "
              f"{1e3 * b:.1f} -> {1e3 * a:.1f} ms ({a / b:.2f}x)")


if __name__ == "__main__":
    main()
