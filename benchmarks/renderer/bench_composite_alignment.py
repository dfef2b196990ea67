"""The board rendered through a calibration of real photos against the photos' corners (examples/composite.py's
check, on more views), with OpenCV's projection of the same calibration as the peer.

    python benchmarks/renderer/bench_composite_alignment.py [--views N] [--spp S]

For each shipped set (gopro_wide, industrial_ds1): calibrate from the cached detections with the defaults and the
board held flat (the rendered board is the flat print); for N views spread over the set, render the board alone
through the view's calibrated camera on a window around each corner, measure the corners as `tiltfit detect`
does (`tiltfit.report.composite.board_alignment`) and compare them with
- the photo's detected corners (RMS), beside the calibration's own reprojection RMS of that view;
- the calibration's projection (`Calibration.project`) and OpenCV's (`cv2.projectPoints` with the same K,
  distortion coefficients and pose; these calibrations are untilted, so OpenCV's model is theirs).
Writes benchmarks/results/composite_alignment.{json,md}.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))  # benchmarks/
sys.path.insert(0, os.path.dirname(HERE))
RESULTS = os.path.join(HERE, "results")
#: The examples' pixel pitches (mm; pixel results do not depend on them).
SETS = {"gopro_wide": 0.005, "industrial_ds1": 0.00155}


def calibrate_flat(folder: str, pitch_mm: float):
    from tests.real_detections import observations
    from tiltfit.files.calib import calib_dict
    from tiltfit.files.calibrated import Calibration
    from tiltfit.calibrate.flow import calibrate
    from tiltfit.calibrate.fit import FitOptions
    from tiltfit.target.layout import load_target

    obs, _ = observations(folder, pitch_mm)
    target = load_target(os.path.join(folder, "target.json"))
    result = calibrate(obs, "unified", options=FitOptions(distortion="auto", board="flat"))
    data = calib_dict(result, obs=obs, target=target.to_dict())
    return Calibration.from_dict(data, f"{os.path.basename(folder)} (flat board)"), obs


def opencv_projection(cal, points, view) -> np.ndarray:
    import cv2

    R, T = cal.pose(view)
    coefficients = np.asarray(cal.lens.distortion if cal.lens.distortion is not None else [0.0] * 5, np.float64)
    q, _ = cv2.projectPoints(points.reshape(-1, 1, 3), cv2.Rodrigues(R)[0], T, cal.lens.K, coefficients)
    return q.reshape(-1, 2)


def rms(a, b) -> float:
    d = np.asarray(a) - np.asarray(b)
    ok = np.isfinite(d).all(1)
    return float(np.sqrt(np.mean(np.sum(d[ok] ** 2, 1))))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--views", type=int, default=3, help="views per set [3]")
    p.add_argument("--spp", type=int, default=16, help="samples per pixel [16, as the example]")
    p.add_argument("--out", default=os.path.join(RESULTS, "composite_alignment"),
                   help="output path without extension (.json and .md are written)")
    args = p.parse_args(argv)

    from tiltfit.report.composite import board_alignment

    rows = []
    for name, pitch in SETS.items():
        folder = os.path.join(HERE, "..", "data", "real", name)
        t0 = time.perf_counter()
        cal, obs = calibrate_flat(folder, pitch)
        print(f"[{name}] calibrated in {time.perf_counter() - t0:.1f} s, {len(cal.views)} views",
              file=sys.stderr, flush=True)
        if abs(cal.lens.theta_F) > 0 or cal.lens.distortion_centre != "sensor":
            print(f"[{name}] tilted or lens-axis distortion: OpenCV's projectPoints is not the peer", file=sys.stderr)
        points = cal.target.feature_points()
        picks = np.unique(np.linspace(0, len(cal.views) - 1, args.views).round().astype(int))
        for k in picks:
            image = cal.views[k]["image"]
            photo = obs.corners_px[obs.names.index(image)]
            t0 = time.perf_counter()
            a = board_alignment(cal, int(k), photo, spp=args.spp)
            seconds = time.perf_counter() - t0
            cv = opencv_projection(cal, points, int(k))
            rows.append({"set": name, "view": image, "n_corners": a.n_corners,
                         "calibration_rms_px": a.rms_reprojection_px, "rendered_vs_photo_px": a.rms_photo_px,
                         "ratio": a.rms_photo_px / a.rms_reprojection_px,
                         "rendered_vs_projection_px": a.rms_projection_px,
                         "rendered_vs_opencv_px": rms(a.rendered_px, cv),
                         "projection_vs_opencv_px": rms(a.projected_px, cv), "seconds": seconds})
            print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    summary = {name: {key: float(np.median([r[key] for r in rows if r["set"] == name]))
                      for key in ("ratio", "rendered_vs_projection_px", "rendered_vs_opencv_px",
                                  "projection_vs_opencv_px", "seconds")} for name in SETS}
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    with open(args.out + ".json", "w", encoding="utf-8") as f:
        json.dump({"spp": args.spp, "rows": rows, "median": summary}, f, indent=1)
    lines = ["# The board rendered through a calibration against the photos (examples/composite.py's check)", "",
             f"`python benchmarks/renderer/bench_composite_alignment.py --views {args.views} --spp {args.spp}`: each set "
             "calibrated from its cached detections (defaults, board flat); per view the board rendered alone "
             "through the calibrated camera, its corners measured as `tiltfit detect` does. Peer: OpenCV's "
             "`cv2.projectPoints` of the same calibration.", "",
             "| set | view | corners | calibration RMS px | rendered vs photo px | ratio | rendered vs projection px "
             "| rendered vs OpenCV px | projection vs OpenCV px | s |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['set']} | {os.path.basename(r['view'])} | {r['n_corners']} | {r['calibration_rms_px']:.3f} "
                     f"| {r['rendered_vs_photo_px']:.3f} | {r['ratio']:.3f} | {r['rendered_vs_projection_px']:.3f} "
                     f"| {r['rendered_vs_opencv_px']:.3f} | {r['projection_vs_opencv_px']:.1e} | {r['seconds']:.1f} |")
    lines += ["", "Medians per set: ratio rendered-vs-photo / calibration RMS; rendered vs projection; rendered vs "
              "OpenCV; projection vs OpenCV; seconds per view (two shared cores).", ""]
    for name, m in summary.items():
        lines.append(f"- {name}: ratio {m['ratio']:.3f}, {m['rendered_vs_projection_px']:.3f} px, "
                     f"{m['rendered_vs_opencv_px']:.3f} px, {m['projection_vs_opencv_px']:.1e} px, {m['seconds']:.1f} s")
    with open(args.out + ".md", "w", encoding="utf-8") as f:
        f.write("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
