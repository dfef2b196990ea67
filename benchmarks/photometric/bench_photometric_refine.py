"""What the photometric refinement gives over the corner fit, on captures we did not make with its model (issue 30 §5).

Captures of the independent exact-tracing generator (`tiltfit.experiments.exact_capture`: every ray through the
tilted thin lens, stratified aperture and pixel area, Poisson and read noise, 8-bit sRGB) and, for the same lens
and poses, of the project's ray tracer (`tiltfit.experiments.synth.render_view(method="renderer")`, Gaussian noise, float).
Cases: lens tilt +5° and −5°, heavy blur (2 views, d = 36 mm, untilted) and strong inclination (boards turned
55-60°).

Per case: tiltfit's detector and joint corner-and-blur fit (`calibrate(..., "joint")`, distortion none), then the
refinement as `tiltfit calibrate --refine photometric` runs it (start σ, corners, the start's intrinsics
covariance; lens samples from the blur, 2000 pixels a view). Beside them OpenCV's `calibrateCamera` on the same
corners (pinhole, no distortion: the chief-ray projection of a thin lens at any tilt is a pinhole at w), for the
focal length (f·pitch against w) and the principal point; OpenCV has no photometric peer.

Table per case: truth, corner fit ± σ (error in σ), refined ± σ (error in σ), OpenCV ± σ, kept?, why not, the
bound record, times.

    python benchmarks/photometric/bench_photometric_refine.py [--quick 1] [--seeds N]

`--seeds N` repeats every case with N noise seeds (and sampling seeds of the generators) and adds a summary over
them: per parameter the RMS error and the RMS of error/σ of the corner fit and of the kept calibration.

Writes benchmarks/results/photometric_refine.{json,md}. One torch thread.
"""
from __future__ import annotations

import math
import os
import sys
import time

import numpy as np
import torch

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)

from benchmarks.results_io import run_benchmark, write_lines  # noqa: E402

from tiltfit.experiments import exact_capture as ec  # noqa: E402
from tiltfit.target.layout import Target  # noqa: E402

W_PX, H_PX, PITCH_MM, W_MM = 240, 160, 0.13, 55.0
BOARD = Target(tuple(50.0 * i for i in range(7)), tuple(50.0 * j for j in range(5)), (0, 0), 25.0)
KEYS = ("w_mm", "U_mm", "d_mm", "theta_F_deg", "theta_L_deg")

#: name: (U0 mm (focus of the untilted lens), d mm, lens tilt °, views: (rx°, ry°, distance mm) per view)
CASES = {
    "tilt +5°": (760.0, 40.0, 5.0, ((20.0, 5.0, 780.0), (-15.0, 15.0, 820.0), (-10.0, -10.0, 800.0))),
    "tilt −5°": (760.0, 40.0, -5.0, ((20.0, 5.0, 780.0), (-15.0, 15.0, 820.0), (-10.0, -10.0, 800.0))),
    "heavy blur (2 views, d 36 mm)": (620.0, 36.0, 0.0, ((25.0, 10.0, 760.0), (-20.0, -15.0, 860.0))),
    "inclined 55-60°": (650.0, 30.0, 0.0, ((55.0, 10.0, 800.0), (-10.0, 60.0, 820.0), (-58.0, -10.0, 790.0))),
}
QUICK = ("heavy blur (2 views, d 36 mm)",)
#: The generators each case is captured by: all by the exact generator, the heavy-blur case by the renderer too.
GENERATORS = {"exact": tuple(CASES), "renderer": ("heavy blur (2 views, d 36 mm)",)}


def captures(case: str, generator: str, seed: int = 0):
    """Linear images of the case's views, and the truth (w, U, d, θF, θL, principal point)."""
    from renderer.cameras.lens import Lens, Sensor
    from camio.files import srgb_to_linear
    from tiltfit.experiments import synth

    U0, d, tilt, views = CASES[case]
    lens = ec.ExactLens.focused_at(W_MM, U0, d, tilt, W_PX, H_PX, PITCH_MM)
    truth = {**lens.truth(), "cx_px": (W_PX - 1) / 2, "cy_px": (H_PX - 1) / 2}
    images = []
    for k, (rx, ry, dist) in enumerate(views):
        R, T = ec.pose_facing(BOARD, rx, ry, dist)
        if generator == "exact":
            img = ec.capture(lens, R, T, BOARD, seed=100 * seed + k, aperture_strata=6, pixel_strata=2)
            images.append(srgb_to_linear(img / 255.0))
        else:
            cam = Lens(truth["w_mm"], truth["U_mm"], d, math.radians(truth["theta_F_deg"]),
                       sensor=Sensor(W_PX, H_PX, PITCH_MM))
            view = synth.render_view(BOARD, cam, R, T, dark=0.05, white=0.8, background=0.25, method="renderer",
                                     spp=64, noise_sigma=0.004, seed=100 * seed + k)
            images.append(view.image[..., 0].astype(np.float64))
    return images, truth


