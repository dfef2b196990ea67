"""Calibration with one bad (low-contrast) view against the same without it (issue 33 §3), OpenCV's
calibrateCamera on the same corners in the same run.

    python benchmarks/robustness/bench_bad_view.py [--set industrial_ds1] [--good 3 | --views 0,5,10] [--contrast 0.003]
                                        [--bits 16|8]

Three good photos of a shipped real set (tiltfit's cached detections) and a fourth photo made from another photo of
the set with its contrast scaled to `--contrast` about mid-grey (`--bits 16`: a linear PNG; `--bits 8`: an 8-bit PNG,
where 0.3 % is under one grey level: the corners survive, the blur widths come out near 0 px or random, the case of
issue 33 §3(a)). tiltfit is also run with the screen of disagreeing blur widths off (`tiltfit.calibrate.blur_views`, the
behaviour before it) in the same run. Each case is calibrated with tiltfit's
defaults (`calibrate`, unified, distortion k1, flat board) and with `cv2.calibrateCamera` (k1 only, square pixels)
on the same corners; focal length, principal point, RMS per corner and time. Writes
benchmarks/results/bad_view.json and .md (medians over `--repeats` runs for the times).
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time

import cv2
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from tests.real_detections import REAL, observations, photos  # noqa: E402
from benchmarks.results_io import add_output_options, save  # noqa: E402

PITCH = {"industrial_ds1": 0.0048, "gopro_wide": 0.005}


def low_contrast_view(folder: str, photo: str, contrast: float, target, bits: int = 16):
    """The DET dict of `photo` with its contrast scaled by `contrast` about mid-grey (`bits`-bit PNG)."""
    from tiltfit.cli.detect import detect_image

    grey = cv2.imread(photo, cv2.IMREAD_GRAYSCALE).astype(np.float64) / 255.0
    low = 0.5 + (grey - 0.5) * contrast
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "low_" + os.path.splitext(os.path.basename(photo))[0] + ".png")
        top, dtype = (65535, np.uint16) if bits == 16 else (255, np.uint8)
        cv2.imwrite(path, np.round(low * top).astype(dtype))
        return detect_image(path, target, None)


def calibrate_case(obs, repeats: int, screen: bool = True):
    from tiltfit.calibrate import blur_views
    from tiltfit.calibrate.flow import calibrate
    from tiltfit.calibrate.fit import FitError, FitOptions
    from tiltfit.detect.opencv import opencv_calibrate

    out = {}
    times, result = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        needs = blur_views.needs_screening
        if not screen:
            blur_views.needs_screening = lambda *a: False
        try:
            result = calibrate(obs, "unified", options=FitOptions(distortion="k1", board="flat"))
            err = None
        except FitError as e:
            err = str(e)
        finally:
            blur_views.needs_screening = needs
        times.append(time.perf_counter() - t0)
    if err:
        out["tiltfit"] = {"error": err, "time_s": float(np.median(times))}
    else:
        v = result.values
        out["tiltfit"] = {"focal_px": v["w_mm"] / obs.pixel_pitch_mm, "cx": v["principal_point_px"][0],
                          "cy": v["principal_point_px"][1],
                          "rms_px": float(np.sqrt(result.rss["corners"] / (result.rss["n_corners"] / 2))),
                          "U_mm": None if "U_mm" in result.undetermined else v["U_mm"],
                          "d_mm": None if "d_mm" in result.undetermined else v["d_mm"],
                          "time_s": float(np.median(times)), "notes": list(result.notes) + list(result.warnings)}
    if not screen:
        return out
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        rms, K, _ = opencv_calibrate(obs, cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST)
        times.append(time.perf_counter() - t0)
    out["opencv"] = {"focal_px": float(K[0, 0]), "cx": float(K[0, 2]), "cy": float(K[1, 2]), "rms_px": float(rms),
                     "time_s": float(np.median(times))}
    return out


def write_markdown(path: str, res: dict) -> None:
    lines = [f"# One bad (low-contrast) view: {res['set']}, {res['good']} good views + "
             f"{res['bad_photo']} at {res['contrast']:g} contrast", "",
             f"Reproduce: `python benchmarks/robustness/bench_bad_view.py --set {res['set']} --views "
             f"{','.join(map(str, res['views']))} --contrast {res['contrast']:g} --bits {res['bits']}` "
             f"({res['bits']}-bit photo). tiltfit: `calibrate` unified, distortion k1, flat board; OpenCV: calibrateCamera, "
             f"k1 only, square pixels, same corners. Times are medians of {res['repeats']} runs.", "",
             f"Bad view: {res['bad_corners']} corners found, blur widths median {res['bad_blur_median_px']:.3g} px "
             f"(good views: {res['good_blur_median_px']:.3g} px).", "",
             "| case | tool | focal px | cx | cy | RMS px | U mm | d mm | time s | note |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    cases = res["cases"]
    for name, case in cases.items():
        for tool in ("tiltfit", "opencv"):
            if tool not in case:
                continue
            r = case[tool]
            if "error" in r:
                lines.append(f"| {name} | {tool} | — | — | — | — | — | — | {r['time_s']:.2f} | error: {r['error']} |")
            else:
                note = "; ".join(r.get("notes", []))[:200]
                focus = " | ".join("—" if r.get(k) is None else f"{r[k]:.4g}" for k in ("U_mm", "d_mm")) \
                    if tool == "tiltfit" else "— | —"
                lines.append(f"| {name} | {tool} | {r['focal_px']:.2f} | {r['cx']:.2f} | {r['cy']:.2f} | "
                             f"{r['rms_px']:.3f} | {focus} | {r['time_s']:.2f} | {note} |")
    a, b = cases["without the bad view"], cases["with the bad view"]
    for tool in ("tiltfit", "opencv"):
        if "error" not in a[tool] and "error" not in b[tool]:
            lines.append(f"\n{tool}: focal length moved by {b[tool]['focal_px'] - a[tool]['focal_px']:+.2f} px "
                         f"with the bad view; time ratio with/without {b[tool]['time_s'] / a[tool]['time_s']:.2f}")
    with open(path, "w", encoding="utf-8") as f:
        f.write("\n".join(lines) + "\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--set", default="industrial_ds1")
    ap.add_argument("--good", type=int, default=3)
    ap.add_argument("--views", default=None, help="the good views (indices into the set's photos with a board)")
    ap.add_argument("--bits", type=int, choices=(8, 16), default=16)
    ap.add_argument("--contrast", type=float, default=0.003)
    ap.add_argument("--repeats", type=int, default=3)
    add_output_options(ap, "bad_view")
    args = ap.parse_args(argv)
    from tiltfit.calibrate.model import Observations
    from tiltfit.target.layout import load_target

    folder = os.path.join(REAL, args.set)
    obs = observations(folder, PITCH[args.set])[0]
    views = [int(v) for v in args.views.split(",")] if args.views else list(range(args.good))
    good = obs.subset(views)
    target = load_target(os.path.join(folder, "target.json"))
    bad_photo = photos(folder)[args.good + 5]
    det = low_contrast_view(folder, bad_photo, args.contrast, target, args.bits)
    corners = np.array([[np.nan, np.nan] if c is None else c for c in det["corners_px"]], dtype=np.float64)
    blur = np.array([np.nan if b is None else b for b in det["blur_px"]], dtype=np.float64)
    both = Observations(good.points_mm, np.concatenate([good.corners_px.numpy(), corners[None]]),
                        np.concatenate([good.blur_px.numpy(), blur[None]]), good.image_size_px, good.pixel_pitch_mm,
                        list(good.names) + ["low_contrast.png"])
    cases = {"without the bad view": calibrate_case(good, args.repeats),
             "with the bad view": calibrate_case(both, args.repeats),
             "with the bad view, no blur screen (before)": calibrate_case(both, args.repeats, screen=False)}
    res = {"set": args.set, "good": len(views), "views": views, "bits": args.bits, "contrast": args.contrast, "repeats": args.repeats,
           "bad_photo": os.path.basename(bad_photo), "bad_corners": int(np.isfinite(corners).all(-1).sum()),
           "bad_blur_median_px": float(np.nanmedian(blur)),
           "good_blur_median_px": float(np.nanmedian(good.blur_px.numpy())), "cases": cases}
    save(args.out, res, write_markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
