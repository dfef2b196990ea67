"""Why the widths' fit converges slowly on the sharp real sets (issue 32 §1): blur that differs with the edge's
direction, which the fitted model (one diameter a point, b(x) = |β + g · (x − p)|, the same for every edge) can only
mimic with a V-shaped b through zero inside the bands.

For every `--every`-th photo of the real sets (tiltfit's cached corners, as `bench_blur_smoothness.py`), the widths
are measured as usual (`tiltfit.detect.blur.measure_blur`); at each fit of the passes after the first, the same bands
are fitted again split in two by the edge's direction, each half with the same model and start: the bands along the
more horizontal edges of the image against the more vertical ones, and the bands along edges pointing at the image
centre (radial) against those across (tangential). Per set: the diameters of the halves (medians, and the share of
points where they differ by more than 3 σ of their difference), the share of points where the joint fit's b passes
through zero inside a band (the V), and the share of joint fits still moving after their 30 iterations. Diameters
are in the fit's pyramid-level pixels.

    python benchmarks/history/diag_blur_anisotropy.py [--every 2] [--out STEM]
"""
from __future__ import annotations

import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # the repository root
sys.path.insert(0, HERE)

from benchmarks.results_io import run_benchmark, write_lines  # noqa: E402


def _split(groups, by: str):
    """Per point, (bands of the first kind, bands of the second) or None where either is empty: by "axes", the bands
    whose edge is more horizontal in the image first; by "radial", the bands whose edge points within 45° of the
    image centre's direction first (`centre`: the level image's centre)."""
    out = []
    for g in groups:
        first, second = [], []
        for b in g:
            w = b["w"][:, None]
            along = (b["dxy"] * w).sum(0) / w.sum()  # the band's mean offset from the point: along its edge
            if by == "axes":
                one = abs(along[0]) > abs(along[1])
            else:
                point = (b["px"] - b["dxy"])[0]
                radial = point - _split.centre
                one = abs(along @ radial) > abs(along[0] * radial[1] - along[1] * radial[0])
            (first if one else second).append(b)
        out.append((first, second) if first and second else None)
    return out


def measure(args) -> dict:
    import torch

    import tiltfit
    from camio.files import read_image
    from tiltfit.detect import blur as B
    from tiltfit.detect.imaging import to_gray

    sys.path.insert(0, os.path.join(HERE, "benchmarks", "detection"))
    from bench_blur_smoothness import SETS, _photos

    torch.set_num_threads(1)
    fit, lm = B.fit_corners, B.batched_levenberg_marquardt
    rows, record = [], {}

    def solver(*a, **k):
        sol = lm(*a, **k)
        record["converged"] = sol.converged.numpy()
        record["x"] = sol.x.numpy()
        return sol

    def fit_and_split(img, groups, r0, iterations=30):
        out = fit(img, groups, r0, iterations)
        if iterations < 30:  # the first pass: finds the blur only
            return out
        conv, x = record["converged"], record["x"]
        stats = record.setdefault("later", dict(points=0, moving=0, v=0, pairs={"axes": [], "radial": []}))
        stats["points"] += len(groups)
        stats["moving"] += int((~conv).sum())
        for c, g in enumerate(groups):  # b = β + g · dxy changes sign inside a band (weights > 0): the V
            sb = np.concatenate([x[c, 0] + b["dxy"] @ x[c, 1:3] for b in g])
            stats["v"] += int(np.any(np.sign(sb) != np.sign(x[c, 0])))
        _split.centre = np.array([img.shape[1], img.shape[0]]) / 2.0 - 0.5
        for by in ("axes", "radial"):
            halves = _split(groups, by)
            keep = [i for i, h in enumerate(halves) if h is not None]
            if not keep:
                continue
            res = [fit(img, [halves[i][j] for i in keep], r0[keep], iterations) for j in (0, 1)]
            (b1, s1, _, ok1), (b2, s2, _, ok2) = res
            ok = ok1 & ok2
            stats["pairs"][by] += list(zip(b1[ok], s1[ok], b2[ok], s2[ok]))
        return out

    B.fit_corners, B.batched_levenberg_marquardt = fit_and_split, solver
    try:
        for set_name, (photos_dir, cache_dir) in SETS.items():
            target, photos = _photos(photos_dir, cache_dir, args.every)
            record.pop("later", None)
            for name, corners in photos:
                B.measure_blur(to_gray(read_image(os.path.join(photos_dir, name))), target, corners)
                print(f"[diag_blur_anisotropy] {set_name} {name}", file=sys.stderr, flush=True)
            st = record.get("later", dict(points=0, moving=0, v=0, pairs={"axes": [], "radial": []}))
            row = {"set": set_name, "images": len(photos), "later_fits": st["points"],
                   "moving_after_30": st["moving"], "v_shaped": st["v"]}
            for by, pairs in st["pairs"].items():
                p = np.array(pairs).reshape(-1, 4)
                diff = np.abs(p[:, 0] - p[:, 2]) / np.hypot(p[:, 1], p[:, 3])
                row[by] = {"points": len(p), "median_first": float(np.median(p[:, 0])) if len(p) else None,
                           "median_second": float(np.median(p[:, 2])) if len(p) else None,
                           "median_ratio": float(np.median(p[:, 0] / np.maximum(p[:, 2], 1e-9))) if len(p) else None,
                           "differ_3_sigma": int(np.sum(diff > 3))}
            rows.append(row)
    finally:
        B.fit_corners, B.batched_levenberg_marquardt = fit, lm
    return {"rows": rows, "every": args.every, "tiltfit": os.path.dirname(tiltfit.__file__)}


def write_markdown(path, res):
    lines = ["# Blur widths by edge direction on the real sets", "",
             f"`python benchmarks/history/diag_blur_anisotropy.py --every {res['every']}` (tiltfit from "
             f"`{res['tiltfit']}`): the fits of the passes after the first (one a point and pass), repeated on the "
             "bands of each edge direction alone; diameters in the fit's pyramid-level pixels, medians. V: the joint "
             "fit's b = β + g · (x − p) passes through zero inside a band; moving: the joint fit not converged in its "
             "30 iterations; differ: the two halves' diameters differ by more than 3 σ of their difference.", "",
             "| set | images | later fits | V-shaped | moving after 30 | horizontal-edge b | vertical-edge b | "
             "ratio | differ > 3σ | radial-edge b | tangential-edge b | ratio | differ > 3σ |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in res["rows"]:
        cells = []
        for by in ("axes", "radial"):
            s = r.get(by)
            cells += ([f"{s['median_first']:.2f}", f"{s['median_second']:.2f}", f"{s['median_ratio']:.2f}",
                       f"{s['differ_3_sigma']} of {s['points']}"] if s and s["points"] else ["–"] * 4)
        lines.append(f"| {r['set']} | {r['images']} | {r['later_fits']} | {r['v_shaped']} | {r['moving_after_30']} | "
                     + " | ".join(cells) + " |")
    write_lines(path, lines + [""])


if __name__ == "__main__":
    sys.exit(run_benchmark(__doc__, "blur_anisotropy", measure, write_markdown, every=2))
