"""Detection time against OpenCV at every image size and target type, and where the time goes (issue 32 §1).

Image kinds (3 images each; real photos, decoded to linear by camio.files for ours, 8-bit grey for OpenCV):
- `chess_640x480`: sony_small (/work/shared/data/real/sony_small, 4 × 6 corners), the first three photos;
- `chess_1280x720`: gopro_wide photos (1280 × 960, 8 × 6 corners) cropped to 1280 × 720 rows around the
  board (no 1280 × 720 chessboard photo is shipped: the crop is a real photo at that size, the board whole);
- `chess_1280x960`: gopro_wide, the first three photos whole;
- `chess_1280x1024`: industrial_ds1 (16 × 10 corners), the first three photos;
- `charuco_1280x720`: charuco_webcam frames 0, 16 and 32 (cam_0.mp4, 4 × 5 squares, 12 corners, inverted print).

Methods, each timed in the same run on the same image (median CPU time of `--repeats` calls, one thread each;
decoding excluded):
- `ours`: corners alone (`tiltfit.detect.chessboard.detect` / `tiltfit.detect.charuco.detect_board` with
  measure_blur=False), what OpenCV measures;
- `ours_widths`: corners and blur widths, what `tiltfit detect` does by default;
- `opencv`: cv2.findChessboardCornersSB (NORMALIZE_IMAGE | EXHAUSTIVE | ACCURACY) + cornerSubPix 5 × 5
  (`tiltfit.detect.opencv.sb_corners`, the repository's peer), and `opencv_plain` (findChessboardCornersSB
  with no flags, its fastest use); for ChArUco cv2.aruco.CharucoDetector.detectBoard (detector built once).
Where the time goes: the stage timings our Detection records (`timings`), medians over the kind's images,
split into costs per image (pyramid, saddle maps and grid growth, OpenCV's marker reading, lattice search)
and costs that grow with the corners (refinement, indexing, completion, blur widths), with the time per corner.
Corner accuracy: median distance from our corners to OpenCV's on the same image (labelling matched), and for
the ChArUco frames to the published corners (caliscope's detections) of the same ids.

Run from a checkout (the `tiltfit` imported is the one on sys.path first, so a clean clone of an older commit
can be measured with the same script: `cd /tmp/det_before && python /work/main/benchmarks/detection/bench_detect_speed.py
--out /work/main/benchmarks/results/detect_speed_before`).

Writes benchmarks/results/detect_speed.{json,md}. Usage:
    python benchmarks/detection/bench_detect_speed.py [--repeats 3] [--images 3] [--kinds all|KIND,...] [--out STEM]
(`--kinds charuco_1280x720`: that kind alone, e.g. with `--out benchmarks/results/detect_speed_charuco`).
"""
from __future__ import annotations

import csv
import collections
import glob
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

SHARED = "/work/shared/data/real"
PER_IMAGE = ("pyramid", "grid", "opencv", "lattice")
PER_CORNER = ("refine", "index", "complete", "blur", "model")


def _chess_kinds(n_images):
    import cv2

    from camio.files import read_image
    from tiltfit.target.layout import load_target

    sets = [("chess_640x480", sorted(glob.glob(f"{SHARED}/sony_small/*.jpg")),
             os.path.join(HERE, "benchmarks", "small_sets", "sony_small", "target.json"), None),
            ("chess_1280x720", sorted(glob.glob(os.path.join(HERE, "data/real/gopro_wide/*.jpg"))),
             os.path.join(HERE, "data/real/gopro_wide/target.json"), 720),
            ("chess_1280x960", sorted(glob.glob(os.path.join(HERE, "data/real/gopro_wide/*.jpg"))),
             os.path.join(HERE, "data/real/gopro_wide/target.json"), None),
            ("chess_1280x1024", sorted(glob.glob(os.path.join(HERE, "data/real/industrial_ds1/*.png"))),
             os.path.join(HERE, "data/real/industrial_ds1/target.json"), None)]
    from tiltfit.detect.opencv import sb_corners

    for name, paths, target_path, rows in sets:
        target = load_target(target_path)
        ny, nx = target.grid_shape
        images = []
        for p in paths:
            linear, g8 = read_image(p), cv2.imread(p, cv2.IMREAD_GRAYSCALE)
            if rows is not None:  # crop to `rows` rows around the board OpenCV finds, the board whole
                c = sb_corners(g8, (nx, ny))
                if c is None:
                    continue
                y0 = int(np.clip(round(c[:, 1].mean() - rows / 2), 0, g8.shape[0] - rows))
                if c[:, 1].min() < y0 + 20 or c[:, 1].max() > y0 + rows - 20:
                    continue
                linear, g8 = linear[y0:y0 + rows], g8[y0:y0 + rows]
            images.append((os.path.basename(p), np.ascontiguousarray(linear), np.ascontiguousarray(g8)))
            if len(images) == n_images:
                break
        yield name, target, images


