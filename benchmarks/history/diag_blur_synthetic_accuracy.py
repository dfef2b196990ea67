"""Blur widths on synthetic views of known blur, for comparing two checkouts (issue 32 §1: the widths made smooth in
the corners must stay as accurate): per view, the median and largest error of `measure_blur` against the true
diameters and the RMS of error / σ. The views are test_blur.py's (the paper camera binned 12×, blur 0.05–0.4 of a
square, noise 0.002–0.01, sRGB 8-bit) with three seeds each, and the view across the plane of focus.

Run from the checkout measured (`tiltfit` is imported from the current directory):
    cd /tmp/old && python /work/main/benchmarks/history/diag_blur_synthetic_accuracy.py
"""
import os
import sys

sys.path.insert(0, os.getcwd())  # the checkout measured
import numpy as np  # noqa: E402
import torch  # noqa: E402

from tiltfit.detect.blur import measure_blur  # noqa: E402
from tiltfit.experiments.synth import PAPER_CAMERA, look_at_pose, render_view, with_blur_ratio  # noqa: E402
from tiltfit.target.design import design_target  # noqa: E402

torch.set_num_threads(1)
CAM = PAPER_CAMERA.binned(12)
TARGET = design_target(9, 6, 20.0, w_mm=55.39, distance_mm=650.0, inclination_deg=20.0)
POSE = look_at_pose(TARGET, (40.0, -30.0, -650.0), roll_deg=10.0)
out = []
for ratio, noise in [(0.05, 0.002), (0.15, 0.002), (0.4, 0.002), (0.15, 0.01), (0.4, 0.01), (0.1, 0.004)]:
    for seed in (1, 5, 9):
        cam = with_blur_ratio(CAM, TARGET, *POSE, ratio, U_mm=400.0)
        v = render_view(TARGET, cam, *POSE, noise_sigma=noise, srgb8=True, seed=seed)
        b, s = measure_blur(v.image[..., 0], TARGET, v.truth.corners_px)
        e = b - v.truth.blur_px
        out.append((ratio, noise, seed, np.median(v.truth.blur_px), np.median(e), np.max(np.abs(e)), np.sqrt(np.mean((e / s) ** 2))))
R, T = look_at_pose(TARGET, (60.0, -400.0, -450.0), roll_deg=8.0)
v = render_view(TARGET, CAM.with_(d=50.0), R, T, noise_sigma=0.004, srgb8=True, seed=2)
b, s = measure_blur(v.image[..., 0], TARGET, v.truth.corners_px); e = b - v.truth.blur_px
out.append(("focus", 0.004, 2, np.median(v.truth.blur_px), np.median(e), np.max(np.abs(e)), np.sqrt(np.mean((e / s) ** 2))))
for r in out:
    print("ratio %s noise %s seed %s truth %.2f | median err %+.4f max |err| %.3f RMS z %.2f" % r)
a = np.array([r[4:] for r in out], float)
print("ALL: mean |median err| %.4f, mean max|err| %.3f, median RMS z %.2f" % (np.mean(np.abs(a[:, 0])), np.mean(a[:, 1]), np.median(a[:, 2])))
