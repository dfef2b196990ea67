"""Is the photometric fit's σ honest (issue 22)? Predicted σ against the spread of its estimates, in one run:

1. Monte Carlo on captures of the independent simulator (tests/tiltfit/test_photometric_independent.py: a
   physical tilted thin lens, its own jittered sampling, a grey wall, a gamma tone curve read as sRGB, an
   illumination gradient, glare, 8 bits) with each view's own geometric error (every sensor point displaced by a
   quadratic field drawn per view and per draw: a board that is not flat, a print that is not the ideal grid;
   tests/tiltfit/test_photometric_sigma.py). Each draw: new noise, jitter and fields; the refinement starts from
   one corner fit (of draw 0). Ratio = RMS over the draws of the predicted σ / standard deviation of the
   estimates (1 is honest), for the three σ the fit computes: `sigma` (per-view cluster-robust, the one
   reported), `sigma_tiles` (sandwich over blur-disc tiles, the σ reported before) and `sigma_gauss_newton`
   (textbook).
2. Real subsets of one session: data/real/industrial_ds1 split in 2 interleaved halves, data/real/gopro_wide in 3
   (tiltfit's cached corners); each subset: corner fit (unified, free principal point, opencv5), the refinement
   of it on the subset's photos as `tiltfit calibrate --refine photometric` runs it (0 lens samples, 1,000 pixels
   a megapixel view, the trust region, held-out pixels and the k-fold corner check), then spread/σ pooled over
   the pairs of subsets, sqrt(mean Δ² / (σa² + σb²)) (1 is honest; one or three independent differences per
   parameter, so it is noisy), for the refinement's three σ, for the corner fit's σ and for what CALIB.json
   carries (the refinement's values and σ where it is kept, else the corner fit's).

    python benchmarks/photometric/bench_photometric_sigma.py [--draws 24] [--sets industrial_ds1 gopro_wide]
        [--warp-px 0.3 0] [--out benchmarks/results/photometric_sigma] [--markdown-only]

One torch thread. Writes OUT.json and OUT.md.
"""
from __future__ import annotations

import argparse
import itertools
import json
import math
import os
import sys
import time

import numpy as np
import torch

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, "tests", "tiltfit"))

from benchmarks.results_io import add_output_options, markdown_only, save  # noqa: E402

KEYS = ("w_mm", "U_mm", "d_mm", "theta_F_deg", "theta_L_deg")
SIGMAS = ("sigma", "sigma_tiles", "sigma_gauss_newton")
SIGMA_NAMES = {"sigma": "views (reported)", "sigma_tiles": "tiles (before)", "sigma_gauss_newton": "Gauss–Newton"}
REAL = {"industrial_ds1": {"pitch_mm": 0.0048, "distortion": "opencv5", "groups": 2},
        "gopro_wide": {"pitch_mm": 0.005, "distortion": "opencv5", "groups": 3}}
#: Lens parameter (stored) freed by the refinement -> the keys it moves.
MOVES = {"log_w_mm": ("w_mm",), "inv_U_per_m": ("U_mm",), "d_scaled": ("d_mm",),
         "theta_F": ("theta_F_deg", "theta_L_deg")}