def _charuco_kind(n_images):
    import cv2

    from camio.files import srgb_to_linear
    from tiltfit.target.layout import target_from_dict

    target = target_from_dict({"type": "charuco", "dictionary": "DICT_4X4_1000", "squares": [4, 5], "square_mm": 54,
                               "marker_mm": 40.5, "inverted": True}, "charuco_webcam")
    wanted = [16 * k for k in range(n_images)]
    cap = cv2.VideoCapture(os.path.join(SHARED, "charuco_webcam", "cam_0.mp4"))
    images, fi = [], 0
    while len(images) < n_images:
        ok, f = cap.read()
        if not ok:
            break
        if fi in wanted:
            g8 = cv2.cvtColor(f, cv2.COLOR_BGR2GRAY)
            images.append((f"frame{fi}", srgb_to_linear(g8.astype(np.float32) / 255.0), g8))
        fi += 1
    return "charuco_1280x720", target, images


def _published():
    out = collections.defaultdict(dict)
    with open(os.path.join(SHARED, "charuco_webcam", "published_corners_cam0.csv")) as f:
        for r in csv.DictReader(f):
            out[f"frame{int(r['frame_index'])}"][int(r["keypoint_id"])] = (float(r["img_loc_x"]), float(r["img_loc_y"]))
    return out


def _timed(fn, repeats):
    """(fn's result, median CPU time of `repeats` calls, s): CPU time, not wall, so that other jobs on a shared
    machine do not inflate it (every method runs on one thread)."""
    out, cpu = None, []
    for _ in range(repeats):
        t0 = time.process_time()
        out = fn()
        cpu.append(time.process_time() - t0)
    return out, statistics.median(cpu)


def _stages(timings: dict) -> dict:
    """Our stage timings, s, gathered into named stages (grid@f for every pyramid level tried → grid)."""
    out = collections.Counter()
    for k, v in timings.items():
        if k == "total":
            continue
        out["grid" if k.startswith("grid@") else k] += v
    return dict(out)


