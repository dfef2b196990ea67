"""The photometric fit's time before and after a change, on the slow tests' own fits (issue 32 §4).

The captures and starts of the test suite's slowest photometric fits (tests/tiltfit/test_photometric.py), made
once by this checkout and fitted by the code of two trees in subprocesses (`--before REV`, extracted with
`git archive`, and this checkout or `--after REV`), one after the other in the same run:

- kernel: `test_kernel_selection_finds_a_gaussian_where_there_is_one`'s two fits (kernel `auto`, 128 lens
  samples, 700 pixels a view, 2 views at 342 x 228; the captures blurred by a Gaussian of σ 1.2 px, then plain);
- biased +5°: `test_photometric_fit_meets_the_targets_where_corners_are_biased[5.0]`'s fit (the closed-form
  aperture, 20,000 pixels a view, 3 views at 684 x 456, 128 spp captures, started from the corner fit);
- sigma: `test_photometric_sigma_covers_the_error_over_noise_draws`'s three fits (500 pixels, 3 views at 171 x 114);
- forward: the forward model alone (no Jacobian) on 20,000 pixels of a kernel view: the lens samples (64, 256) and
  the closed form (4 x 4 points a pixel);
- real: `tiltfit calibrate ... --refine photometric` with its defaults on the first 4 photos with a board of
  data/real/industrial_ds1 and gopro_wide (`photometric_start.calibrate_refined_cached`, detections from the cache;
  distorted lenses, so the focus geometry goes point by point): wall seconds of the whole command (the corner fit
  included) and CALIB.json's photometric values.

CPU seconds of the worker process (one torch thread) after a warm-up fit (imports); the fitted values of both
trees side by side, their difference in units of the fit's own σ, and each fit's error against the captures'
truth. The peer is the code before the change (OpenCV has no photometric fit).

    python benchmarks/photometric/bench_photometric_fit_speed.py [--before REV] [--after REV] [--out PATH]

writes benchmarks/results/photometric_fit_speed.{md,json}.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))
RESULTS = os.path.join(ROOT, "benchmarks", "results")
KEYS = ("w_mm", "U_mm", "d_mm", "theta_L_deg", "theta_F_deg", "psf_sigma_px")
#: Real sets -> pixel pitch (mm), as bench_photometric_real_bounds.py takes them.
REAL_SETS = {"industrial_ds1": 0.0048, "gopro_wide": 0.005}


def make_cases(path: str) -> None:
    """The slow tests' captures and starts (their own helpers), saved for the workers."""
    import cv2
    import torch

    sys.path.insert(0, os.path.join(ROOT, "tests", "tiltfit"))
    import test_photometric as tp

    torch.set_num_threads(1)
    images, poses, truth = tp._captures(U0_mm=700.0, views=(0, 1))
    kernel = {"images": images, "blurred": [cv2.GaussianBlur(im, (0, 0), 1.2, borderType=cv2.BORDER_REFLECT)
                                            for im in images],
              "start": tp._camera(tp._perturbed_init(poses, truth, scale=0.5), images, truth["pitch"]),
              "truth": {"w_mm": tp.W_MM, "U_mm": truth["U_mm"], "d_mm": tp.D_MM, "theta_L_deg": tp.THETA_L_DEG}}
    images, poses, truth = tp._captures(U0_mm=760.0, spp=128, downscale=8, theta_L_deg=5.0)
    biased = {"images": images, "start": tp._corner_fit(images, tp.BOARD, truth["pitch"]).camera,
              "truth": {"w_mm": tp.W_MM, "U_mm": truth["U_mm"], "d_mm": tp.D_MM, "theta_L_deg": 5.0}}
    sigma = []
    for seed in range(3):
        images, poses, truth = tp._captures(U0_mm=1000.0, spp=32, downscale=32, seed=seed)
        sigma.append({"images": images, "start": tp._camera(tp._perturbed_init(poses, truth, seed=seed + 1), images,
                                                            truth["pitch"]),
                      "truth": {"w_mm": tp.W_MM, "U_mm": truth["U_mm"], "d_mm": tp.D_MM,
                                "theta_L_deg": tp.THETA_L_DEG}})
    torch.save({"kernel": kernel, "biased": biased, "sigma": sigma, "board": tp.BOARD}, path)