def corner_fit(images):
    from tiltfit.calibrate.flow import calibrate
    from tiltfit.detect.chessboard import detect
    from tiltfit.calibrate.fit import FitOptions
    from tiltfit.calibrate.model import Observations

    dets = [detect(im, BOARD) for im in images]
    obs = Observations(BOARD.feature_points(), np.stack([d.corners_px for d in dets]),
                       np.stack([d.blur_px for d in dets]), (W_PX, H_PX), PITCH_MM)
    res = calibrate(obs, "joint", options=FitOptions(distortion="none", nominal_focal_mm=W_MM))
    return obs, res, [int(d.found.sum()) for d in dets]


def principal_sigma(res) -> tuple[float, float]:
    cov = res.intrinsics_covariance
    if not cov:
        return (math.nan, math.nan)
    names, M = cov["names"], np.asarray(cov["matrix"])
    return tuple(math.sqrt(max(M[names.index(k), names.index(k)], 0.0)) if k in names else math.nan
                 for k in ("cx_px", "cy_px"))


def opencv_fit(obs) -> dict:
    """cv2.calibrateCamera on the same corners: pinhole, no distortion, square pixels; f·pitch and the principal
    point with their σ (calibrateCameraExtended's)."""
    import cv2

    obj, img = [], []
    P = np.asarray(obs.points_mm, dtype=np.float32)
    for v in range(obs.corners_px.shape[0]):
        c = np.asarray(obs.corners_px[v], dtype=np.float64)
        ok = np.isfinite(c).all(1)
        obj.append(P[ok].reshape(-1, 1, 3))
        img.append(c[ok].astype(np.float32).reshape(-1, 1, 2))
    f0 = W_MM / PITCH_MM
    K0 = np.array([[f0, 0, (W_PX - 1) / 2], [0, f0, (H_PX - 1) / 2], [0, 0, 1]], dtype=np.float64)
    flags = (cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_ZERO_TANGENT_DIST
             | cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3)
    t0 = time.perf_counter()
    rms, K, _, _, _, sd, _, _ = cv2.calibrateCameraExtended(obj, img, (W_PX, H_PX), K0, np.zeros(5), flags=flags)
    sd = np.asarray(sd).ravel()
    # OpenCV's pixel centre convention: (0, 0) is the centre of the top-left pixel, as ours.
    return {"f_mm": float(K[0, 0]) * PITCH_MM, "f_mm_sigma": float(sd[0]) * PITCH_MM, "cx_px": float(K[0, 2]),
            "cy_px": float(K[1, 2]), "cx_sigma": float(sd[2]), "cy_sigma": float(sd[3]), "rms_px": float(rms),
            "seconds": time.perf_counter() - t0}


