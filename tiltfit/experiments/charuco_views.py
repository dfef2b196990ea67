"""The ChArUco views of `tests/tiltfit/test_charuco.py` and `benchmarks/detection/bench_charuco.py`: one board, one camera,
views of about a third of the board and whole views, and their constant-blur renders.

Board: 12 × 9 squares of 15 mm with 11 mm DICT_5X5_100 markers, 10 mm margin. Camera: a 25 mm lens focused at
560 mm on a 320 × 240 sensor of 0.03 mm pixels. A view is (camera position (mm, target frame), the board point
it looks at (x, y) mm or None for the board's centre, roll °).
"""
from __future__ import annotations

import numpy as np
from renderer import Lens, Sensor

from tiltfit.experiments.synth import look_at_pose, observe, plane_homography, render_constant_blur
from tiltfit.target.layout import target_from_dict

BOARD = {"type": "charuco", "units": "mm", "dictionary": "DICT_5X5_100", "squares": [12, 9], "square_mm": 15.0,
         "marker_mm": 11.0, "margin": 10.0}
TARGET = target_from_dict(BOARD)
CAMERA = Lens(25.0, 560.0, 0.0, sensor=Sensor(320, 240, 0.03))
#: Views of about a third of the board (25–34 of its 88 corners; a square about 42 px).
PARTIAL = [((60.0, 30.0, -300.0), (50.0, 40.0), -20.0), ((150.0, 120.0, -280.0), (140.0, 100.0), 15.0),
           ((160.0, 20.0, -300.0), (130.0, 35.0), 5.0), ((20.0, 130.0, -290.0), (45.0, 100.0), -8.0),
           ((100.0, 60.0, -270.0), (90.0, 70.0), 30.0), ((140.0, 90.0, -310.0), (120.0, 60.0), -35.0)]
#: Whole views (a square about 22 px).
FULL = [((40.0, -60.0, -540.0), None, 8.0), ((150.0, 120.0, -520.0), None, -10.0), ((-60.0, 40.0, -560.0), None, 20.0),
        ((90.0, 160.0, -500.0), None, -25.0)]


def pose(view):
    """(R, T_mm) camera_from_target of a view (`PARTIAL`, `FULL`)."""
    position, look, roll = view
    return look_at_pose(TARGET, position, None if look is None else (*look, 0.0), roll_deg=roll)


def square_px(corners, target=TARGET) -> float:
    """Median side of a square in the image, px, from the target's corners (n, 2) (NaN where not seen)."""
    g = corners.reshape(*target.grid_shape, 2)
    return float(np.nanmedian(np.hypot(*np.diff(g, axis=1).transpose(2, 0, 1))))


def blurred_renders(view, blurs, noise: float, rng, target=TARGET):
    """A view's constant-blur renders (`tiltfit.experiments.synth.render_constant_blur`) plus Gaussian noise from `rng`.

    Args:
        view: a view (`PARTIAL`, `FULL`); blurs: blur-disc diameters in squares; noise: σ of the noise;
        target: the board drawn (`TARGET`, or a plain checkerboard of its squares).
    Yields:
        (truth (`tiltfit.experiments.synth.observe`), square_px, blur in squares, image (H, W)), one per blur.
    """
    R, T = pose(view)
    truth = observe(target, CAMERA, R, T)
    sq = square_px(np.where(truth.in_image[:, None], truth.corners_px, np.nan), target)
    for b in blurs:
        img = render_constant_blur(target, plane_homography(CAMERA, R, T), CAMERA.sensor.size_px, b * sq)
        yield truth, sq, b, img + rng.normal(0.0, noise, img.shape)
