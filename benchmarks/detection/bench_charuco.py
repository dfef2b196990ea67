"""ChArUco corners against OpenCV's CharucoDetector on the same renders: ids and error versus blur, time; and
calibration from views of a third of the board against whole views (ray-traced).

Peer, measured in the same run on the same images: `cv2.aruco.CharucoDetector(board).detectBoard` on the 8-bit
sRGB image (its default refinement), the board being `CharucoTarget.opencv_board()`.

Images:
- blur sweep: `tiltfit.experiments.synth.render_constant_blur` (exact area-averaged board with markers, looked up through the
  view's homography, one disc of the given diameter, then Gaussian noise of σ 0.003: white 0.8, dark 0.05, so
  0.4 % of the contrast), 320 × 240, a 12 × 9 board of 15 mm squares with 11 mm DICT_5X5_100 markers; 4 partial
  views (25–34 of 88 corners visible, a square about 42 px) and 2 whole views (a square about 22 px); blur
  diameter 0 to 0.5 of the projected square. Truth: the board corners projected by the view's homography. A
  corner farther than a quarter square from its id's truth has a wrong id.
- calibration: the renderer's ray tracer (thin-lens camera, textured board), 24 spp, 8-bit, 6 partial and 4
  whole views; `unified` fit without distortion, principal point held: w ± σ of each set.

Writes benchmarks/results/charuco.{json,md}. Usage:
    python benchmarks/detection/bench_charuco.py [--quick] [--out STEM] [--markdown-only]
"""
from __future__ import annotations

import argparse
import math
import os
import platform
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))

from benchmarks import results_io  # noqa: E402
from tiltfit.detect.charuco import CANCEL_BITS_BLUR, detect_charuco, opencv_corners, refine_model  # noqa: E402
from tiltfit.experiments.charuco_views import CAMERA, FULL, PARTIAL, TARGET, blurred_renders, pose  # noqa: E402
from tiltfit.experiments.synth import render_view  # noqa: E402

BLURS = (0.0, 0.1, 0.25, 0.4, 0.5)
NOISE = 0.003


def _stats(found, err, sq, n_visible):
    wrong = err > 0.25 * sq
    ok = err[~wrong]
    return {"found": int(found), "visible": int(n_visible), "wrong_ids": int(wrong.sum()),
            "rms_px": float(np.sqrt(np.mean(ok ** 2))) if ok.size else None,
            "max_px": float(ok.max()) if ok.size else None}


def blur_sweep(repeats: int, views) -> list:
    rng = np.random.default_rng(0)
    rows = []
    for kind, v in views:
        for truth, sq, b, img in blurred_renders(v, BLURS, NOISE, rng):
            vis = truth.in_image
            det, t_ours, _ = results_io.timed(lambda: detect_charuco(img, TARGET), repeats)
            floor = None
            if b > CANCEL_BITS_BLUR:  # the noise's floor: the model fit's Cramér–Rao bound at the found corners
                _, fl = refine_model(img, TARGET, np.where(det.found[:, None], truth.corners_px, np.nan),
                                     np.where(det.found, b * sq, np.nan))
                floor = float(np.sqrt(np.nanmean(fl[det.found] ** 2)))
            oc, t_cv, _ = results_io.timed(lambda: opencv_corners(img, TARGET), repeats)
            fo, fc = det.found, np.isfinite(oc).all(1)
            e_o = np.hypot(*(det.corners_px[fo] - truth.corners_px[fo]).T)
            e_c = np.hypot(*(oc[fc] - truth.corners_px[fc]).T)
            both = fo & fc
            common = {"n": int(both.sum())}
            if both.any():
                common["ours_rms_px"] = float(np.sqrt(np.mean(np.sum((det.corners_px[both] - truth.corners_px[both]) ** 2, 1))))
                common["opencv_rms_px"] = float(np.sqrt(np.mean(np.sum((oc[both] - truth.corners_px[both]) ** 2, 1))))
            rows.append({"view": kind, "square_px": sq, "blur_squares": b, "blur_px": b * sq,
                         "ours": {**_stats(fo.sum(), e_o, sq, vis.sum()), "time_s": t_ours, "how": det.message,
                                  "floor_rms_px": floor,
                                  "blur_ratio": float(np.nanmedian(det.blur_px / (b * sq))) if b > 0 else None},
                         "opencv": {**_stats(fc.sum(), e_c, sq, vis.sum()), "time_s": t_cv}, "common": common})
            print(kind, b, rows[-1]["ours"], rows[-1]["opencv"], flush=True)
    return rows


