"""(a) Corner detectors against blur: ours (`tiltfit.detect.chessboard`) against OpenCV's findChessboardCornersSB and
findChessboardCorners + cornerSubPix on `tiltfit.experiments.synth` images of the target, blur growing to the projected square."""
from __future__ import annotations

import time

import numpy as np

from .common import StabilityConfig, Study, subplots_row


def detector_target():
    """The detector sweep's target (as benchmarks/detection/bench_detect_opencv.py): 9 × 6 cells of 20 mm, rows designed
    for a 20° inclined view from 650 mm."""
    from tiltfit.target.design import design_target

    return design_target(9, 6, 20.0, w_mm=55.39, distance_mm=650.0, inclination_deg=20.0)


#: Camera positions in the target frame (mm) and rolls (degrees) of the detector sweep (as the benchmark); the
#: board is ~650 mm away and the focus is put at 400 mm, so the aperture sets the blur.
DETECTOR_POSES = (((40.0, -30.0, -650.0), 10.0), ((-80.0, -120.0, -600.0), -15.0), ((150.0, 60.0, -700.0), 25.0))
DETECTOR_NOISE = 0.004  # linear read noise of the detector images


def _opencv_detectors(pattern):
    """{name: callable(gray8) -> (M, 2) corners or None}: OpenCV's two chessboard detectors."""
    import cv2

    def sb(gray8):
        flags = cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
        ok, c = cv2.findChessboardCornersSB(gray8, pattern, flags=flags)
        return c.reshape(-1, 2).astype(np.float64) if ok else None

    def classic(gray8):
        ok, c = cv2.findChessboardCorners(gray8, pattern,
                                          flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
        if not ok:
            return None
        crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 1e-3)
        return cv2.cornerSubPix(gray8, c, (11, 11), (-1, -1), crit).reshape(-1, 2).astype(np.float64)

    return {"opencv_sb": sb, "opencv_classic": classic}


DETECTOR_LABELS = {"ours": "ours (tiltfit.detect.chessboard)", "opencv_sb": "cv2.findChessboardCornersSB",
                   "opencv_classic": "cv2.findChessboardCorners + cornerSubPix"}


def _score(found, truth, visible, by_index: bool, square_px: float):
    """(success, corner errors in px). OpenCV's corners are matched to the nearest true corner; ours are
    indexed, so a wrong index costs its distance. Success: every visible corner, none off by half a square."""
    if found is None:
        return False, np.zeros(0)
    if by_index:
        ok = np.isfinite(found).all(1)
        err = np.hypot(*(found[ok] - truth[ok]).T)
        return bool(ok[visible].all() and (err < 0.5 * square_px).all()), err
    d = np.hypot(found[:, None, 0] - truth[None, :, 0], found[:, None, 1] - truth[None, :, 1]).min(1)
    return bool(len(found) >= visible.sum() and (d < 0.5 * square_px).all()), d


def study_detectors(cfg: StabilityConfig, log) -> Study:
    """(a) Success rate and corner RMS of the three detectors against blur / projected square."""
    from tiltfit.experiments.synth import PAPER_CAMERA

    t0 = time.perf_counter()
    target = detector_target()
    ny, nx = target.grid_shape
    methods = {"ours": None, **_opencv_detectors((nx, ny))}
    base = PAPER_CAMERA.binned(cfg.detector_downscale)
    images = _detector_images(cfg, target, methods, base, log)
    rows = _detector_rows(cfg, images, methods)
    limits, findings = _detector_findings(rows, methods)
    fig = _detector_figure(cfg, rows, methods, base)
    return Study("detectors", "(a) Corner detectors against blur", rows, findings,
                 {"limits": limits, "images": images, "image_px": [base.sensor.width_px, base.sensor.height_px],
                  "noise_linear": DETECTOR_NOISE, "target": target.to_dict()}, fig, time.perf_counter() - t0)


def _detector_images(cfg: StabilityConfig, target, methods: dict, base, log) -> list:
    """One record per blur ratio and pose: the view's square and blur (px), and each detector's success and
    corner RMS (px)."""
    from tiltfit.detect.chessboard import detect
    from tiltfit.experiments.synth import look_at_pose, projected_square_px, render_view, with_blur_ratio

    images = []
    for ratio in cfg.detector_ratios:
        for k, (pos, roll) in enumerate(DETECTOR_POSES[:cfg.detector_poses]):
            R, T = look_at_pose(target, pos, roll_deg=roll)
            cam = with_blur_ratio(base, target, R, T, max(ratio, 1e-4), U_mm=400.0)
            v = render_view(target, cam, R, T, noise_sigma=DETECTOR_NOISE, srgb8=True,
                            seed=cfg.seed + 100 * k + int(round(1000 * ratio)))
            square = float(np.median(projected_square_px(target, cam, R, T)))
            rec = {"ratio": ratio, "pose": k, "square_px": square, "blur_px": float(np.median(v.truth.blur_px))}
            for name, fn in methods.items():
                if name == "ours":
                    det = detect(v.image, target, measure_blur=False)
                    found, by_index = (det.corners_px if det.grid_found else None), True
                else:
                    found, by_index = fn(v.image_srgb8[..., 0]), False
                ok, err = _score(found, v.truth.corners_px, v.truth.in_image, by_index, square)
                rec[f"{name}_ok"] = ok
                rec[f"{name}_rms_px"] = float(np.sqrt(np.mean(err ** 2))) if ok and err.size else None
            images.append(rec)
            log(f"(a) blur/square {ratio:.2f} pose {k}: blur {rec['blur_px']:.1f} px, square {square:.1f} px | "
                + " | ".join(f"{n} {'ok' if rec[n + '_ok'] else '--'}" for n in methods))
    return images


