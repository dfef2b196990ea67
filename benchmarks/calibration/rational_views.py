"""How many views determine a distortion model: the fitted radial mapping's 1σ at the image corner (pixels,
propagated from the fit's covariance, `tiltfit.select.held_out.mapping_sigma_px`) and the coefficients, for the first
n GoPro views (data/real/gopro_wide, tiltfit's cached detections). Issue 24: `--distortion rational` from one
view wrote coefficients of 3.6e5; it is now refused where that σ exceeds `MAX_MAPPING_SIGMA_PX`.

    python benchmarks/calibration/rational_views.py [-o benchmarks/results/rational_views.json]   # and .md beside it
"""
from __future__ import annotations

import argparse
import json
import os
import re
import sys

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
DATA = os.path.join(ROOT, "data", "real", "gopro_wide")


def main(argv=None) -> int:
    from tiltfit.calibrate.flow import calibrate
    from tiltfit.calibrate.fit import FitError, FitOptions
    from tiltfit.calibrate.model import Observations
    from tiltfit.target.layout import load_target
    from tiltfit.select.held_out import MAX_MAPPING_SIGMA_PX, mapping_sigma_px

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-o", "--output", default=os.path.join(ROOT, "benchmarks", "results", "rational_views.json"))
    args = ap.parse_args(argv)
    target = load_target(os.path.join(DATA, "target.json"))
    with open(os.path.join(DATA, "detections_tiltfit.json"), encoding="utf-8") as f:
        dets = json.load(f)
    names = sorted(k for k, v in dets.items() if "no_board" not in v)
    rows = []
    for model in ("rational", "opencv5", "k1k2", "k1"):
        for n in (1, 2, 3, 5, 10, len(names)):
            ns = names[:n]
            C = np.array([[c if c is not None else [np.nan, np.nan] for c in dets[k]["corners_px"]] for k in ns])
            B = np.array([[b if b is not None else np.nan for b in dets[k]["blur_px"]] for k in ns], dtype=float)
            obs = Observations(target.feature_points(), C.astype(float), B, tuple(dets[ns[0]]["image_size_px"]),
                               0.00155, ns)
            row = {"model": model, "views": n}
            try:
                res = calibrate(obs, "unified", options=FitOptions(distortion=model))
                row.update(mapping_sigma_px=round(mapping_sigma_px(res), 3),
                           coefficients=[float(f"{c:.4g}") for c in res.camera.distortion.tolist()],
                           rms_px=round(float(np.sqrt(res.rss["corners"] / max(res.rss["n_corners"] // 2, 1))), 4))
            except FitError as e:
                row["refused"] = str(e)
            rows.append(row)
            print(json.dumps(row), file=sys.stderr, flush=True)
    res = {"max_mapping_sigma_px": MAX_MAPPING_SIGMA_PX, "data": "data/real/gopro_wide (first n views, sorted)",
           "rows": rows}
    with open(args.output, "w", encoding="utf-8") as f:
        json.dump(res, f, indent=1)
    write_markdown(os.path.splitext(args.output)[0] + ".md", res)
    return 0


def write_markdown(path: str, res: dict) -> None:
    """The table of `res` (one row a model and view count) as the results page quotes it."""
    lines = ["# Distortion models against the number of views", "",
             "The fitted radial mapping's 1σ at the image corner (pixels, propagated from the fit's covariance, "
             "`tiltfit.select.held_out.mapping_sigma_px`) for the first n GoPro views (data/real/gopro_wide, cached "
             f"detections), default options otherwise. A named model is refused above {res['max_mapping_sigma_px']} px "
             "or where its terms are undetermined. `python benchmarks/calibration/rational_views.py`.", "",
             "| model | views | mapping σ at the corner (px) | max abs coefficient | RMS (px) | outcome |",
             "|---|---:|---:|---:|---:|---|"]
    for r in res["rows"]:
        if "refused" in r:
            sigma = re.search(r"uncertain by ±([0-9.]+) px", r["refused"])
            why = re.search(r"(its denominator term .*? is not determined|the fit found no consistent solution)",
                            r["refused"])
            lines.append(f"| {r['model']} | {r['views']} | {sigma.group(1) if sigma else ''} | | | refused"
                         + (f": {why.group(1)}" if why else "") + " |")
        else:
            top = max(abs(c) for c in r["coefficients"])
            lines.append(f"| {r['model']} | {r['views']} | {r['mapping_sigma_px']:.3g} | {top:.3g} | "
                         f"{r['rms_px']:.3g} | fitted |")
    with open(path, "w", encoding="utf-8") as f:
        f.write("\n".join(lines) + "\n")


if __name__ == "__main__":
    sys.exit(main())