def measure_case(case: str, generator: str, seed: int = 0) -> dict:
    from tiltfit.photometric import PhotometricOptions, refine_photometric

    t0 = time.perf_counter()
    images, truth = captures(case, generator, seed)
    t_capture = time.perf_counter() - t0
    t0 = time.perf_counter()
    obs, corner, found = corner_fit(images)
    t_corner = time.perf_counter() - t0
    out = {"case": case, "generator": generator, "seed": seed, "truth": truth, "corners_found": found,
           "capture_s": t_capture, "corner_fit_s": t_corner}
    cx_s, cy_s = principal_sigma(corner)
    pp = corner.values.get("principal_point_px")
    out["corner_fit"] = {**{k: corner.values.get(k) for k in KEYS}, "cx_px": float(pp[0]), "cy_px": float(pp[1]),
                         "free_principal_point": bool(corner.free_principal_point)}
    out["corner_fit_sigma"] = {**{k: corner.sigma.get(k) for k in KEYS}, "cx_px": cx_s, "cy_px": cy_s}
    out["opencv"] = opencv_fit(obs)
    t0 = time.perf_counter()
    res = refine_photometric(images, BOARD, corner.camera,
                             PhotometricOptions(lens_samples=0, max_pixels=2000),
                             start_sigma=corner.sigma, corners=obs,
                             corner_held_out_px=(corner.held_out or {}).get("rms_px"),
                             start_covariance=corner.intrinsics_covariance)
    out["refine_s"] = time.perf_counter() - t0
    out["refined"] = {k: res.values[k] for k in KEYS}
    out["refined_sigma"] = {k: res.sigma[k] for k in KEYS}
    out.update(kept=res.kept, rejected_because=res.rejected_because, at_bound=res.at_bound, bounds=res.bounds,
               held_out=res.held_out, corner_check=res.corner_check, aperture=res.values["aperture"],
               closed_form_pixels=res.values["closed_form_pixels"], lens_samples=res.values["lens_samples"],
               rms_linear=res.rms, iterations=res.iterations)
    return out


def measure(args) -> dict:
    torch.set_num_threads(1)
    names = QUICK if args.quick else tuple(CASES)
    t0 = time.perf_counter()
    rows = []
    for seed in range(args.seeds):
        for gen in (("exact",) if args.quick else tuple(GENERATORS)):
            for name in (n for n in names if n in GENERATORS[gen]):
                print(f"case {name} ({gen}, seed {seed})", file=sys.stderr, flush=True)
                try:
                    rows.append(measure_case(name, gen, seed))
                except Exception as e:   # a case that fails is a result too (the detector on heavy blur, a fit)
                    rows.append({"case": name, "generator": gen, "seed": seed, "error": f"{type(e).__name__}: {e}"})
                print(f"  {rows[-1].get('kept', rows[-1].get('error'))}", file=sys.stderr, flush=True)
    opts = (" --quick 1" if args.quick else "") + (f" --seeds {args.seeds}" if args.seeds != 1 else "")
    return {"command": "python benchmarks/photometric/bench_photometric_refine.py" + opts, "seeds": args.seeds,
            "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "image": [W_PX, H_PX], "pitch_mm": PITCH_MM,
            "w_mm": W_MM, "cases": rows, "wall_s": time.perf_counter() - t0}


def _fmt(v, s, t, digits):
    if v is None or not isinstance(v, (int, float)) or not math.isfinite(v):
        return "—"
    err = v - t
    z = f", {err / s:+.1f}σ" if s and math.isfinite(s) and s > 0 else ""
    return f"{v:.{digits}f} ± {s:.{digits}f} ({err:+.{digits}f}{z})" if s is not None and math.isfinite(s) else \
        f"{v:.{digits}f} ({err:+.{digits}f})"