def say(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def monte_carlo(case: str, draws: int, views: int, max_pixels: int, warp_px: float, trust_region: bool = True) -> dict:
    import test_photometric_sigma as mc

    t_cpu, t = time.process_time(), time.perf_counter()
    out = mc.monte_carlo(case, draws, mc.VIEWS[:views], warp_px, max_pixels, lens_rings=2, lens_sectors=4,
                         say=lambda m: say(m), trust_region=trust_region)
    out |= {"case": case, "draws": draws, "views": views, "max_pixels": max_pixels, "warp_px": warp_px,
            "trust_region": trust_region,
            "ratios": {w: mc.ratios(out, w) for w in SIGMAS},
            "spread": {k: float(np.std([r["values"][k] for r in out["rows"]], ddof=1)) for k in KEYS},
            "mean_error": {k: float(np.mean([r["values"][k] for r in out["rows"]]) - out["truth"][k]) for k in KEYS},
            "rms_sigma": {w: {k: float(math.sqrt(np.mean([r[w][k] ** 2 for r in out["rows"]]))) for k in KEYS}
                          for w in SIGMAS},
            "cpu_s": time.process_time() - t_cpu, "wall_s": time.perf_counter() - t}
    return out


def real_subset(name: str, obs, views: list, target, folder: str) -> dict:
    from benchmarks.photometric.photometric_start import corner_start, grey_photos
    from tiltfit.photometric import PhotometricError, PhotometricOptions, refine_photometric

    cfg = REAL[name]
    sub = obs.subset(views)
    start = corner_start(sub, target, cfg["distortion"])   # the peer's time: OpenCV on the same corners
    corner, corner_s, kfold, opencv_s = start["corner"], start["corner_s"], start["kfold"], start["opencv_s"]
    images = grey_photos(folder, sub.names)
    t_cpu, t = time.process_time(), time.perf_counter()
    base = {"views": len(views), "names": list(sub.names), "corner_fit": {k: corner.values.get(k) for k in KEYS},
            "corner_fit_sigma": {k: corner.sigma.get(k) for k in KEYS}, "corner_sigma_model": dict(corner.sigma_model),
            "corner_fit_s": corner_s, "opencv_s": opencv_s}
    try:
        res = refine_photometric(images, target, corner.camera,
                                 PhotometricOptions(lens_samples=0,
                                                    max_pixels=1000 if images[0].size >= 1 << 20 else 2000),
                                 start_sigma=corner.sigma, corners=sub, corner_held_out_px=kfold["rms_px"],
                                 start_covariance=corner.intrinsics_covariance)
    except PhotometricError as e:   # `tiltfit calibrate --refine photometric` stops with this message
        say(f"[{name}] views {views[0]}, {views[1]}, …: refinement failed: {e}")
        return base | {"failed": str(e), "kept": "—", "rejected_because": f"failed: {e}", "free": [],
                       "calib": base["corner_fit"], "calib_sigma": base["corner_fit_sigma"]}
    ph_s, ph_cpu = time.perf_counter() - t, time.process_time() - t_cpu
    moved = [k for p in res.free for k in MOVES[p]]
    out = {"views": len(views), "names": list(sub.names), "kept": res.kept, "rejected_because": res.rejected_because,
           "free": res.free, "moved": moved, "sigma_model": res.sigma_model,
           "corner_fit": {k: corner.values.get(k) for k in KEYS}, "corner_fit_sigma": {k: corner.sigma.get(k) for k in KEYS},
           "corner_sigma_model": dict(corner.sigma_model),
           "photometric": {k: res.values[k] for k in KEYS}, **{f"photometric_{w}": {k: getattr(res, w)[k] for k in KEYS}
                                                                for w in SIGMAS},
           "photometric_sigma_held": {k: (res.sigma_held or {}).get(k, 0.0) for k in KEYS},
           "photometric_wall_s": ph_s, "photometric_cpu_s": ph_cpu, "corner_fit_s": corner_s, "opencv_s": opencv_s}
    # What CALIB.json carries: the refinement's values and σ where it is kept, else the corner fit's.
    ph = res.kept == "photometric"
    out["calib"] = {k: out["photometric" if ph and k in moved else "corner_fit"][k] for k in KEYS}
    out["calib_sigma"] = {k: (res.sigma if ph and k in moved else corner.sigma).get(k) for k in KEYS}
    say(f"[{name}] views {views[0]}, {views[1]}, …: kept {res.kept} ({res.rejected_because or 'held-out evidence'}); "
        + ", ".join(f"{k} {res.values[k]:.4f} ± {res.sigma[k]:.4f} (corner {corner.values[k]:.4f} ± "
                    f"{corner.sigma[k]:.4f})" for k in KEYS) + f"; {ph_s:.1f} s")
    return out


def pooled(subsets: list, value: str, sigma: str, key: str):
    """sqrt(mean over pairs of Δ² / (σa² + σb²)), None where a σ is missing or 0 (held) and, for the refinement,
    where the subsets' refinements did not free the same lens parameters (their models differ: U held at the
    start's placeholder in one, fitted in another)."""
    if value == "photometric":
        subsets = [s for s in subsets if "failed" not in s]   # the refinement stopped on a subset
        if len({tuple(s["free"]) for s in subsets}) > 1:
            return None
    terms = []
    for a, b in itertools.combinations(subsets, 2):
        va, vb, sa, sb = a[value][key], b[value][key], a[sigma][key], b[sigma][key]
        if None in (va, vb, sa, sb) or not (sa > 0 and sb > 0) or not all(map(math.isfinite, (va, vb, sa, sb))):
            return None
        terms.append((va - vb) ** 2 / (sa ** 2 + sb ** 2))
    return math.sqrt(sum(terms) / len(terms)) if terms else None


def real(name: str) -> dict:
    from tests.real_detections import observations
    from tiltfit.target.layout import load_target

    cfg = REAL[name]
    folder = os.path.join(ROOT, "data", "real", name)
    target = load_target(os.path.join(folder, "target.json"))
    obs, _ = observations(folder, cfg["pitch_mm"])
    K = cfg["groups"]
    subsets = [real_subset(name, obs, list(range(g, obs.n_views, K)), target, folder) for g in range(K)]
    spread = {}
    for k in KEYS:
        row = {f"photometric_{w}": pooled(subsets, "photometric", f"photometric_{w}", k) for w in SIGMAS}
        row["corner_fit"] = pooled(subsets, "corner_fit", "corner_fit_sigma", k)
        row["calib"] = pooled(subsets, "calib", "calib_sigma", k)
        spread[k] = row
    return {"set": name, "groups": K, "distortion": cfg["distortion"], "subsets": subsets, "spread_over_sigma": spread}


def _f(x, fmt=".3g"):
    return "—" if x is None or (isinstance(x, float) and not math.isfinite(x)) else format(x, fmt)


def write_markdown(path: str, res: dict) -> None:
    meta = res["meta"]
    L = ["# Photometric σ: predicted against empirical", "",
         f"Generated by `{meta['command']}`, {meta['date']} (module docstring: what is measured). One torch thread, "
         "2 cores shared with other jobs.", "",
         "Three σ of the same photometric fit: **views** (`sigma`, reported from now on: per-view cluster-robust, "
         "views as clusters, each view's pose, levels and illumination profiled out, CR2 correction, never below the "
         "textbook σ), **tiles** (`sigma_tiles`: the sandwich over blur-disc tiles that `sigma` was before) and "
         "**Gauss–Newton** (`sigma_gauss_newton`, independent pixels).", ""]
    for mc in res["monte_carlo"]:
        bound = [r["at_bound"] for r in mc["rows"] if r["at_bound"]]
        L += [f"## Monte Carlo: {mc['draws']} draws, {mc['case']}, {mc['views']} views, {mc['max_pixels']} pixels a view, "
              + (f"per-view quadratic displacement σ {mc['warp_px']} px a coefficient" if mc["warp_px"] else
                 "noise alone (no per-view displacement)")
              + ("" if mc.get("trust_region", True) else ", no trust region (every lens parameter free)"), "",
              f"Freed: {', '.join(mc['free'])}; draws that ended with a parameter at its trust bound (its σ 0 there, "
              f"the corner fit kept): {len(bound)}"
              + (f" ({', '.join(sorted({p for b in bound for p in b}))})" if bound else "") +
              f". {mc['cpu_s']:.0f} CPU s" + (f" (measured by `{mc['from']}`)" if mc.get("from") else "") +
              ". Ratio = RMS predicted σ / empirical spread "
              "(1 is honest; with this many draws a ratio is known to about ±" +
              f"{100 / math.sqrt(2 * (mc['draws'] - 1)):.0f} %).", "",
              "| parameter | truth | mean error | empirical spread | " + " | ".join(
                  f"{SIGMA_NAMES[w]} σ (ratio)" for w in SIGMAS) + " |", "|---|---|---|---|---|---|---|"]
        for k in KEYS:
            L.append(f"| {k} | {mc['truth'][k]:.4g} | {mc['mean_error'][k]:+.3g} | {mc['spread'][k]:.3g} | " + " | ".join(
                f"{mc['rms_sigma'][w][k]:.3g} ({mc['ratios'][w][k]:.2f})" for w in SIGMAS) + " |")
        L.append("")
    if res["real"]:
        L += ["## Real subsets of one session: spread/σ pooled over pairs, sqrt(mean Δ² / (σa² + σb²))", "",
              "Each subset: corner fit (unified, free principal point, opencv5) and the refinement as `tiltfit calibrate "
              "--refine photometric` runs it. *CALIB.json* is what the file carries: the refinement's values and σ "
              "where it is kept (for the parameters it moved), else the corner fit's (per-view σ, `tiltfit.uncertainty.covariance`). "
              "— : held (σ 0) in a subset, or (photometric columns) the subsets' refinements freed different lens "
              "parameters, so their models differ.", "",
              "Photometric σ: *views* includes the held principal point's and distortion's uncertainty (the corner "
              "fit's, propagated: `sigma_held`, shown as [held …] below); *tiles* and *Gauss–Newton* are conditional "
              "on them.", "",
              "| set | parameter | photometric, views σ | photometric, tiles σ | photometric, Gauss–Newton σ | "
              "corner fit σ | CALIB.json |", "|---|---|---|---|---|---|---|"]
        for r in res["real"]:
            for k in KEYS:
                s = r["spread_over_sigma"][k]
                L.append(f"| {r['set']} ({r['groups']} subsets) | {k} | " + " | ".join(
                    _f(s[c], ".2f") for c in ("photometric_sigma", "photometric_sigma_tiles",
                                              "photometric_sigma_gauss_newton", "corner_fit", "calib")) + " |")
        L += ["", "| set | subset | views | kept | why not | freed | design effect | " + " | ".join(
            f"{k}: photometric ± views σ (tiles, GN) / corner fit ± σ" for k in ("w_mm", "U_mm", "d_mm")) +
              " | photometric s / view | OpenCV s | photometric / OpenCV |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in res["real"]:
            for g, s in enumerate(r["subsets"]):
                if "failed" in s:
                    L.append(f"| {r['set']} | {g + 1} | {s['views']} | — | refinement failed: {s['failed']} | — | — | "
                             + " | ".join(f"— / {_f(s['corner_fit'][k], '.4g')} ± {_f(s['corner_fit_sigma'][k])}"
                                          for k in ("w_mm", "U_mm", "d_mm")) + " | — | "
                             f"{s['opencv_s']:.3f} | — |")
                    continue
                cells = []
                for k in ("w_mm", "U_mm", "d_mm"):
                    cells.append(f"{s['photometric'][k]:.4g} ± {_f(s['photometric_sigma'][k])} "
                                 f"[held {_f(s.get('photometric_sigma_held', {}).get(k))}] "
                                 f"({_f(s['photometric_sigma_tiles'][k])}, {_f(s['photometric_sigma_gauss_newton'][k])}) / "
                                 f"{_f(s['corner_fit'][k], '.4g')} ± {_f(s['corner_fit_sigma'][k])}")
                de = s["sigma_model"].get("design_effect")
                L.append(f"| {r['set']} | {g + 1} | {s['views']} | {s['kept']} | {s['rejected_because'] or '—'} | "
                         f"{', '.join(s['free'])} | {_f(de, '.2f')} | " + " | ".join(cells) +
                         f" | {s['photometric_wall_s'] / s['views']:.2f} | {s['opencv_s']:.3f} | "
                         f"{s['photometric_wall_s'] / max(s['opencv_s'], 1e-9):.0f}x |")
    L.append("")
    with open(path, "w", encoding="utf-8") as f:
        f.write("\n".join(L))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=24, help="Monte Carlo draws [24]")
    ap.add_argument("--views", type=int, default=6, help="views of the Monte Carlo captures (at most 6) [6]")
    ap.add_argument("--max-pixels", type=int, default=400, help="pixels a view in the Monte Carlo [400]")
    ap.add_argument("--warp-px", type=float, nargs="*", default=[0.3, 0.0],
                    help="σ of each displacement coefficient (px), one Monte Carlo each [0.3 0] (0: noise alone)")
    ap.add_argument("--cases", nargs="*", default=["heavy blur"], help="simulator cases [heavy blur]")
    ap.add_argument("--sets", nargs="*", default=list(REAL), help="real sets [industrial_ds1 gopro_wide]")
    ap.add_argument("--no-trust-region", action="store_true",
                    help="Monte Carlo refinements without the corner fit's trust region (every lens parameter free)")
    ap.add_argument("--monte-carlo-from", metavar="JSON", nargs="*",
                    help="take the Monte Carlo part from earlier OUT.json files instead of running it")
    add_output_options(ap, "photometric_sigma")
    args = ap.parse_args(argv)
    if markdown_only(args, write_markdown):
        return 0
    torch.set_num_threads(1)
    command = "python benchmarks/photometric/bench_photometric_sigma.py " + " ".join(argv if argv is not None else sys.argv[1:])
    if args.monte_carlo_from:
        mcs = []
        for path in args.monte_carlo_from:
            with open(path, encoding="utf-8") as f:
                earlier = json.load(f)
            mcs += [m | {"from": f"{earlier['meta']['command']} ({earlier['meta']['date']}; {path})"}
                    for m in earlier["monte_carlo"]]
    else:
        mcs = [monte_carlo(c, args.draws, args.views, args.max_pixels, w, not args.no_trust_region)
               for c in args.cases for w in args.warp_px]
    reals = [real(name) for name in args.sets]
    res = {"meta": {"command": command.strip(), "date": time.strftime("%Y-%m-%dT%H:%M:%S%z")},
           "monte_carlo": mcs, "real": reals}
    save(args.out, res, write_markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
