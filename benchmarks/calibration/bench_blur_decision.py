"""What the calibration decides about the blur model on the shipped real photos: refused (U and d not written) or
used, the widths' noise, the blur the model explains, and the blur residuals' trend with depth.

Sets: GoPro (all 35 views with a board, the README's first 12, the set split in three both as contiguous thirds
and round-robin), industrial_ds1 (all 20 views, halves). `tiltfit.calibrate.flow.calibrate` with `tiltfit
calibrate`'s defaults (distortion and board auto) on tiltfit's cached detections (tests/real_detections.py).

    python benchmarks/calibration/bench_blur_decision.py [--out benchmarks/results/blur_decision] [--markdown-only]
"""
from __future__ import annotations

import argparse
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from tests.real_detections import REAL, observations  # noqa: E402
from benchmarks.results_io import add_output_options, markdown_only, save  # noqa: E402

from tiltfit.calibrate.flow import calibrate  # noqa: E402
from tiltfit.calibrate.fit import FitError, FitOptions  # noqa: E402
from tiltfit.calibrate.model import Observations  # noqa: E402

PITCH_MM = {"gopro_wide": 0.005, "industrial_ds1": 0.0048}


def subsets(n_views: int, set_name: str) -> dict:
    if set_name == "gopro_wide":
        third = -(-n_views // 3)
        out = {"all": range(n_views), "README's first 12": range(12)}
        out.update({f"third {k + 1} (contiguous)": range(k * third, min(n_views, (k + 1) * third)) for k in range(3)})
        out.update({f"third {k + 1} (round-robin)": range(k, n_views, 3) for k in range(3)})
        return out
    half = n_views // 2
    return {"all": range(n_views), "first half": range(half), "second half": range(half, n_views)}


def run_one(obs: Observations, idx) -> dict:
    idx = list(idx)
    sub = Observations(obs.points_mm, obs.corners_px[idx], obs.blur_px[idx], obs.image_size_px, obs.pixel_pitch_mm,
                       [obs.names[i] for i in idx])
    try:
        res = calibrate(sub, "unified", options=FitOptions(distortion="auto", board="auto"))
    except FitError as e:
        return {"views": len(idx), "error": str(e)}
    blur = res.model_selection.get("blur", {})
    return {"views": len(idx), "board": res.board.model if res.board is not None else "flat",
            "U_mm": res.values.get("U_mm") if "U_mm" not in res.undetermined else None,
            "sigma_U_mm": res.sigma.get("U_mm") if "U_mm" not in res.undetermined else None,
            "blur": blur, "warnings": res.warnings}


def write_markdown(path: str, res: dict) -> None:
    lines = ["# The blur model's decision on the real sets", "",
             "`python benchmarks/calibration/bench_blur_decision.py`: `calibrate` with the command line's defaults on the cached "
             "detections. U written only where the blur model is used; *refused*: why (the widths' noise σ_n from "
             "neighbouring corners, on the target file's points). Trend: the blur residuals' quadratic trend with "
             "depth (Huber, per-view cluster-robust Wald χ²(2)); warned where p < 1e-3 and its change ≥ 0.5 σ_n.",
             "",
             "| set | views | board | U (mm) | σ_n (px) | blur model | trend change (px) | trend p | warned |",
             "|---|---|---|---|---|---|---|---|---|"]
    for row in res["rows"]:
        if "error" in row:
            lines.append(f"| {row['set']}: {row['subset']} | {row['views']} | fit failed: {row['error']} ||||||")
            continue
        b, t = row["blur"], row["blur"].get("trend_with_depth") or {}
        U = "—" if row["U_mm"] is None else f"{row['U_mm']:.0f} ± {row['sigma_U_mm']:.2g}"
        used = "used" if b.get("used") else f"refused: {b.get('why_not') or 'U undetermined'}"
        lines.append(f"| {row['set']}: {row['subset']} | {row['views']} | {row['board']} | {U} | "
                     f"{b.get('noise_px', float('nan')):.3g} | {used} | "
                     + (f"{t['amplitude_px']:.2g} | {t['p_value']:.1g} | {'yes' if t['significant'] else 'no'} |"
                        if t else "— | — | — |"))
    with open(path, "w", encoding="utf-8") as f:
        f.write("\n".join(lines) + "\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_output_options(ap, "blur_decision")
    args = ap.parse_args(argv)
    if markdown_only(args, write_markdown):
        return 0
    rows = []
    for set_name, pitch in PITCH_MM.items():
        obs, _ = observations(os.path.join(REAL, set_name), pitch)
        for label, idx in subsets(obs.n_views, set_name).items():
            row = run_one(obs, idx)
            rows.append({"set": set_name, "subset": label, **row})
            print(f"[bench_blur_decision] {set_name} {label}: U {row.get('U_mm')}", file=sys.stderr, flush=True)
    save(args.out, {"rows": rows}, write_markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
