"""The photometric fit's forward model against exact tracing, pixel by pixel (issue 30 §4).

The peer is `tiltfit.experiments.exact_capture`: an independent generator that traces every ray through the
tilted thin lens (12 x 12 stratified aperture samples, 4 x 4 area samples per pixel). For each case the board is
rendered by both at the generator's true lens and pose, and the dark fraction D (0 paper, 1 ink) compared on the
pixels the fit uses (`usable_pixels`: the blur disc on the board inside its margin):

- bias: the mean of model − exact on edge pixels (0.03 < D < 0.97) and their RMS beyond the generator's own
  noise (two seeds: RMS² − σ²/2 of their mean);
- what that mismatch does to a fit: the shift of d (and of U) that best explains it, by least squares on the
  model's own derivative (central differences), in % (a pure rendering error turned into a parameter error);
- by blur size, inclination, tilt and position in the image; for each of the forward model's paths: the
  aperture in closed form (4 x 4 points per pixel, 8 x 8 below render.SHARP_BLUR_PX, as the fit takes them),
  the fixed lens samples (64, the refinement's count for sharp pixels, and 256), and `auto` (the refinement's
  mix: closed form from CLOSED_FORM_MIN_BLUR_PX of blur).

Candidates checked beside it (each its own section): the 8-bit sRGB decoding (bias of decoded levels against the
linear signal), the per-view gain (levels fitted to the 8-bit capture against the truth), the pixel's area
(closed form with 4 x 4 against 8 x 8 points per pixel on sharp edges) and the pixel quadrature alone
(`pixel_quadrature`: no generator noise; the closed form with n x n points per pixel and the lens samples
against the closed form with 40 x 40 points, by blur size: what set SHARP_BLUR_PX and CLOSED_FORM_MIN_BLUR_PX).

    python benchmarks/photometric/bench_photometric_forward.py [--quick 1] [--part 0|1|2] [--strata N]

`--part 1` the cases alone, `--part 2` the other sections alone (each to its own --out; the full run is both);
`--strata` the generator's aperture strata per side [12].

Writes benchmarks/results/photometric_forward.{json,md}. One torch thread.
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

from renderer.cameras import ThinLensCamera  # noqa: E402
from renderer.cameras.lens import Lens, Sensor  # noqa: E402
from camio.files import srgb_to_linear  # noqa: E402
from tiltfit.experiments import exact_capture as ec  # noqa: E402
from tiltfit.photometric import CLOSED_FORM_MIN_BLUR_PX  # noqa: E402
from tiltfit.photometric.render import (SHARP_BLUR_PX, SUBPIXELS, SUBPIXELS_SHARP,  # noqa: E402
                                        dark_fraction_disc, dark_fraction_samples, hammersley_disc_samples,
                                        pixel_blur_px, usable_pixels)
from tiltfit.target.layout import Target  # noqa: E402

W_PX, H_PX, PITCH_MM, W_MM, DIST_MM = 128, 96, 0.1, 50.0, 720.0
BOARD = Target(tuple(20.0 * i for i in range(5)), tuple(20.0 * j for j in range(4)), (0, 0), 12.0)
LOOK = ec.Board()


def focus_for_blur(blur_px: float, d_mm: float) -> float:
    """U0 (mm, nearer than the board) whose blur disc at the board's distance is `blur_px` wide."""
    return 1.0 / (1.0 / DIST_MM + blur_px * PITCH_MM / (W_MM * d_mm))


#: name: (blur at the board, px; d mm; lens tilt °; board rx°, ry°; shift of the board's centre in the image, mm)
CASES = {
    "sharp (0.7 px), facing": (0.7, 10.0, 0.0, 0.0, 10.0, (0, 0)),
    "sharp (0.7 px), inclined 60°": (0.7, 10.0, 0.0, 60.0, 10.0, (0, 0)),
    "2 px, facing": (2.0, 20.0, 0.0, 0.0, 10.0, (0, 0)),
    "4 px, facing": (4.0, 20.0, 0.0, 0.0, 10.0, (0, 0)),
    "4 px, inclined 35°": (4.0, 20.0, 0.0, 35.0, 10.0, (0, 0)),
    "4 px, inclined 60°": (4.0, 20.0, 0.0, 60.0, 10.0, (0, 0)),
    "4 px, off-centre": (4.0, 20.0, 0.0, 20.0, 10.0, (-12.0, -8.0)),
    "12 px (d 36 mm), facing": (12.0, 36.0, 0.0, 0.0, 10.0, (0, 0)),
    "12 px (d 36 mm), inclined 50°": (12.0, 36.0, 0.0, 50.0, 10.0, (0, 0)),
    "tilt +5°, inclined 20°": (None, 36.0, 5.0, 20.0, 10.0, (0, 0)),
    "tilt −5°, inclined 20°": (None, 36.0, -5.0, 20.0, 10.0, (0, 0)),
}
QUICK = ("2 px, facing", "12 px (d 36 mm), inclined 50°", "tilt +5°, inclined 20°")