def write_markdown(path: str, res: dict) -> None:
    L = ["# Photometric refinement against the corner fit (issue 30 §5)", "",
         f"`{res['command']}`, {res['created']}; {res['image'][0]} x {res['image'][1]} px, pitch {res['pitch_mm']} mm, "
         f"w {res['w_mm']} mm, board 6 x 4 cells of 50 mm; {res['wall_s']:.0f} s in all.", "",
         "*exact*: the independent generator (6² aperture x 2² area samples a pixel, Poisson + read noise, 8-bit "
         "sRGB, decoded); *renderer*: the project's ray tracer (64 spp, Gaussian noise 0.004). Each cell: value ± σ "
         "(error, error in σ). OpenCV: `calibrateCamera` on the same corners (pinhole, no distortion): f·pitch beside "
         "w, and the principal point; it has no photometric step. The refinement holds the principal point (the "
         "corner fit's).", ""]
    if res.get("seeds", 1) > 1:
        L += _summary_lines(res)
    digits = {"w_mm": 3, "U_mm": 2, "d_mm": 3, "theta_F_deg": 3, "theta_L_deg": 4, "cx_px": 2, "cy_px": 2}
    for c in res["cases"]:
        if c.get("seed", 0) != 0:
            continue
        L += [f"## {c['case']} ({c['generator']}" + (", seed 0" if res.get("seeds", 1) > 1 else "") + ")", ""]
        if "error" in c:
            L += [f"Failed: {c['error']}", ""]
            continue
        t, cf, cs, rf, rs, cv = (c["truth"], c["corner_fit"], c["corner_fit_sigma"], c["refined"], c["refined_sigma"],
                                 c["opencv"])
        L += [f"Corners found per view: {c['corners_found']}; kept: **{c['kept']}**"
              + (f" ({c['rejected_because']})" if c["rejected_because"] else "") + f"; aperture {c['aperture']} "
              f"({c['closed_form_pixels']} pixels in closed form), {c['iterations']} iterations.", "",
              "| | truth | corner fit | refined | OpenCV |", "|---|---|---|---|---|"]
        for k in KEYS + ("cx_px", "cy_px"):
            dg = digits[k]
            ref = _fmt(rf[k], rs[k], t[k], dg) if k in rf else "held"
            if k == "w_mm":
                ocv = _fmt(cv["f_mm"], cv["f_mm_sigma"], t[k], dg)
            elif k in ("cx_px", "cy_px"):
                ocv = _fmt(cv[k], cv[k.replace("_px", "_sigma")], t[k], dg)
            else:
                ocv = "—"
            L.append(f"| {k} | {t[k]:.{dg}f} | {_fmt(cf[k], cs[k], t[k], dg)} | {ref} | {ocv} |")
        L.append("")
        for b in c["bounds"]:
            L.append(f"- bound {b['parameter']}: start {b['start']:.6g}, [{b['low']:.6g}, {b['high']:.6g}], refined "
                     f"{b['refined']:.6g}" + (" **at the bound**" if b["at_bound"] else ""))
        h, cc = c.get("held_out"), c.get("corner_check")
        if h:
            L.append(f"- held-out pixels ({h['pixels']}): cost {h['refined']:.4g} refined, {h['start']:.4g} start")
        if cc:
            L.append(f"- corners held out of the photometric fit: RMS {cc['refined_px']:.4f} px refined, limit "
                     f"{cc['limit_px']:.4f} px")
        L += [f"- time: capture {c['capture_s']:.1f} s, corner fit {c['corner_fit_s']:.1f} s, refinement "
              f"{c['refine_s']:.1f} s, OpenCV {c['opencv']['seconds']:.3f} s", ""]
    write_lines(path, L)


def _summary_lines(res: dict) -> list:
    """Per case, generator and parameter over the seeds: RMS error and RMS of error/σ, corner fit against the kept
    calibration (the refinement where kept, else the corner fit), and how often the refinement was kept."""
    groups = {}
    for c in res["cases"]:
        groups.setdefault((c["case"], c["generator"]), []).append(c)
    L = [f"## Over {res['seeds']} seeds: RMS error (RMS of error/σ), corner fit → kept calibration", "",
         "| case | kept | " + " | ".join(KEYS) + " |", "|---|---|" + "---|" * len(KEYS)]
    for (case, gen), rows in groups.items():
        ok = [c for c in rows if "error" not in c]
        kept = sum(c["kept"] == "photometric" for c in ok)
        cells = []
        for k in KEYS:
            def stats(pick):
                e, z = [], []
                for c in ok:
                    v, sg = pick(c)
                    if v is None or not math.isfinite(v):
                        continue
                    e.append(v - c["truth"][k])
                    if sg and math.isfinite(sg) and sg > 0:
                        z.append((v - c["truth"][k]) / sg)
                rms = lambda a: math.sqrt(sum(x * x for x in a) / len(a)) if a else math.nan  # noqa: E731
                return rms(e), rms(z)

            ce, cz = stats(lambda c: (c["corner_fit"][k], c["corner_fit_sigma"][k]))
            ke, kz = stats(lambda c: (c["refined"][k], c["refined_sigma"][k]) if c["kept"] == "photometric" else
                           (c["corner_fit"][k], c["corner_fit_sigma"][k]))
            cells.append(f"{ce:.3g} ({cz:.2f}) → {ke:.3g} ({kz:.2f})")
        L.append(f"| {case} ({gen}) | {kept} of {len(ok)}" + (f", {len(rows) - len(ok)} failed" if len(ok) < len(rows)
                                                                else "") + " | " + " | ".join(cells) + " |")
    return L + [""]


if __name__ == "__main__":
    sys.exit(run_benchmark(__doc__, "photometric_refine", measure, write_markdown, quick=0, seeds=1))
