"""ChArUco corners on a real webcam video of a white-on-black board against the published detections and
OpenCV's CharucoDetector on the same frames; and the same video mirrored (every frame must be refused).

Data: /work/shared/data/real/charuco_webcam (caliscope, BSD-2): cam_0.mp4, 48 frames 1280 × 720, a 4 × 5 board of
54 mm squares, 40.5 mm DICT_4X4_1000 markers, printed inverted; `published_corners_cam0.csv` is caliscope's own
detections (OpenCV ChArUco ids), a second detector, not ground truth.

Ours: `tiltfit.detect.charuco.detect_board` with the target's `"inverted": true`. Peer, measured in the same run on the
same frames: `cv2.aruco.CharucoDetector(board).detectBoard` on the inverted 8-bit grey frame (its default
refinement). A corner farther than 2 px from the published corner of its id counts as a wrong id.

Writes benchmarks/results/charuco_webcam.{json,md}. Usage: python benchmarks/detection/bench_charuco_webcam.py [--every K]
"""
from __future__ import annotations

import argparse
import collections
import csv
import json
import os
import statistics
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))

DATA = "/work/shared/data/real/charuco_webcam"
OUT = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "benchmarks", "results", "charuco_webcam")
WRONG_ID_PX = 2.0


def frames():
    import cv2

    cap = cv2.VideoCapture(os.path.join(DATA, "cam_0.mp4"))
    while True:
        ok, f = cap.read()
        if not ok:
            return
        yield cv2.cvtColor(f, cv2.COLOR_BGR2GRAY)


def published():
    out = collections.defaultdict(dict)
    with open(os.path.join(DATA, "published_corners_cam0.csv")) as f:
        for r in csv.DictReader(f):
            out[int(r["frame_index"])][int(r["keypoint_id"])] = np.array([float(r["img_loc_x"]), float(r["img_loc_y"])])
    return out


def agreement(corners: np.ndarray, reference: dict) -> list[float]:
    """Distances, px, from each corner found in both to the reference corner of the same id."""
    return [float(np.hypot(*(corners[k] - xy))) for k, xy in reference.items() if np.isfinite(corners[k]).all()]


def summary(d: list[float], n_ref: int, n_found: int) -> dict:
    return {"n_compared": len(d), "n_reference": n_ref, "n_found": n_found,
            "median_px": statistics.median(d) if d else None, "p90_px": float(np.percentile(d, 90)) if d else None,
            "wrong_ids": int(sum(e > WRONG_ID_PX for e in d))}


