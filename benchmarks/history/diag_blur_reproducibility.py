"""How reproducible the blur widths of the real photos are under changes of floating-point rounding alone.

For each image (every `--every`-th of a set), on the corners of the current `detect`, the blur widths of
`tiltfit.detect.blur.measure_blur` are computed three ways:
- `rev`: the code at git revision REV (`--rev`, extracted with `git archive`);
- `rev_reordered`: the same code with one sum in `pixel_esf` evaluated in another order,
  (G2₁ + G2₄) − (G2₂ + G2₃) instead of G2₁ − G2₂ − G2₃ + G2₄: mathematically identical, only the
  rounding differs;
- `current`: the working tree's code.
Counted: points whose width moves from `rev`'s by more than 1 and 3 of `rev`'s standard deviations. Where
`rev_reordered` already moves many points, the measurement is not reproducible at that level and the same
counts for `current` are no sign of a changed method.

Writes benchmarks/results/blur_reproducibility.{json,md}. Usage:
    python benchmarks/history/diag_blur_reproducibility.py --rev fc99d87 [--every 3]
"""
from __future__ import annotations

import argparse
import glob
import importlib.util
import os
import shutil
import subprocess
import sys
import tempfile

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))  # the repository root: benchmarks.results_io
from benchmarks.results_io import add_output_options, markdown_only, save  # noqa: E402
from camio.files import read_image  # noqa: E402
from tiltfit.detect import blur as current  # noqa: E402
from tiltfit.detect.chessboard import detect, to_gray  # noqa: E402
from tiltfit.detect.imaging import build_pyramid  # noqa: E402
from tiltfit.target.layout import load_target  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SETS = {"gopro_wide": "*.jpg", "industrial_ds1": "*.png"}
ORIGINAL_SUM = "    G2u = (_G2(u) * sgn).sum(-1)\n"
REORDERED_SUM = "    G2 = _G2(u)\n    G2u = (G2[..., 0] + G2[..., 3]) - (G2[..., 1] + G2[..., 2])\n"


def load_module(path: str, name: str):
    """tiltfit/detect/blur.py from another checkout, as a module of the installed package (its relative imports)."""
    spec = importlib.util.spec_from_file_location(f"tiltfit.{name}", path)
    module = importlib.util.module_from_spec(spec)
    module.__package__ = "tiltfit"
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def revision_blur_modules(rev: str):
    folder = tempfile.mkdtemp(prefix="blur_rev_")
    try:
        text = subprocess.run(["git", "-C", ROOT, "show", f"{rev}:tiltfit/detect/blur.py"], check=True, capture_output=True,
                              text=True).stdout
        assert ORIGINAL_SUM in text, f"{rev}: tiltfit/detect/blur.py has no `{ORIGINAL_SUM.strip()}` to reorder"
        paths = {}
        for name, body in (("rev", text), ("rev_reordered", text.replace(ORIGINAL_SUM, REORDERED_SUM))):
            paths[name] = os.path.join(folder, f"blur_{name}.py")
            with open(paths[name], "w") as f:
                f.write(body)
        return {name: load_module(p, f"blur_{name}") for name, p in paths.items()}
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def write_markdown(path: str, res: dict) -> None:
    md = ["# Blur widths of the real photos under changes of rounding alone", "",
          f"`{res['command']}`: on the corners of the current `detect`, blur widths by tiltfit {res['rev']} "
          "(`rev`), by the same code with one sum of `pixel_esf` in another order (`rev_reordered`, "
          "mathematically identical), and by the current code; points moved from `rev` by more than 1 and 3 σ "
          "(`rev`'s standard deviation).", "",
          "| set | images | points | rev_reordered: > 1 σ | > 3 σ | median | current: > 1 σ | > 3 σ | median |",
          "|---|---|---|---|---|---|---|---|---|"]
    for name, s in res["sets"].items():
        a, b = s["rev_reordered"], s["current"]
        md.append(f"| {name} | {s['images']} | {s['points']} | {a['over_1']} | {a['over_3']} | {a['median']} | "
                  f"{b['over_1']} | {b['over_3']} | {b['median']} |")
    md.append("")
    with open(path, "w") as f:
        f.write("\n".join(md))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rev", default="fc99d87")
    ap.add_argument("--every", type=int, default=3)
    add_output_options(ap, "blur_reproducibility")
    args = ap.parse_args(argv)
    if markdown_only(args, write_markdown):
        return
    torch.set_num_threads(1)
    mods = revision_blur_modules(args.rev)
    mods["current"] = current
    res = {"command": "python benchmarks/history/diag_blur_reproducibility.py " + " ".join(
        argv if argv is not None else sys.argv[1:]), "rev": args.rev, "sets": {}}
    for name, pattern in SETS.items():
        folder = os.path.join(ROOT, "data", "real", name)
        target = load_target(os.path.join(folder, "target.json"))
        z = {"rev_reordered": [], "current": []}
        paths = sorted(glob.glob(os.path.join(folder, pattern)))[:: args.every]
        for path in paths:
            gray = to_gray(read_image(path))
            levels = build_pyramid(gray)
            corners = detect(gray, target, measure_blur=False).corners_px
            b0, s0 = mods["rev"].measure_blur(gray, target, corners, levels=levels)
            for key in z:
                b1, _ = mods[key].measure_blur(gray, target, corners, levels=levels)
                ok = np.isfinite(b0) & np.isfinite(b1) & (s0 > 0)
                z[key].append(np.abs(b1[ok] - b0[ok]) / s0[ok])
            print(f"{name}/{os.path.basename(path)}: " + ", ".join(
                f"{k} {int((v[-1] > 1).sum())} > 1 σ" for k, v in z.items()), flush=True)
        s = {"images": len(paths), "points": int(sum(v.size for v in z["current"]))}
        for key, v in z.items():
            v = np.concatenate(v)
            s[key] = {"over_1": int((v > 1).sum()), "over_3": int((v > 3).sum()),
                      "median": round(float(np.median(v)), 4)}
        res["sets"][name] = s
    save(args.out, res, write_markdown)


if __name__ == "__main__":
    main()