def _record(res, truth: dict) -> dict:
    values = {k: float(res.values[k]) for k in KEYS}
    sigma = {k: float(res.sigma[k]) for k in KEYS if k in res.sigma}
    return {"values": values, "sigma": sigma, "kernel": res.values["kernel"], "rms": float(res.rms),
            "iterations": int(res.iterations), "kept": res.kept,
            "error": {k: values[k] - v for k, v in truth.items()}}


def worker(cases_path: str, out_path: str) -> None:
    """Run in a tree (on sys.path first): every fit once after a warm-up, CPU seconds and the values."""
    import numpy as np
    import torch

    torch.set_num_threads(1)
    from tiltfit.photometric import PhotometricOptions, refine_photometric
    from tiltfit.photometric.render import dark_fraction_disc, dark_fraction_samples, hammersley_disc_samples

    cases = torch.load(cases_path, weights_only=False)
    board = cases["board"]
    s0 = cases["sigma"][0]
    refine_photometric(s0["images"], board, s0["start"], PhotometricOptions(lens_samples=64, max_pixels=500))
    out = {"fits": {}, "forward": {}}

    def timed(name, fn):
        t = time.process_time()
        got = fn()
        out["fits"][name] = {"cpu_s": time.process_time() - t, "results": got}
        print(f"{name}: {out['fits'][name]['cpu_s']:.1f} CPU s", file=sys.stderr, flush=True)

    k = cases["kernel"]
    opts = PhotometricOptions(kernel="auto", lens_samples=128, max_pixels=700)
    timed("kernel (2 fits)", lambda: [_record(refine_photometric(k["blurred"], board, k["start"], opts), k["truth"]),
                                      _record(refine_photometric(k["images"], board, k["start"], opts), k["truth"])])
    b = cases["biased"]
    timed("biased +5° (1 fit)", lambda: [_record(refine_photometric(b["images"], board, b["start"],
                                                                     PhotometricOptions(max_pixels=20000)),
                                                  b["truth"])])
    timed("sigma (3 fits)", lambda: [_record(refine_photometric(c["images"], board, c["start"],
                                                                PhotometricOptions(lens_samples=64, max_pixels=500,
                                                                                   seed=seed)), c["truth"])
                                     for seed, c in enumerate(cases["sigma"])])
    cam = k["start"].double().view_camera(1)
    rng = np.random.default_rng(0)
    h, w = k["images"][0].shape
    uv = torch.tensor(np.stack([rng.uniform(0, w, 20000), rng.uniform(0, h, 20000)], -1))
    near = max(len(board.x_edges), len(board.y_edges))
    paths = {"lens samples 64": lambda: dark_fraction_samples(board, cam, uv, hammersley_disc_samples(64)),
             "lens samples 256": lambda: dark_fraction_samples(board, cam, uv, hammersley_disc_samples(256)),
             "closed form 4x4": lambda: dark_fraction_disc(board, cam, uv, near)}
    with torch.no_grad():
        for name, fn in paths.items():
            times = []
            for _ in range(3):
                t = time.process_time()
                D = fn()
                times.append(time.process_time() - t)
            out["forward"][name] = {"cpu_s": float(np.median(times)), "D": D.numpy().tolist()}
    from benchmarks.photometric.photometric_start import calibrate_refined_cached

    out["real"] = {}
    for name, pitch in REAL_SETS.items():
        path = out_path + f".{name}.CALIB.json"
        t = time.process_time()
        _, _, status, wall = calibrate_refined_cached(name, pitch, 4, path)
        calib = json.load(open(path)) if os.path.isfile(path) else {}
        ph = calib.get("photometric") or {}
        out["real"][name] = {"status": status, "wall_s": wall, "cpu_s": time.process_time() - t,
                             "kept": ph.get("kept", calib.get("refinement")),
                             "values": {k: calib.get(k) for k in ("w_mm", "U_mm", "d_mm", "theta_F_deg")},
                             "refined": {k: (ph.get("refined") or ph).get(k) for k in ("w_mm", "U_mm", "d_mm")},
                             "sigma": {k: (ph.get("sigma") or {}).get(k) for k in ("w_mm", "U_mm", "d_mm")},
                             "photometric": ph}
        print(f"{name}: {wall:.1f} s wall", file=sys.stderr, flush=True)
    with open(out_path, "w") as f:
        json.dump(out, f)