def main(argv=None) -> int:
    import cv2

    from camio.files import srgb_to_linear
    from tiltfit.detect.charuco import detect_board
    from tiltfit.target.layout import target_from_dict

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--every", type=int, default=1, help="use every K-th frame")
    args = ap.parse_args(argv)
    target = target_from_dict({"type": "charuco", "dictionary": "DICT_4X4_1000", "squares": [4, 5], "square_mm": 54,
                               "marker_mm": 40.5, "inverted": True}, "charuco_webcam")
    peer = cv2.aruco.CharucoDetector(target.opencv_board())
    ref = published()
    ours_d, cv_d, ours_cv_d = [], [], []
    n = dict(ref=0, ours=0, cv=0, frames=0, mirrored_labelled=0, mirrored_frames=0)
    t_ours, t_cv, per_frame = [], [], []
    for fi, g8 in enumerate(frames()):
        if fi % args.every:
            continue
        n["frames"] += 1
        linear = srgb_to_linear(g8.astype(np.float32) / 255.0)
        t0 = time.perf_counter()
        det = detect_board(linear, target, measure_blur=False)
        t_ours.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        cc, ids, _, _ = peer.detectBoard(255 - g8)
        t_cv.append(time.perf_counter() - t0)
        cv_corners = np.full((target.n_points, 2), np.nan)
        if ids is not None and len(ids):
            cv_corners[ids.ravel()] = cc.reshape(-1, 2)
        ours = det.corners_px if det.grid_found else np.full((target.n_points, 2), np.nan)
        d_o, d_c = agreement(ours, ref[fi]), agreement(cv_corners, ref[fi])
        cv_ref = {k: cv_corners[k] for k in range(target.n_points) if np.isfinite(cv_corners[k]).all()}
        ours_d += d_o
        cv_d += d_c
        ours_cv_d += agreement(ours, cv_ref)
        n["ref"] += len(ref[fi])
        n["ours"] += int(np.isfinite(ours).all(1).sum())
        n["cv"] += int(np.isfinite(cv_corners).all(1).sum())
        per_frame.append({"frame": fi, "published": len(ref[fi]), "ours": int(np.isfinite(ours).all(1).sum()),
                          "opencv": int(np.isfinite(cv_corners).all(1).sum()),
                          "ours_median_px": statistics.median(d_o) if d_o else None,
                          "opencv_median_px": statistics.median(d_c) if d_c else None})
        # the mirrored stream: every frame flipped left-right must be refused, not labelled
        mirror = detect_board(np.ascontiguousarray(linear[:, ::-1]), target, measure_blur=False)
        n["mirrored_frames"] += 1
        n["mirrored_labelled"] += int(mirror.grid_found and mirror.found.any())
        print(f"frame {fi}: ours {per_frame[-1]['ours']}, OpenCV {per_frame[-1]['opencv']}, published "
              f"{len(ref[fi])}; mirrored: {'LABELLED' if mirror.grid_found else mirror.message[:60]}", flush=True)
    result = {
        "data": DATA, "frames": n["frames"], "wrong_id_px": WRONG_ID_PX,
        "ours_vs_published": summary(ours_d, n["ref"], n["ours"]),
        "opencv_vs_published": summary(cv_d, n["ref"], n["cv"]),
        "ours_vs_opencv": summary(ours_cv_d, n["cv"], n["ours"]),
        "median_s": {"ours": statistics.median(t_ours), "opencv": statistics.median(t_cv),
                     "ratio": statistics.median(t_ours) / statistics.median(t_cv)},
        "mirrored": {"frames": n["mirrored_frames"], "labelled": n["mirrored_labelled"]},
        "per_frame": per_frame,
    }
    os.makedirs(os.path.dirname(OUT), exist_ok=True)
    with open(OUT + ".json", "w") as f:
        json.dump(result, f, indent=1)
    rows = [("ours vs published", result["ours_vs_published"]), ("OpenCV vs published", result["opencv_vs_published"]),
            ("ours vs OpenCV", result["ours_vs_opencv"])]
    md = ["# ChArUco corners on the inverted-print webcam video (charuco_webcam)", "",
          f"`python benchmarks/detection/bench_charuco_webcam.py`: {n['frames']} frames; a corner more than {WRONG_ID_PX:g} px "
          "from the reference corner of its id is a wrong id.", "",
          "| comparison | corners compared | found / reference | median px | 90th pct px | wrong ids |", "|---|---|---|---|---|---|"]
    for name, s in rows:
        md.append(f"| {name} | {s['n_compared']} | {s['n_found']} / {s['n_reference']} | {s['median_px']:.3f} | "
                  f"{s['p90_px']:.3f} | {s['wrong_ids']} |")
    t = result["median_s"]
    md += ["", f"Median time a frame: ours {t['ours']:.2f} s, OpenCV {t['opencv']:.3f} s (ratio {t['ratio']:.0f}; ours "
           "includes the lattice placement and the point-symmetry refinement).", "",
           f"Mirrored stream (every frame flipped left-right): {n['mirrored_labelled']} of {n['mirrored_frames']} frames "
           "labelled (each should be refused as a mirror image).", ""]
    with open(OUT + ".md", "w") as f:
        f.write("\n".join(md))
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    sys.exit(main())