def _detector_rows(cfg: StabilityConfig, images: list, methods: dict) -> list:
    """One row per blur ratio: median blur and square (px), each detector's success rate and corner RMS (px)."""
    rows = []
    for ratio in cfg.detector_ratios:
        rr = [r for r in images if r["ratio"] == ratio]
        row = {"blur_over_square": ratio, "blur_px": float(np.median([r["blur_px"] for r in rr])),
               "square_px": float(np.median([r["square_px"] for r in rr]))}
        for name in methods:
            row[f"{name}_success"] = float(np.mean([r[f"{name}_ok"] for r in rr]))
            errs = [r[f"{name}_rms_px"] for r in rr if r[f"{name}_rms_px"] is not None]
            row[f"{name}_rms_px"] = float(np.sqrt(np.mean(np.square(errs)))) if errs else None
        rows.append(row)
    return rows


def _detector_findings(rows: list, methods: dict) -> tuple[dict, list]:
    """Each detector's limits (the largest blur where it finds every board, its first failure, its corner RMS)
    and one sentence each."""
    limits = {}
    findings = []
    for name in methods:
        ok = [r["blur_over_square"] for r in rows if r[f"{name}_success"] == 1.0]
        bad = [r["blur_over_square"] for r in rows if r[f"{name}_success"] < 1.0]
        last_ok = max(ok) if ok else None
        first_bad = min((b for b in bad if last_ok is None or b > last_ok), default=None)
        rms = [r[f"{name}_rms_px"] for r in rows if r[f"{name}_rms_px"] is not None]
        over_1px = min((r["blur_over_square"] for r in rows if (r[f"{name}_rms_px"] or 0.0) > 1.0), default=None)
        at_bad = next((r for r in rows if r["blur_over_square"] == first_bad), None)
        limits[name] = {"all_found_up_to": last_ok, "first_failure": first_bad, "rms_over_1px_from": over_1px,
                        "rms_px_min": min(rms) if rms else None, "rms_px_max": max(rms) if rms else None,
                        "success_at_largest_blur": rows[-1][f"{name}_success"]}
        lim = limits[name]
        if last_ok is None:
            text = f"{DETECTOR_LABELS[name]} found no board at any blur of the sweep"
        else:
            text = (f"{DETECTOR_LABELS[name]} finds every board up to blur/square = {last_ok:.2f}"
                    + (f", {100 * at_bad[f'{name}_success']:.0f} % of them at {first_bad:.2f}"
                       if first_bad is not None else " (the largest blur of the sweep)")
                    + (f" and {100 * lim['success_at_largest_blur']:.0f} % at {rows[-1]['blur_over_square']:.2f}"
                       if first_bad is not None and first_bad < rows[-1]["blur_over_square"] else "")
                    + (f"; corner RMS {lim['rms_px_min']:.3f}–{lim['rms_px_max']:.3f} px on the boards it finds"
                       if rms else "")
                    + (f", above 1 px from blur/square = {over_1px:.2f}" if over_1px is not None else ""))
        findings.append(text + ".")
    findings.append("A board counts as found when every visible corner is returned within half a square of its "
                    "true position (OpenCV's corners matched to the nearest true corner, ours by index).")
    return limits, findings


def _detector_figure(cfg: StabilityConfig, rows: list, methods: dict, base):
    """Success rate and corner RMS against blur / projected square, one curve per detector."""
    fig, (ax1, ax2) = subplots_row(2)
    x = [r["blur_over_square"] for r in rows]
    for name, style in zip(methods, ("o-", "s--", "^:")):
        ax1.plot(x, [r[f"{name}_success"] for r in rows], style, label=DETECTOR_LABELS[name])
        ax2.plot(x, [np.nan if r[f"{name}_rms_px"] is None else r[f"{name}_rms_px"] for r in rows], style,
                 label=DETECTOR_LABELS[name])
    ax1.set_xlabel("blur diameter / projected square")
    ax1.set_ylabel("success rate")
    ax1.set_ylim(-0.05, 1.05)
    ax1.legend(fontsize="x-small")
    ax2.set_xlabel("blur diameter / projected square")
    ax2.set_ylabel("corner RMS error [px] (successes)")
    ax2.set_yscale("log")
    for ax in (ax1, ax2):
        ax.grid(alpha=0.3)
    fig.suptitle(f"(a) detectors vs blur: {base.sensor.width_px}×{base.sensor.height_px} px, "
                 f"{min(cfg.detector_poses, len(DETECTOR_POSES))} pose(s) per blur", fontsize="medium")
    return fig