def _measure_kind(name, target, images, repeats, published):
    import cv2

    from tiltfit.detect.charuco import detect_board
    from tiltfit.detect.opencv import match_labelling, sb_corners

    charuco = name.startswith("charuco")
    ny, nx = target.grid_shape
    if charuco:
        peer = cv2.aruco.CharucoDetector(target.opencv_board())

        def opencv(g8):
            cc, ids, _, _ = peer.detectBoard(255 - g8)
            c = np.full((target.n_points, 2), np.nan)
            if ids is not None and len(ids):
                c[ids.ravel()] = cc.reshape(-1, 2)
            return c
    else:
        def opencv(g8):
            return sb_corners(g8, (nx, ny))

        def opencv_plain(g8):
            ok, c = cv2.findChessboardCornersSB(g8, (nx, ny))
            return c if ok else None
    rows = []
    for image, linear, g8 in images:
        det, t_ours = _timed(lambda: detect_board(linear, target, measure_blur=False), repeats)
        det_w, t_widths = _timed(lambda: detect_board(linear, target, measure_blur=True), repeats)
        peer_c, t_cv = _timed(lambda: opencv(g8), repeats)
        row = {"image": image, "shape": list(g8.shape), "corners": int(det.found.sum()),
               "widths": int(np.isfinite(det_w.blur_px).sum()), "ours_s": t_ours, "ours_widths_s": t_widths,
               "opencv_s": t_cv, "stages_s": _stages(det_w.timings_s), "stages_corners_s": _stages(det.timings_s)}
        if not charuco:
            row["opencv_plain_s"] = _timed(lambda: opencv_plain(g8), repeats)[1]
        b = det_w.blur_px[np.isfinite(det_w.blur_px)]
        if b.size:
            row["blur_px_median"] = float(np.median(b))
            row["blur_px_max"] = float(b.max())
        if det.grid_found and peer_c is not None:
            ok = np.isfinite(peer_c).all(1) & det.found
            if charuco:
                e = np.hypot(*(det.corners_px[ok] - peer_c[ok]).T)
            else:
                e = match_labelling(det.corners_px, peer_c)[0]
                e = e[np.isfinite(e)]
            row["vs_opencv_median_px"] = float(np.median(e)) if e.size else None
            row["vs_opencv_n"] = int(e.size)
        if charuco:
            ref = published.get(image, {})
            d = [float(np.hypot(*(det.corners_px[k] - np.array(xy)))) for k, xy in ref.items() if det.found[k]]
            dc = [float(np.hypot(*(peer_c[k] - np.array(xy)))) for k, xy in ref.items()
                  if np.isfinite(peer_c[k]).all()]
            row["vs_published_median_px"] = float(np.median(d)) if d else None
            row["opencv_vs_published_median_px"] = float(np.median(dc)) if dc else None
            row["published"] = len(ref)
        print(f"{name} {image}: ours {t_ours:.3f} s ({row['corners']} corners), with widths {t_widths:.3f} s, "
              f"OpenCV {t_cv:.3f} s", flush=True)
        rows.append(row)
    return _summarise(name, rows)


def _median(values):
    v = [x for x in values if x is not None]
    return statistics.median(v) if v else None


def _summarise(name, rows):
    t = {k: _median(r.get(k) for r in rows) for k in ("ours_s", "ours_widths_s", "opencv_s", "opencv_plain_s")}
    stages = collections.defaultdict(list)
    for r in rows:
        for k, v in r["stages_s"].items():
            stages[k].append(v)
    stage_med = {k: statistics.median(v + [0.0] * (len(rows) - len(v))) for k, v in stages.items()}
    corners = _median(r["corners"] for r in rows) or 0
    per_image = sum(v for k, v in stage_med.items() if k in PER_IMAGE)
    per_corner = sum(v for k, v in stage_med.items() if k in PER_CORNER)
    return {"kind": name, "images": len(rows), "shape": rows[0]["shape"] if rows else None, "corners_median": corners,
            "time_median_s": t,
            "ratio_ours_over_opencv": t["ours_s"] / t["opencv_s"] if rows else None,
            "ratio_widths_over_opencv": t["ours_widths_s"] / t["opencv_s"] if rows else None,
            "ratio_ours_over_opencv_plain": (t["ours_s"] / t["opencv_plain_s"]) if t["opencv_plain_s"] else None,
            "stages_median_s": stage_med, "per_image_s": per_image, "per_corner_stages_s": per_corner,
            "per_corner_s": per_corner / corners if corners else None,
            "vs_opencv_median_px": _median(r.get("vs_opencv_median_px") for r in rows),
            "vs_published_median_px": _median(r.get("vs_published_median_px") for r in rows),
            "opencv_vs_published_median_px": _median(r.get("opencv_vs_published_median_px") for r in rows),
            "blur_px_median": _median(r.get("blur_px_median") for r in rows),
            "rows": rows}