def _tree(rev: str, where: str) -> str:
    """`git archive` of `rev` unpacked under `where`."""
    path = os.path.join(where, rev)
    os.makedirs(path)
    archive = subprocess.run(["git", "-C", ROOT, "archive", rev], check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", path], input=archive, check=True)
    return path


def _run_worker(tree: str, cases: str, out: str) -> dict:
    env = {**os.environ, "PYTHONPATH": tree, "OMP_NUM_THREADS": "1"}
    code = (f"import sys; sys.path.insert(0, {tree!r}); sys.path.insert(1, {HERE!r}); "
            f"import bench_photometric_fit_speed as b; b.worker({cases!r}, {out!r})")
    subprocess.run([sys.executable, "-c", code], check=True, env=env, cwd=tree)
    with open(out) as f:
        return json.load(f)


def compare(before: dict, after: dict) -> dict:
    """Per fit: CPU before, after, their ratio; the largest |after − before| / σ over the lens values; the
    forward paths' times and their largest difference in D."""
    rows = {}
    for name, a in after["fits"].items():
        b = before["fits"][name]
        shift = 0.0
        for rb, ra in zip(b["results"], a["results"]):
            for key, s in rb["sigma"].items():
                if s > 0 and math.isfinite(s):
                    shift = max(shift, abs(ra["values"][key] - rb["values"][key]) / s)
        rows[name] = {"before_cpu_s": b["cpu_s"], "after_cpu_s": a["cpu_s"], "speed_up": b["cpu_s"] / a["cpu_s"],
                      "max_shift_sigma": shift}
    forward = {}
    for name, a in after["forward"].items():
        b = before["forward"][name]
        diff = max(abs(x - y) for x, y in zip(a["D"], b["D"]))
        forward[name] = {"before_cpu_s": b["cpu_s"], "after_cpu_s": a["cpu_s"], "speed_up": b["cpu_s"] / a["cpu_s"],
                         "max_abs_dD": diff}
    real = {}
    for name, a in after.get("real", {}).items():
        b = before.get("real", {}).get(name)
        if b:
            real[name] = {"before_wall_s": b["wall_s"], "after_wall_s": a["wall_s"], "before_cpu_s": b.get("cpu_s"),
                          "after_cpu_s": a.get("cpu_s"), "before_kept": b["kept"],
                          "after_kept": a["kept"], "before": b["values"], "after": a["values"]}
    return {"fits": rows, "forward": forward, "real": real}


def _num(v, decimals: int | None = None) -> str:
    if v is None:
        return "—"
    return f"{v:.{decimals}f}" if decimals is not None else f"{v:.8g}"


def write_markdown(path: str, res: dict) -> None:
    c = res["comparison"]
    L = ["# The photometric fit's time before and after (the slow tests' own fits, same run)", "",
         f"Before: {res['before_rev']}; after: {res['after_rev']}. `{res['command']}`, {res['created']}; one torch thread, "
         f"CPU seconds of each tree's worker process (after a warm-up fit), the 2 shared cores' load average "
         f"{res['load']:.1f} at the end. Captures made once by this checkout (the tests' own helpers).", "",
         "| fit | before CPU s | after CPU s | speed-up | largest change of a lens value (units of its σ) |",
         "|---|---|---|---|---|"]
    for name, r in c["fits"].items():
        L.append(f"| {name} | {r['before_cpu_s']:.1f} | {r['after_cpu_s']:.1f} | {r['speed_up']:.1f}x | "
                 f"{r['max_shift_sigma']:.1e} |")
    L += ["", "Forward model alone (20,000 pixels of a 342 x 228 view, blur about 9 px; median of 3):", "",
          "| path | before CPU s | after CPU s | speed-up | largest |ΔD| |", "|---|---|---|---|---|"]
    for name, r in c["forward"].items():
        L.append(f"| {name} | {r['before_cpu_s']:.3f} | {r['after_cpu_s']:.3f} | {r['speed_up']:.1f}x | "
                 f"{r['max_abs_dD']:.1e} |")
    if c.get("real"):
        L += ["", "Real photos, `tiltfit calibrate ... --refine photometric` with its defaults on 4 photos (CPU and wall "
              "s of the whole command, the corner calibration included, so commits between the two revisions outside "
              "the photometric fit count too; CALIB.json's lens, the refinement's where kept):", "",
              "| set | CPU s before | after | wall s before | after | kept before | after | w mm before | after | "
              "U mm before | after | d mm before | after |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for name, r in c["real"].items():
            vals = " | ".join(f"{_num(r['before'].get(k))} | {_num(r['after'].get(k))}" for k in ("w_mm", "U_mm", "d_mm"))
            L.append(f"| {name} | {_num(r.get('before_cpu_s'), 1)} | {_num(r.get('after_cpu_s'), 1)} | "
                     f"{r['before_wall_s']:.1f} | {r['after_wall_s']:.1f} | {r['before_kept']} | "
                     f"{r['after_kept']} | {vals} |")
    L += ["", "Fitted values (error against the captures' truth: θL °, U and d %, w %; σ the fit's own):", "",
          "| fit | code | kernel | θL err ° | σ θL ° | U err % | d err % | w err % | Gaussian σ px | RMS | iterations |",
          "|---|---|---|---|---|---|---|---|---|---|---|"]
    for name in c["fits"]:
        for code in ("before", "after"):
            for i, r in enumerate(res[code]["fits"][name]["results"]):
                e, v = r["error"], r["values"]
                t = {k: v[k] - e[k] for k in e}
                L.append(f"| {name} #{i + 1} | {code} | {r['kernel']} | {e['theta_L_deg']:+.5f} | "
                         f"{r['sigma']['theta_L_deg']:.5f} | {100 * e['U_mm'] / t['U_mm']:+.4f} | "
                         f"{100 * e['d_mm'] / t['d_mm']:+.4f} | {100 * e['w_mm'] / t['w_mm']:+.4f} | "
                         f"{v['psf_sigma_px']:.4f} | {r['rms']:.6f} | {r['iterations']} |")
    with open(path, "w") as f:
        f.write("\n".join(L) + "\n")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", default="8c1f30a", help="revision to compare with [8c1f30a]")
    ap.add_argument("--after", default=None, help="revision to measure [the working tree]")
    ap.add_argument("--out", default=os.path.join(RESULTS, "photometric_fit_speed"),
                    help="results path without extension")
    ap.add_argument("--markdown-only", action="store_true", help="rewrite OUT.md from OUT.json (no timing)")
    args = ap.parse_args()
    if args.markdown_only:
        with open(args.out + ".json") as f:
            write_markdown(args.out + ".md", json.load(f))
        return 0
    rev = subprocess.run(["git", "-C", ROOT, "rev-parse", "--short", args.after or "HEAD"], capture_output=True,
                         text=True).stdout.strip()
    with tempfile.TemporaryDirectory() as tmp:
        cases = os.path.join(tmp, "cases.pt")
        make_cases(cases)
        before = _run_worker(_tree(args.before, tmp), cases, os.path.join(tmp, "before.json"))
        after_tree = ROOT if args.after is None else _tree(args.after, tmp)
        after = _run_worker(after_tree, cases, os.path.join(tmp, "after.json"))
    comparison = compare(before, after)
    for side in (before, after):
        for f in side["forward"].values():
            f.pop("D")
    res = {"command": "python benchmarks/photometric/bench_photometric_fit_speed.py"
                      + (f" --before {args.before}" if args.before != "8c1f30a" else "")
                      + (f" --after {args.after}" if args.after else ""),
           "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "before_rev": args.before,
           "after_rev": rev if args.after else rev + " (working tree)", "load": os.getloadavg()[0], "comparison": comparison,
           "before": before, "after": after}
    with open(args.out + ".json", "w") as f:
        json.dump(res, f, indent=1)
    write_markdown(args.out + ".md", res)
    print(open(args.out + ".md").read())
    return 0


if __name__ == "__main__":
    sys.exit(main())