def checker_reference(views) -> list:
    """The same views and noise with a plain checkerboard of the same squares: the point-symmetry refinement
    (window 0.4 square) started at the truth, i.e. what noise alone leaves at each blur."""
    from tiltfit.detect.chessboard import refine_symmetric
    from tiltfit.target.layout import Target

    checker = Target(TARGET.x_edges, TARGET.y_edges, TARGET.dark_cell, TARGET.margin)
    rng = np.random.default_rng(0)
    rows = []
    for kind, v in views:
        for truth, sq, b, img in blurred_renders(v, BLURS, NOISE, rng, checker):
            vis = truth.in_image
            xy, _, ok = refine_symmetric(img, truth.corners_px[vis], np.full(vis.sum(), min(0.4 * sq, 20.0)))
            e = np.hypot(*(xy - truth.corners_px[vis]).T)[ok]
            rows.append({"view": kind, "blur_squares": b, "rms_px": float(np.sqrt(np.mean(e ** 2))),
                         "max_px": float(e.max())})
    return rows


def calibration(spp: int) -> dict:
    from tiltfit.calibrate.fit import FitOptions
    from tiltfit.calibrate.model import Observations
    from tiltfit.calibrate.photos import fit_with_held_out

    cam = CAMERA.with_(U=420.0, d=0.8)
    out = {"truth_w_mm": cam.w, "spp": spp}
    for kind, views in (("partial", PARTIAL), ("full", FULL)):
        dets = []
        for k, v in enumerate(views):
            R, T = pose(v)
            r = render_view(TARGET, cam, R, T, method="renderer", spp=spp, seed=k, srgb8=True)
            dets.append(detect_charuco(r.image, TARGET))
        obs = Observations(TARGET.feature_points(), np.stack([d.corners_px for d in dets]),
                           np.stack([d.blur_px for d in dets]), CAMERA.sensor.size_px, CAMERA.sensor.pixel_pitch,
                           names=[f"{kind}{k}" for k in range(len(dets))])
        res, _, _ = fit_with_held_out(obs, "unified", options=FitOptions(distortion="none", free_principal_point=False),
                                      held_out_folds=0)
        out[kind] = {"views": len(dets), "corners_per_view": [int(d.found.sum()) for d in dets],
                     "w_mm": res.values["w_mm"], "sigma_w_mm": res.sigma["w_mm"],
                     "rms_px": math.sqrt(res.rss["corners"] / max(res.rss["n_corners"] // 2, 1))}
        print(kind, out[kind], flush=True)
    p, f = out["partial"], out["full"]
    out["difference_in_sigma"] = abs(p["w_mm"] - f["w_mm"]) / math.hypot(p["sigma_w_mm"], f["sigma_w_mm"])
    return out


def write_markdown(path: str, res: dict) -> None:
    def num(v, fmt=".3f"):
        return "—" if v is None else format(v, fmt)

    lines = ["# ChArUco corners: ours against OpenCV's CharucoDetector", "",
             f"Machine: {res['machine']}. Command: `{res['command']}`. Same images for both, in one run; "
             f"times are medians of {res['repeats']} runs per image. See `benchmarks/detection/bench_charuco.py` for the "
             "renders (one blur disc per image, Gaussian noise of σ 0.003 on white 0.8 and dark 0.05: 0.4 % of the "
             "contrast) and `docs/charuco.md` for the method.", "",
             "## Corner error against blur", "",
             "Blur: disc diameter in squares (pixels). found / visible corners; wrong ids: corners more than a quarter "
             "square from their id's truth; RMS and max over the corners with right ids. *floor*: the RMS error "
             "the noise allows at those corners, √(mean trace of the Cramér–Rao covariance) of the model fit "
             "(`refine_model`) at the true corners and blur (computed where the model refines, blur > "
             f"{CANCEL_BITS_BLUR} square). *common*: RMS on the corners both found.", "",
             "| view | blur | ours found | wrong ids | RMS px | max px | floor RMS px | OpenCV found | wrong ids "
             "| RMS px | max px | common n | ours RMS | OpenCV RMS | blur measured / rendered | time ours s "
             "| time OpenCV s |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in res["blur_sweep"]:
        o, c, m = r["ours"], r["opencv"], r["common"]
        lines.append(f"| {r['view']} ({r['square_px']:.0f} px square) | {r['blur_squares']:g} ({r['blur_px']:.1f} px) "
                     f"| {o['found']}/{o['visible']} | {o['wrong_ids']} | {num(o['rms_px'])} | {num(o['max_px'])} "
                     f"| {num(o.get('floor_rms_px'), '.4f')} | {c['found']}/{c['visible']} | {c['wrong_ids']} "
                     f"| {num(c['rms_px'])} | {num(c['max_px'])} "
                     f"| {m['n']} | {num(m.get('ours_rms_px'))} | {num(m.get('opencv_rms_px'))} "
                     f"| {num(o['blur_ratio'])} | {o['time_s']:.2f} | {c['time_s']:.3f} |")
    if res.get("checker_reference"):
        lines += ["", "Reference: a plain checkerboard of the same squares, same views and noise, the point-symmetry "
                  "refinement (window 0.4 square) started at the truth: what that method leaves (its bias under "
                  "perspective at heavy blur included), not the noise's floor:", "",
                  "| view | blur | RMS px | max px |", "|---|---|---|---|"]
        lines += [f"| {r['view']} | {r['blur_squares']:g} | {r['rms_px']:.3f} | {r['max_px']:.3f} |"
                  for r in res["checker_reference"]]
    t_o = np.median([r["ours"]["time_s"] for r in res["blur_sweep"]])
    t_c = np.median([r["opencv"]["time_s"] for r in res["blur_sweep"]])
    lines += ["", f"Detection time per 320 × 240 image, median over all rows: ours {t_o:.2f} s (ids, refinement, "
              f"blur widths), OpenCV {t_c:.3f} s: ours takes {t_o / t_c:.0f}× OpenCV's time.", ""]
    cal = res.get("calibration")
    if cal:
        p, f = cal["partial"], cal["full"]
        lines += ["## Calibration from partial views (ray-traced)", "",
                  f"The renderer's ray tracer, {cal['spp']} spp, 8-bit; w (truth {cal['truth_w_mm']:g} mm) from the "
                  "unified fit without distortion.", "",
                  "| views | corners per view | w mm | σ(w) mm | RMS px per corner |", "|---|---|---|---|---|",
                  f"| {p['views']} partial | {p['corners_per_view']} | {p['w_mm']:.4f} | {p['sigma_w_mm']:.4f} | "
                  f"{p['rms_px']:.3f} |",
                  f"| {f['views']} whole | {f['corners_per_view']} | {f['w_mm']:.4f} | {f['sigma_w_mm']:.4f} | "
                  f"{f['rms_px']:.3f} |", "",
                  f"Partial and whole differ by {cal['difference_in_sigma']:.2f} σ (combined).", ""]
    with open(path, "w") as fh:
        fh.write("\n".join(lines))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="2 partial and 1 whole view, 1 repeat, no calibration")
    ap.add_argument("--repeats", type=int, default=3)
    results_io.add_output_options(ap, "charuco")
    args = ap.parse_args()
    if results_io.markdown_only(args, write_markdown):
        return 0
    repeats = 1 if args.quick else args.repeats
    views = [("partial", v) for v in PARTIAL[:2 if args.quick else 4]] + [("whole", v) for v in FULL[:1 if args.quick else 2]]
    res = {"machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs (shared)",
           "command": "python benchmarks/detection/bench_charuco.py" + (" --quick" if args.quick else ""),
           "repeats": repeats, "blur_sweep": blur_sweep(repeats, views), "checker_reference": checker_reference(views)}
    if not args.quick:
        res["calibration"] = calibration(spp=24)
    results_io.save(args.out, res, write_markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
