"""ChArUco corners against OpenCV on every frame of the webcam video (issue 32 §1): per-frame CPU time ratios.

`bench_detect_speed.py` times three frames (0, 16, 32); OpenCV's time moves up to 1.5× between runs and our time
depends on how many corners OpenCV's marker read names (1 refinement where it names all 12, 3 where the completion
adds some, ~20 where the lattice is searched), so this one times all 48 frames of cam_0.mp4 (1280 × 720), each
frame's ours and OpenCV's runs alternating: `tiltfit.detect.charuco.detect_board(measure_blur=False)` (corners
alone) and `cv2.aruco.CharucoDetector.detectBoard` (detector built once), one thread each, CPU time, the median of
`--repeats` runs each. Reports each frame's ratio and their median (what a user calibrating from a video waits,
frame by frame), and the mean times.

Run from a checkout (the `tiltfit` imported is the one in the current directory), e.g. alternately in a checkout of
an older commit and this one:
    python benchmarks/detection/bench_charuco_frames.py [--repeats 3] [--out STEM]
Writes benchmarks/results/charuco_frames.{json,md}.
"""
from __future__ import annotations

import os
import platform
import statistics
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # the repository root
sys.path.insert(0, os.getcwd())  # the checkout measured
sys.path.insert(1, HERE)

from benchmarks.results_io import run_benchmark, write_lines  # noqa: E402

VIDEO = "/work/shared/data/real/charuco_webcam/cam_0.mp4"
TARGET = {"type": "charuco", "dictionary": "DICT_4X4_1000", "squares": [4, 5], "square_mm": 54, "marker_mm": 40.5,
          "inverted": True}


def _cpu(fn):
    t = time.process_time()
    fn()
    return time.process_time() - t


def measure(args):
    import cv2
    import torch

    import tiltfit
    from camio.files import srgb_to_linear
    from tiltfit.detect.charuco import detect_board
    from tiltfit.target.layout import target_from_dict

    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    target = target_from_dict(TARGET, "charuco_webcam")
    peer = cv2.aruco.CharucoDetector(target.opencv_board())
    cap, frames = cv2.VideoCapture(VIDEO), []
    while True:
        ok, bgr = cap.read()
        if not ok:
            break
        g8 = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
        frames.append((g8, srgb_to_linear(g8.astype(np.float32) / 255.0)))
    detect_board(frames[0][1], target, measure_blur=False)  # first call: imports, kernels, dictionaries
    rows = []
    for i, (g8, linear) in enumerate(frames):
        ours, cv = [], []
        for _ in range(args.repeats):
            ours.append(_cpu(lambda: detect_board(linear, target, measure_blur=False)))
            cv.append(_cpu(lambda: peer.detectBoard(255 - g8)))
        det = detect_board(linear, target, measure_blur=False)
        rows.append({"frame": i, "ours_s": statistics.median(ours), "opencv_s": statistics.median(cv),
                     "corners": int(det.found.sum())})
        rows[-1]["ratio"] = rows[-1]["ours_s"] / rows[-1]["opencv_s"]
        print(f"frame{i}: ours {rows[-1]['ours_s']:.3f} s, OpenCV {rows[-1]['opencv_s']:.3f} s", flush=True)
    return {"rows": rows, "repeats": args.repeats, "tiltfit": os.path.dirname(tiltfit.__file__),
            "median_ratio": statistics.median(r["ratio"] for r in rows),
            "mean_ours_s": statistics.mean(r["ours_s"] for r in rows),
            "mean_opencv_s": statistics.mean(r["opencv_s"] for r in rows),
            "machine": {"platform": platform.platform(), "python": platform.python_version(),
                        "torch": torch.__version__, "opencv": cv2.__version__, "threads": 1}}


def write_markdown(path, res):
    rows = res["rows"]
    lines = ["# ChArUco corners against CharucoDetector on every webcam frame", "",
             f"`python benchmarks/detection/bench_charuco_frames.py` (tiltfit from `{res['tiltfit']}`; one thread each; "
             f"CPU time, the median of {res['repeats']} runs a frame, ours and OpenCV's alternating). 1280 × 720 frames "
             "of cam_0.mp4; ours: corners alone.", "",
             f"Median of the {len(rows)} frames' ratios: **{res['median_ratio']:.2f}**; mean time a frame: ours "
             f"{res['mean_ours_s']:.3f} s, OpenCV {res['mean_opencv_s']:.3f} s.", "",
             "| frame | corners | ours | OpenCV | ours / OpenCV |", "|---|---|---|---|---|"]
    lines += [f"| {r['frame']} | {r['corners']} | {r['ours_s']:.3f} s | {r['opencv_s']:.3f} s | {r['ratio']:.2f} |"
              for r in rows]
    write_lines(path, lines + [""])


if __name__ == "__main__":
    sys.exit(run_benchmark(__doc__, "charuco_frames", measure, write_markdown, repeats=3))
