"""Is the widths' fitted gradient g the blur field's gradient? (issue 32 §1: bounding g by what the board can produce)

The widths' model has one diameter a point varying linearly along its bands, b(x) = |β + g · (x − p)|. If g were
the gradient of the blur over the board (thin lens: b = w d |1/U − 1/z|, smooth in board position), it would agree
with the gradient the neighbouring points' widths show. For every `--every`-th photo of the real sets (tiltfit's
cached corners, as `bench_blur_smoothness.py`), the widths are measured as usual (`measure_blur`); per point, the g of
its last fit in a pass after the first (signed as the gradient of b = |β|: g · sign β) is compared with the gradient
fitted by weighted least squares to the differences of the final widths at its (up to 4) grid neighbours
(b_j − b_k = ∇b · (x_j − x_k), weights 1/(σ_j² + σ_k²); s: its standard error, the mean of the two axes').
Gradients are diameter per pixel (the same at every pyramid level).

    python benchmarks/history/diag_blur_gradient.py [--every 2] [--out STEM]
"""
from __future__ import annotations

import math
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # the repository root
sys.path.insert(0, HERE)

from benchmarks.results_io import run_benchmark, write_lines  # noqa: E402


def neighbour_gradient(blur: np.ndarray, sigma: np.ndarray, corners_px: np.ndarray, grid_shape, k: int):
    """(∇b (2,), its standard error) at point k from its grid neighbours' widths, or None (< 2 neighbours)."""
    ny, nx = grid_shape
    j, i = divmod(k, nx)
    D, y, v = [], [], []
    for jj, ii in ((j - 1, i), (j + 1, i), (j, i - 1), (j, i + 1)):
        m = jj * nx + ii
        if 0 <= jj < ny and 0 <= ii < nx and np.isfinite(blur[m]) and np.isfinite(sigma[m]):
            D.append(corners_px[m] - corners_px[k])
            y.append(blur[m] - blur[k])
            v.append(sigma[m] ** 2 + sigma[k] ** 2)
    if len(D) < 2:
        return None
    D, y, v = np.array(D), np.array(y), np.array(v)
    M = D.T @ (D / v[:, None])
    if np.linalg.cond(M) > 1e6:
        return None
    cov = np.linalg.inv(M)
    return cov @ (D.T @ (y / v)), math.sqrt(np.trace(cov) / 2)


def measure(args) -> dict:
    import torch

    import tiltfit
    from camio.files import read_image
    from tiltfit.detect import blur as B
    from tiltfit.detect.imaging import to_gray

    sys.path.insert(0, os.path.join(HERE, "benchmarks", "detection"))
    from bench_blur_smoothness import SETS, _photos

    torch.set_num_threads(1)
    fit, lm, half = B.fit_corners, B.batched_levenberg_marquardt, B._half_edges
    record = {"keys": [], "x": None, "g": {}}

    def bands(target, ks, *a, **k):
        out = half(target, ks, *a, **k)
        record["keys"] += [int(c) for c, bk in zip(ks, out) if bk]
        return out

    def solver(*a, **k):
        sol = lm(*a, **k)
        record["x"] = sol.x.numpy()
        return sol

    def fit_and_keep(img, groups, r0, iterations=30, **k):
        out = fit(img, groups, r0, iterations, **k)
        keys, record["keys"] = record["keys"], []
        if iterations == 30:  # a pass after the first
            x = record["x"]
            for c, key in enumerate(keys):
                record["g"][key] = x[c, 1:3] * np.sign(x[c, 0])
        return out

    rows = []
    B.fit_corners, B.batched_levenberg_marquardt, B._half_edges = fit_and_keep, solver, bands
    try:
        for set_name, (photos_dir, cache_dir) in SETS.items():
            target, photos = _photos(photos_dir, cache_dir, args.every)
            fitted, nb, se = [], [], []
            for name, corners in photos:
                record["g"] = {}
                blur, sigma = B.measure_blur(to_gray(read_image(os.path.join(photos_dir, name))), target, corners)
                for key, g in record["g"].items():
                    got = neighbour_gradient(blur, sigma, corners, target.grid_shape, key) if np.isfinite(blur[key]) else None
                    if got is not None:
                        fitted.append(g), nb.append(got[0]), se.append(got[1])
                print(f"[diag_blur_gradient] {set_name} {name}", file=sys.stderr, flush=True)
            f, n, s = np.array(fitted).reshape(-1, 2), np.array(nb).reshape(-1, 2), np.array(se)
            z = np.hypot(*(f - n).T) / s
            rows.append({"set": set_name, "images": len(photos), "points": len(s),
                         "fitted": float(np.median(np.hypot(*f.T))), "neighbours": float(np.median(np.hypot(*n.T))),
                         "se": float(np.median(s)), "difference": float(np.median(np.hypot(*(f - n).T))),
                         "corr_x": float(np.corrcoef(f[:, 0], n[:, 0])[0, 1]),
                         "corr_y": float(np.corrcoef(f[:, 1], n[:, 1])[0, 1]), "over_3se": int(np.sum(z > 3))})
    finally:
        B.fit_corners, B.batched_levenberg_marquardt, B._half_edges = fit, lm, half
    return {"rows": rows, "every": args.every, "tiltfit": os.path.dirname(tiltfit.__file__)}


def write_markdown(path, res):
    lines = ["# The widths' fitted gradient against the neighbours' widths on the real sets", "",
             f"`python benchmarks/history/diag_blur_gradient.py --every {res['every']}` (tiltfit from "
             f"`{res['tiltfit']}`): per point, g of its last fit after the first pass (the gradient of b = |β|) "
             "against the gradient the final widths at its grid neighbours show (weighted least squares; s its "
             "standard error); |·| medians, diameter per pixel; corr: Pearson correlation of the two, per image "
             "axis.", "",
             "| set | images | points | fitted \\|g\\| | neighbours' \\|∇b\\| | s | \\|g − ∇b\\| | corr x | corr y | "
             "\\|g − ∇b\\| > 3 s |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in res["rows"]:
        lines.append(f"| {r['set']} | {r['images']} | {r['points']} | {r['fitted']:.4f} | {r['neighbours']:.4f} | "
                     f"{r['se']:.4f} | {r['difference']:.4f} | {r['corr_x']:+.2f} | {r['corr_y']:+.2f} | "
                     f"{r['over_3se']} |")
    write_lines(path, lines + [""])


if __name__ == "__main__":
    sys.exit(run_benchmark(__doc__, "blur_gradient", measure, write_markdown, every=2))