def setup(case):
    blur, d, tilt, rx, ry, shift = CASES[case]
    U0 = focus_for_blur(blur, d) if blur is not None else 620.0
    lens = ec.ExactLens.focused_at(W_MM, U0, d, tilt, W_PX, H_PX, PITCH_MM)
    R, T = ec.pose_facing(BOARD, rx, ry, DIST_MM, shift)
    return lens, R, T


def model_camera(truth: dict, R, T, **change) -> ThinLensCamera:
    """The project's camera at the generator's truth (the calibration's w, U, d, θF; pose X = R X_b + T)."""
    p = {"w": truth["w_mm"], "U": truth["U_mm"], "d": truth["d_mm"], "theta_F": math.radians(truth["theta_F_deg"])}
    p.update(change)
    lens = Lens(p["w"], p["U"], p["d"], p["theta_F"], sensor=Sensor(W_PX, H_PX, PITCH_MM))
    return ThinLensCamera.from_calibration(lens, torch.tensor(R), torch.tensor(T))


def all_pixels() -> torch.Tensor:
    flat = torch.arange(W_PX * H_PX)
    return torch.stack([(flat % W_PX).to(torch.float64), (flat // W_PX).to(torch.float64)], -1)


def closed_form(cam, uv, blur_px, near) -> np.ndarray:
    """The closed form as the fit takes it: SUBPIXELS_SHARP points a side below SHARP_BLUR_PX, SUBPIXELS above."""
    sharp = torch.from_numpy(np.asarray(blur_px) < SHARP_BLUR_PX)
    out = np.empty(uv.shape[0])
    with torch.no_grad():
        for m, sub in ((sharp, SUBPIXELS_SHARP), (~sharp, SUBPIXELS)):
            if bool(m.any()):
                out[m.numpy()] = dark_fraction_disc(BOARD, cam, uv[m], near, sub).numpy()
    return out


def render_paths(cam, uv, blur_px) -> dict:
    """Dark fraction of every pixel by each of the forward model's paths."""
    near = max(len(BOARD.x_edges), len(BOARD.y_edges))
    closed = closed_form(cam, uv, blur_px, near)
    with torch.no_grad():
        s64 = dark_fraction_samples(BOARD, cam, uv, hammersley_disc_samples(64)).numpy()
        s256 = dark_fraction_samples(BOARD, cam, uv, hammersley_disc_samples(256)).numpy()
    auto = np.where(blur_px >= CLOSED_FORM_MIN_BLUR_PX, closed, s64)
    return {"closed form": closed, "samples 64": s64, "samples 256": s256, "auto": auto}


def implied_shift(cam_fn, truth, uv, pick, r, key, rel=1e-3, subpixels=SUBPIXELS) -> float:
    """The relative change of `key` (d or U) that best explains the residual r = model − exact (least squares on
    the closed form's central difference), in %."""
    near = max(len(BOARD.x_edges), len(BOARD.y_edges))
    base = {"d": truth["d_mm"], "U": truth["U_mm"]}[key]
    with torch.no_grad():
        up = dark_fraction_disc(BOARD, cam_fn(**{key: base * (1 + rel)}), uv[pick], near, subpixels).numpy()
        dn = dark_fraction_disc(BOARD, cam_fn(**{key: base * (1 - rel)}), uv[pick], near, subpixels).numpy()
    J = (up - dn) / (2 * rel)
    return float(-100.0 * (J @ r) / max(J @ J, 1e-300))


def measure_case(case: str, strata: int) -> dict:
    lens, R, T = setup(case)
    truth = lens.truth()
    t0 = time.perf_counter()
    rad = [ec.radiance(lens, R, T, BOARD, LOOK, aperture_strata=strata, seed=s) for s in (0, 1)]
    t_exact = (time.perf_counter() - t0) / 2
    Dg = [((LOOK.paper - r_) / (LOOK.paper - LOOK.ink)).reshape(-1) for r_ in rad]
    Dmean = 0.5 * (Dg[0] + Dg[1])
    cam = model_camera(truth, R, T)
    uv = all_pixels()
    ok = usable_pixels(BOARD, cam, uv)
    blur = pixel_blur_px(cam, uv).numpy()
    t0 = time.perf_counter()
    paths = render_paths(cam, uv, blur)
    t_model = time.perf_counter() - t0
    edge = ok & (Dmean > 0.03) & (Dmean < 0.97)
    noise = float(np.sqrt(((Dg[0] - Dg[1])[edge] ** 2).mean() / 2))
    hx, hy = (W_PX - 1) / 2, (H_PX - 1) / 2
    rho = np.hypot((uv[:, 0].numpy() - hx) / hx, (uv[:, 1].numpy() - hy) / hy) / math.sqrt(2)
    cam_fn = lambda **c: model_camera(truth, R, T, **c)  # noqa: E731
    rows = {}
    for name, D in paths.items():
        r = (D - Dmean)[edge]
        excess2 = float((r ** 2).mean()) - noise ** 2 / 2
        by_blur, by_rho = {}, {}
        for lo, hi in ((0, 1), (1, 3), (3, 8), (8, 1e9)):
            m = edge & (blur >= lo) & (blur < hi)
            if m.sum() >= 20:
                rr = (D - Dmean)[m]
                by_blur[f"{lo:g}-{hi:g}" if hi < 1e9 else f"{lo:g}+"] = {
                    "n": int(m.sum()), "mean": float(rr.mean()),
                    "excess_rms": math.sqrt(max(float((rr ** 2).mean()) - noise ** 2 / 2, 0.0))}
        for lo, hi in ((0, 0.35), (0.35, 0.7), (0.7, 1.01)):
            m = edge & (rho >= lo) & (rho < hi)
            if m.sum() >= 20:
                rr = (D - Dmean)[m]
                by_rho[f"{lo:g}-{hi:g}"] = {"n": int(m.sum()), "mean": float(rr.mean()),
                                           "excess_rms": math.sqrt(max(float((rr ** 2).mean()) - noise ** 2 / 2, 0.0))}
        pick = torch.from_numpy(np.flatnonzero(edge))
        rows[name] = {"mean": float(r.mean()), "rms": float(np.sqrt((r ** 2).mean())),
                      "excess_rms": math.sqrt(max(excess2, 0.0)), "excess_over_noise": math.sqrt(max(excess2, 0.0)) /
                      max(noise / math.sqrt(2), 1e-12),
                      "implied_d_pct": implied_shift(cam_fn, truth, uv, pick, r, "d"),
                      "implied_U_pct": implied_shift(cam_fn, truth, uv, pick, r, "U"),
                      "by_blur_px": by_blur, "by_radius": by_rho}
    # The generator's own noise on the same shift: what the implied shifts would scatter by with no mismatch.
    pick = torch.from_numpy(np.flatnonzero(edge))
    r_noise = ((Dg[0] - Dg[1]) / 2)[edge]
    noise_d = implied_shift(cam_fn, truth, uv, pick, r_noise, "d")
    return {"case": case, "truth": truth, "usable_pixels": int(ok.sum()), "edge_pixels": int(edge.sum()),
            "blur_px_median": float(np.median(blur[edge])) if edge.any() else None,
            "blur_px_range": [float(blur[edge].min()), float(blur[edge].max())] if edge.any() else None,
            "generator_noise_rms": noise, "noise_implied_d_pct": noise_d, "paths": rows,
            "seconds": {"exact_per_capture": t_exact, "model_all_paths": t_model}}


def srgb_and_gain(strata: int) -> dict:
    """8-bit sRGB decoding and the per-view levels, on a 4 px facing capture with shot and read noise."""
    lens, R, T = setup("4 px, facing")
    truth = lens.truth()
    sensor = ec.Sensor()
    rad = ec.radiance(lens, R, T, BOARD, LOOK, aperture_strata=strata, seed=3).reshape(-1)
    out = {}
    levels = []
    for seed in range(4):
        levels.append(srgb_to_linear(ec.expose(rad.reshape(H_PX, W_PX), sensor, seed=seed).astype(np.float64) / 255.0)
                      .reshape(-1))
    dec = np.mean(levels, 0)
    cam = model_camera(truth, R, T)
    uv = all_pixels()
    ok = usable_pixels(BOARD, cam, uv)
    D = (LOOK.paper - rad) / (LOOK.paper - LOOK.ink)
    for name, m in (("paper", ok & (D < 0.001)), ("ink", ok & (D > 0.999)), ("edges", ok & (D > 0.03) & (D < 0.97))):
        diff = dec[m] - rad[m]
        out[f"decoded_minus_linear_{name}"] = {"mean": float(diff.mean()),
                                              "sem": float(diff.std() / math.sqrt(max(diff.size, 1))),
                                              "relative": float(diff.mean() / max(rad[m].mean(), 1e-12))}
    # The levels a least-squares fit of I = white − (white − black) D puts on one 8-bit capture, at the true D.
    near = max(len(BOARD.x_edges), len(BOARD.y_edges))
    with torch.no_grad():
        Dm = dark_fraction_disc(BOARD, cam, uv, near).numpy()
    m = ok
    A = np.stack([1 - Dm[m], Dm[m]], 1)
    sol = np.linalg.lstsq(A, levels[0][m], rcond=None)[0]
    out["levels_fitted"] = {"white": float(sol[0]), "black": float(sol[1]), "white_truth": LOOK.paper,
                            "black_truth": LOOK.ink}
    return out


def pixel_area(strata: int) -> dict:
    """Closed form with 4 x 4 and 8 x 8 points per pixel against exact tracing on the sharp cases."""
    out = {}
    for case in ("sharp (0.7 px), facing", "sharp (0.7 px), inclined 60°"):
        lens, R, T = setup(case)
        truth = lens.truth()
        rad = [ec.radiance(lens, R, T, BOARD, LOOK, aperture_strata=strata, pixel_strata=8, seed=s) for s in (0, 1)]
        Dg = [((LOOK.paper - r_) / (LOOK.paper - LOOK.ink)).reshape(-1) for r_ in rad]
        Dmean = 0.5 * (Dg[0] + Dg[1])
        cam = model_camera(truth, R, T)
        uv = all_pixels()
        ok = usable_pixels(BOARD, cam, uv)
        edge = ok & (Dmean > 0.03) & (Dmean < 0.97)
        noise = float(np.sqrt(((Dg[0] - Dg[1])[edge] ** 2).mean() / 2))
        row = {"generator_noise_rms": noise, "edge_pixels": int(edge.sum())}
        near = max(len(BOARD.x_edges), len(BOARD.y_edges))
        for sub in (4, 8):
            with torch.no_grad():
                D = dark_fraction_disc(BOARD, cam, uv, near, subpixels=sub).numpy()
            r = (D - Dmean)[edge]
            row[f"closed form {sub}x{sub}"] = {"mean": float(r.mean()), "excess_rms": math.sqrt(max(
                float((r ** 2).mean()) - noise ** 2 / 2, 0.0))}
        out[case] = row
    return out


#: pixel_quadrature's geometries: name -> (lens tilt °, board rx°, ry°); and its blur sizes (px at the centre).
QUADRATURE_CASES = {"facing": (0.0, 0.0, 10.0), "tilt +5°, inclined 50°": (5.0, 50.0, 10.0)}
QUADRATURE_BLUR_PX = (1.0, 1.5, 2.0, 3.0, 6.0)


def pixel_quadrature(max_pixels: int = 200) -> dict:
    """The pixel's box alone: no generator, so no noise. On up to `max_pixels` edge pixels of each case, the closed
    form with n x n points per pixel (n = 4, 6, 8, stretched to the box's variance: `sub_points`) and the fixed lens
    samples (64, 256) against the closed form with 40 x 40 points, as the d that would explain the difference (%)
    and the RMS of D."""
    near = max(len(BOARD.x_edges), len(BOARD.y_edges))
    rng = np.random.default_rng(0)
    out = {}
    for name, (tilt, rx, ry) in QUADRATURE_CASES.items():
        rows = {}
        for blur in QUADRATURE_BLUR_PX:
            d = 20.0
            lens = ec.ExactLens.focused_at(W_MM, focus_for_blur(blur, d), d, tilt, W_PX, H_PX, PITCH_MM)
            R, T = ec.pose_facing(BOARD, rx, ry, DIST_MM)
            truth = lens.truth()
            cam_fn = lambda **c: model_camera(truth, R, T, **c)  # noqa: E731
            cam = cam_fn()
            uv = all_pixels()
            uv = uv[torch.from_numpy(usable_pixels(BOARD, cam, uv))]
            with torch.no_grad():
                ref = dark_fraction_disc(BOARD, cam, uv, near, 40).numpy()
            edge = np.flatnonzero((ref > 0.03) & (ref < 0.97))
            edge = np.sort(rng.choice(edge, min(edge.size, max_pixels), replace=False))
            u, ref = uv[torch.from_numpy(edge)], ref[edge]
            pick = torch.arange(u.shape[0])
            blur_px = pixel_blur_px(cam, u).numpy()
            row = {"pixels": int(u.shape[0]), "blur_px_range": [float(blur_px.min()), float(blur_px.max())]}
            with torch.no_grad():
                paths = {f"closed {n}x{n}": dark_fraction_disc(BOARD, cam, u, near, n).numpy() for n in (4, 6, 8)}
                for ns in (64, 256):
                    paths[f"samples {ns}"] = dark_fraction_samples(BOARD, cam, u, hammersley_disc_samples(ns)).numpy()
            paths["as fitted"] = np.where(blur_px >= CLOSED_FORM_MIN_BLUR_PX, closed_form(cam, u, blur_px, near),
                                          paths["samples 64"])
            for path, D in paths.items():
                r = D - ref
                row[path] = {"d_pct": implied_shift(cam_fn, truth, u, pick, r, "d", subpixels=40),
                             "rms": float(np.sqrt((r ** 2).mean()))}
            rows[f"{blur:g}"] = row
            print(f"quadrature {name} {blur:g} px", file=sys.stderr, flush=True)
        out[name] = rows
    return out


def measure(args) -> dict:
    torch.set_num_threads(1)
    strata = args.strata
    names = QUICK if args.quick else tuple(CASES) if args.part in (0, 1) else ()
    t0 = time.perf_counter()
    cases = []
    for name in names:
        print(f"case {name}", file=sys.stderr, flush=True)
        cases.append(measure_case(name, strata))
    extra = {} if args.quick or args.part == 1 else {
        "pixel_quadrature": pixel_quadrature(), "srgb_and_gain": srgb_and_gain(strata), "pixel_area": pixel_area(strata)}
    opts = "".join(f" --{k} {v}" for k, v in (("quick", args.quick), ("part", args.part), ("strata", args.strata))
                   if v != {"quick": 0, "part": 0, "strata": 12}[k])
    return {"command": "python benchmarks/photometric/bench_photometric_forward.py" + opts,
            "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "image": [W_PX, H_PX], "pitch_mm": PITCH_MM,
            "aperture_strata": strata, "pixel_strata": 4, "cases": cases, **extra,
            "wall_s": time.perf_counter() - t0}


def write_markdown(path: str, res: dict) -> None:
    L = ["# Photometric forward model against exact tracing (issue 30 §4)", "",
         f"`{res['command']}`, {res['created']}; {res['image'][0]} x {res['image'][1]} px, pitch "
         f"{res['pitch_mm']} mm, w 50 mm, board 4 x 3 cells of 20 mm at 720 mm; exact tracing "
         f"{res['aperture_strata']}² aperture x {res['pixel_strata']}² area samples per pixel, two seeds.", "",
         "Dark fraction D (0 paper, 1 ink) of the forward model at the generator's truth minus the exact capture's, "
         "on the usable edge pixels. *excess* is the RMS beyond the generator's own noise (in units of the noise of "
         "the two seeds' mean in the last column); *d %*, *U %* are the shifts of d and U that would best explain the "
         "difference (what it does to a fit); *noise d %* is the same for the generator's noise alone."]
    if res["cases"]:
        L += _case_lines(res)
    _extra_lines(L, res)
    L.append("")
    write_lines(path, L)


def _case_lines(res: dict) -> list:
    L = ["", "| case | blur px (median, range) | path | mean | excess RMS | excess / noise | d % | U % | noise d % |",
         "|---|---|---|---|---|---|---|---|---|"]
    for c in res["cases"]:
        lo, hi = c["blur_px_range"] or (math.nan, math.nan)
        for name, p in c["paths"].items():
            L.append(f"| {c['case']} | {c['blur_px_median']:.2f} ({lo:.2f}–{hi:.2f}) | {name} | {p['mean']:+.5f} | "
                     f"{p['excess_rms']:.5f} | {p['excess_over_noise']:.2f} | {p['implied_d_pct']:+.3f} | "
                     f"{p['implied_U_pct']:+.3f} | {c['noise_implied_d_pct']:+.3f} |")
    L += ["", "## By blur size and by position (path `auto`; mean / excess RMS of D)", "",
          "| case | blur px bins | radius bins (0 centre, 1 corner) |", "|---|---|---|"]
    for c in res["cases"]:
        p = c["paths"]["auto"]
        fb = ", ".join(f"{k}: {v['mean']:+.4f} / {v['excess_rms']:.4f} ({v['n']})" for k, v in p["by_blur_px"].items())
        fr = ", ".join(f"{k}: {v['mean']:+.4f} / {v['excess_rms']:.4f} ({v['n']})" for k, v in p["by_radius"].items())
        L.append(f"| {c['case']} | {fb} | {fr} |")
    L += ["", "## Time (same run)", "", "| case | exact capture s | forward model, all four paths s | ratio |",
          "|---|---|---|---|"]
    for c in res["cases"]:
        s = c["seconds"]
        L.append(f"| {c['case']} | {s['exact_per_capture']:.2f} | {s['model_all_paths']:.2f} | "
                 f"{s['exact_per_capture'] / max(s['model_all_paths'], 1e-9):.1f}x |")
    return L


def _extra_lines(L: list, res: dict) -> None:
    if "pixel_quadrature" in res:
        q = res["pixel_quadrature"]
        paths = [k for k in next(iter(next(iter(q.values())).values())) if k not in ("pixels", "blur_px_range")]
        L += ["", "## Pixel quadrature alone (no generator: against the closed form with 40 x 40 points per pixel)", "",
              "The d (%) a fit would take from each path's error alone (RMS of D in brackets), by the blur disc at the "
              f"board's centre; the fit now takes the closed form from {CLOSED_FORM_MIN_BLUR_PX:g} px with "
              f"{SUBPIXELS_SHARP} x {SUBPIXELS_SHARP} points below {SHARP_BLUR_PX:g} px (*as fitted*).", "",
              "| case | blur px (pixels' range) | " + " | ".join(paths) + " |", "|---|---|" + "---|" * len(paths)]
        for case, rows in q.items():
            for blur, row in rows.items():
                lo, hi = row["blur_px_range"]
                L.append(f"| {case} | {blur} ({lo:.2f}–{hi:.2f}) | " + " | ".join(
                    f"{row[p]['d_pct']:+.3f} ({row[p]['rms']:.4f})" for p in paths) + " |")
    if "srgb_and_gain" in res:
        g = res["srgb_and_gain"]
        L += ["", "## 8-bit sRGB decoding and the per-view levels (4 px, facing; Poisson + read noise, 4 captures)", "",
              "| pixels | decoded − linear (mean ± sem) | relative |", "|---|---|---|"]
        for k in ("paper", "ink", "edges"):
            v = g[f"decoded_minus_linear_{k}"]
            L.append(f"| {k} | {v['mean']:+.5f} ± {v['sem']:.5f} | {v['relative']:+.4f} |")
        lv = g["levels_fitted"]
        L += ["", f"Levels fitted to one 8-bit capture at the true D: white {lv['white']:.4f} (truth "
              f"{lv['white_truth']}), black {lv['black']:.4f} (truth {lv['black_truth']})."]
    if "pixel_area" in res:
        L += ["", "## The pixel's area on sharp edges (closed form, points per pixel; exact capture 8 x 8 area samples)",
              "", "| case | generator noise | 4 x 4: mean / excess | 8 x 8: mean / excess |", "|---|---|---|---|"]
        for case, row in res["pixel_area"].items():
            a, b = row["closed form 4x4"], row["closed form 8x8"]
            L.append(f"| {case} | {row['generator_noise_rms']:.4f} | {a['mean']:+.4f} / {a['excess_rms']:.4f} | "
                     f"{b['mean']:+.4f} / {b['excess_rms']:.4f} |")


if __name__ == "__main__":
    sys.exit(run_benchmark(__doc__, "photometric_forward", measure, write_markdown, quick=0, part=0, strata=12))
