"""Whole calibration records of the default calibration on six real sets, and their comparison between two trees:
the check that a speed change changed no output (issue 32 §0: the same choices, notes and warnings; f and pp within
1e-3 σ; every recorded number within 1e-6 relative).

    cd TREE && python /path/to/calib_records.py write OUT.json [--sets a,b]    (the code of the tree in the cwd)
    python benchmarks/calibration/calib_records.py compare BEFORE.json AFTER.json [--rel 1e-6]

A record is `tiltfit.files.calib.calib_dict` of `fit_with_held_out(obs, "unified", FitOptions(distortion="auto",
board="auto"))` (CALIB.json's content without its run time and date) with the result's notes and warnings. Sets:
sony_small, gopro_wide, industrial_ds1, industrial_60 (`bench_calib_real_speed.observations`), charuco_webcam4
(tests/data/charuco_webcam's 4 frames) and charuco_webcam (the published corners of
/work/shared/data/real/charuco_webcam, 47 frames). `compare` exits with status 1 where a record differs.
"""
from __future__ import annotations

import argparse
import csv
import json
import math
import os
import sys

SETS = ("sony_small", "charuco_webcam4", "charuco_webcam", "gopro_wide", "industrial_ds1", "industrial_60")
CHARUCO_WEBCAM = "/work/shared/data/real/charuco_webcam/published_corners_cam0.csv"
#: Keys that change from run to run.
VOLATILE = ("runtime_s", "created", "date", "seconds")


def _charuco(path: str, frame: str, corner: str, x: str, y: str):
    """Observations of the inverted ChArUco board's 3 × 4 corners (54 mm squares, id k at column k % 3, row k // 3)."""
    import numpy as np

    from tiltfit.calibrate.model import Observations

    rows = list(csv.DictReader(open(path)))
    frames = sorted({int(r[frame]) for r in rows})
    pts = np.array([[(k % 3 + 1) * 54.0, (k // 3 + 1) * 54.0, 0.0] for k in range(12)])
    uv = np.full((len(frames), 12, 2), np.nan)
    for r in rows:
        uv[frames.index(int(r[frame])), int(r[corner])] = float(r[x]), float(r[y])
    return Observations(pts, uv, np.full(uv.shape[:2], np.nan), (1280, 720), 0.003, [f"frame_{f}" for f in frames])


def observations(name: str, root: str):
    if name == "charuco_webcam4":
        return _charuco(os.path.join(root, "tests", "data", "charuco_webcam", "published_corners_4views.csv"),
                        "frame", "corner_id", "x_px", "y_px")
    if name == "charuco_webcam":
        return _charuco(CHARUCO_WEBCAM, "frame_index", "keypoint_id", "img_loc_x", "img_loc_y")
    sys.path.insert(0, os.path.join(root, "benchmarks", "calibration"))
    from bench_calib_real_speed import observations as real

    return real(name, root)


def _clean(o):
    if isinstance(o, dict):
        return {k: _clean(v) for k, v in o.items() if k not in VOLATILE}
    if isinstance(o, (list, tuple)):
        return [_clean(v) for v in o]
    return "nan" if isinstance(o, float) and o != o else o


def write(out: str, sets) -> None:
    root = os.getcwd()
    sys.path.insert(0, root)
    import torch

    torch.set_num_threads(1)
    from tiltfit.calibrate.fit import FitOptions
    from tiltfit.calibrate.photos import fit_with_held_out
    from tiltfit.files.calib import calib_dict

    records = {}
    for name in sets:
        res, used, held = fit_with_held_out(observations(name, root), "unified",
                                            options=FitOptions(distortion="auto", board="auto"))
        d = calib_dict(res, obs=used, held_out=held) | {"_notes": list(res.notes), "_warnings": list(res.warnings)}
        records[name] = _clean(json.loads(json.dumps(d, default=str)))
        print(f"{name}: {res.distortion_model}, board {getattr(res.board, 'model', 'flat')}", flush=True)
    with open(out, "w") as f:
        json.dump(records, f)


def _leaves(a, b, path: str, out: list) -> None:
    """(relative difference, path) of every leaf; inf where strings, booleans, integers or the structure differ."""
    if isinstance(a, dict) and isinstance(b, dict):
        if set(a) != set(b):
            out.append((math.inf, f"{path} keys {sorted(set(a) ^ set(b))}"))
            return
        for k in a:
            _leaves(a[k], b[k], f"{path}.{k}", out)
    elif isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            out.append((math.inf, f"{path} lengths {len(a)}, {len(b)}"))
            return
        for i, (u, v) in enumerate(zip(a, b)):
            _leaves(u, v, f"{path}[{i}]", out)
    elif isinstance(a, float) and isinstance(b, (int, float)) or isinstance(b, float) and isinstance(a, int):
        d = 0.0 if a == b or abs(a - b) < 1e-13 else abs(a - b) / max(abs(a), abs(b))
        out.append((d, f"{path} {a!r} {b!r}"))
    elif a != b:
        out.append((math.inf, f"{path} {str(a)[:160]!r} {str(b)[:160]!r}"))


def _in_sigma(a: dict, b: dict) -> float:
    """The largest difference of f (w) and the principal point in units of their σ (`a`'s)."""
    def z(x, y, s):
        return 0.0 if x == y else abs(x - y) / max(s, 1e-300)
    out = [z(a["w_mm"], b["w_mm"], a["sigma"]["w_mm"])]
    out += [z(a["principal_point_px"][i], b["principal_point_px"][i], a["sigma"]["principal_point_px"][i])
            for i in range(2)]
    return max(out)


def compare(before: str, after: str, rel: float) -> int:
    a, b = json.load(open(before)), json.load(open(after))
    bad = False
    for name in a:
        leaves = []
        _leaves(a[name], b.get(name), name, leaves)
        leaves.sort(key=lambda t: -t[0])
        over = [t for t in leaves if t[0] > rel]
        zs = _in_sigma(a[name], b[name])
        bad |= bool(over) or zs > 1e-3
        print(f"{name}: {len(leaves)} leaves, largest relative difference {leaves[0][0]:.2e} ({leaves[0][1][:120]}); "
              f"over {rel:g}: {len(over)}; f, pp within {zs:.1e} σ")
        for d, p in over[:10]:
            print(f"    {d:.2e} {p[:240]}")
    print("DIFFER" if bad else f"SAME: every number within {rel:g} relative, f and pp within 1e-3 σ")
    return int(bad)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    w = sub.add_parser("write")
    w.add_argument("out")
    w.add_argument("--sets", default=",".join(SETS))
    c = sub.add_parser("compare")
    c.add_argument("before")
    c.add_argument("after")
    c.add_argument("--rel", type=float, default=1e-6)
    args = p.parse_args()
    if args.cmd == "write":
        write(args.out, args.sets.split(","))
        return 0
    return compare(args.before, args.after, args.rel)


if __name__ == "__main__":
    sys.exit(main())