def measure(args):
    import cv2
    import torch

    import tiltfit

    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    published = _published()
    kinds = list(_chess_kinds(args.images))
    kinds.insert(2, _charuco_kind(args.images))
    if args.kinds != "all":
        kinds = [k for k in kinds if k[0] in args.kinds.split(",")]
    from tiltfit.detect.charuco import detect_board

    for _, target, images in kinds[:3]:  # first calls (imports, kernels, dictionaries) are not what is measured
        detect_board(images[0][1], target)
    out = [_measure_kind(n, t, ims, args.repeats, published) for n, t, ims in kinds]
    return {"kinds": out, "repeats": args.repeats, "tiltfit": os.path.dirname(tiltfit.__file__),
            "machine": {"platform": platform.platform(), "python": platform.python_version(),
                        "torch": torch.__version__, "opencv": cv2.__version__, "threads": 1,
                        "cpu_count": os.cpu_count()}}


def _f(x, fmt="{:.3f}"):
    return "–" if x is None else fmt.format(x)


def write_markdown(path, res):
    lines = ["# Detection time against OpenCV, by image kind", "",
             f"`python benchmarks/detection/bench_detect_speed.py` (tiltfit from `{res['tiltfit']}`; one thread each; time = "
             f"CPU time, median over the kind's images of the median of {res['repeats']} runs; decoding excluded). OpenCV: "
             "findChessboardCornersSB (normalised, exhaustive, accurate) + cornerSubPix for chessboards (`plain`: SB "
             "without flags), CharucoDetector.detectBoard for ChArUco.", "",
             "| kind | images | corners | ours, corners | ours, corners + widths | OpenCV | OpenCV plain | "
             "corners / OpenCV | + widths / OpenCV | corners / plain |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for k in res["kinds"]:
        t = k["time_median_s"]
        lines.append(f"| {k['kind']} | {k['images']} | {k['corners_median']} | {_f(t['ours_s'])} s | "
                     f"{_f(t['ours_widths_s'])} s | {_f(t['opencv_s'])} s | {_f(t['opencv_plain_s'])} s | "
                     f"{_f(k['ratio_ours_over_opencv'], '{:.2f}')} | {_f(k['ratio_widths_over_opencv'], '{:.2f}')} | "
                     f"{_f(k['ratio_ours_over_opencv_plain'], '{:.2f}')} |")
    lines += ["", "Where the time goes (corners + widths; the detector's own stage timings, wall clock, medians, s: "
              "inflated on a loaded machine, their shares are what to read): per image = pyramid, saddle maps and grid "
              "growth, OpenCV's marker reading, lattice search; per corner = refinement, indexing, completion, blur "
              "widths, ChArUco model fit.", "",
              "| kind | per image | per-corner stages | per corner | stages |", "|---|---|---|---|---|"]
    for k in res["kinds"]:
        st = ", ".join(f"{a} {v:.3f}" for a, v in sorted(k["stages_median_s"].items(), key=lambda kv: -kv[1]))
        lines.append(f"| {k['kind']} | {_f(k['per_image_s'])} | {_f(k['per_corner_stages_s'])} | "
                     f"{_f(k['per_corner_s'], '{:.4f}')} | {st} |")
    lines += ["", "Corner accuracy (median distance, px): ours to OpenCV on the same images; ChArUco also to the "
              "published corners (caliscope's detections, a second detector, not ground truth).", "",
              "| kind | ours vs OpenCV | ours vs published | OpenCV vs published | median blur width |",
              "|---|---|---|---|---|"]
    for k in res["kinds"]:
        lines.append(f"| {k['kind']} | {_f(k['vs_opencv_median_px'], '{:.4f}')} | "
                     f"{_f(k['vs_published_median_px'], '{:.4f}')} | "
                     f"{_f(k['opencv_vs_published_median_px'], '{:.4f}')} | {_f(k['blur_px_median'], '{:.2f}')} px |")
    write_lines(path, lines + [""])


if __name__ == "__main__":
    sys.exit(run_benchmark(__doc__, "detect_speed", measure, write_markdown, repeats=3, images=3, kinds="all"))
