"""Calibration speed after detection: tiltfit against cv2.calibrateCamera on the same corners, before and after.

Sets (all in the same run): the shipped real photos data/real/gopro_wide (36 JPEG, 8×6 corners) and
data/real/industrial_ds1 (20 PNG, 16×10 corners), detected once by `tiltfit detect` (corners and blur widths;
DET files cached in --cache, detection is not timed), and a synthetic tilted capture: 60 views of the paper's
designed target (`reproduce.calibration_target`) seen by the simulated lens (w = 55.39 mm, f = 50.84 mm,
d = 18.81 mm) tilted by θL = 5° (U and θF from the hinge and Scheimpflug rules), 1368 × 912 px (EOS 6D binned
4×), corners with 0.05 px and blur widths with 0.1 px + 3 % Gaussian noise (`model.synthesize_observations`).

Timed, medians of --repeats on the same corners and in the same process:
- OpenCV: cv2.calibrateCamera, one focal length (CALIB_FIX_ASPECT_RATIO, as ours has square pixels), free
  principal point, the set's distortion model (`MODEL`), 200 iterations / 1e-12 (bench_real_calib's settings);
- geometric: `calibrate(without_blur(obs))` with the same model, free principal point, no model selection;
- with blur: the same on corners and blur widths (w, U, d and the blur offset fitted where the widths are
  informative);
- default command: `tiltfit calibrate DET... --target T --pixel-pitch-mm P -q -o CALIB.json` in the process
  (`cli.main`; distortion auto, model selection and the 5-fold held-out error, as a user runs it), and the same
  as a fresh process (wall, with Python's start and imports).
Ratios are ours / OpenCV in the same process. "Before": the same measurements with the code of --base (default
`main`, extracted by `git archive` into a temporary folder) in a child process of the same run.

Writes benchmarks/results/calib_speed.{json,md}. Usage:
    python benchmarks/calibration/bench_calib_speed.py [--repeats 5] [--default-repeats 3] [--base main|none] [--quick]
"""
from __future__ import annotations

import argparse
import datetime
import glob
import json
import math
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time

import cv2
import numpy as np
import torch

sys.path.append(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))  # the repository root, last: a --base child's PYTHONPATH keeps its own tiltfit
from benchmarks.calibration.bench_real_calib import OPENCV_FLAGS  # noqa: E402
from benchmarks.results_io import ROOT, add_output_options, markdown_only, save, timed  # noqa: E402

#: The sets: folder (or "synthetic"), image glob, pixel pitch (mm; intrinsics in pixels do not depend on it),
#: and the distortion model of the geometric comparison.
SETS = {
    "gopro_wide": {"folder": "data/real/gopro_wide", "glob": "*.jpg", "pitch_mm": 0.00155, "model": "opencv5"},
    "industrial_ds1": {"folder": "data/real/industrial_ds1", "glob": "*.png", "pitch_mm": 0.0048,
                       "model": "opencv5"},
    "synthetic_tilted_60": {"folder": None, "pitch_mm": 0.00654 * 4, "model": "k1k2"},
}
SYNTH_VIEWS = 60


def log(msg: str) -> None:
    print(f"[bench_calib_speed {time.perf_counter() - T0:6.1f} s] {msg}", file=sys.stderr, flush=True)


T0 = time.perf_counter()


# --------------------------------------------------------------------------------------------- the inputs

def _detect_real(name: str, spec: dict, cache: str) -> tuple[list, str]:
    """DET files of a real set (detected by `tiltfit detect` where not cached) and its target file."""
    from tiltfit.cli import main as cli

    folder = os.path.join(ROOT, spec["folder"])
    target = os.path.join(folder, "target.json")
    out_dir = os.path.join(cache, name)
    os.makedirs(out_dir, exist_ok=True)
    dets = []
    for img in sorted(glob.glob(os.path.join(folder, spec["glob"]))):
        det = os.path.join(out_dir, os.path.splitext(os.path.basename(img))[0] + ".json")
        missing = det + ".none"
        if not os.path.exists(det) and not os.path.exists(missing):
            log(f"detecting {os.path.relpath(img, ROOT)}")
            if cli.main(["detect", img, "--target", target, "-q", "-o", det]) != 0:
                open(missing, "w").close()  # no board: remembered, not retried
        if os.path.exists(det):
            dets.append(det)
    return dets, target


def _synthetic(cache: str) -> tuple[list, str]:
    """DET files of the synthetic tilted capture (written once, seeded) and its target file."""
    return write_synthetic_views(SYNTH_VIEWS, os.path.join(cache, "synthetic_tilted_60"))


def write_synthetic_views(n: int, out_dir: str, size=(1368, 912)) -> tuple[list, str]:
    """DET files of n views of the designed target through the simulated lens tilted by θL = 5° (seeded: the
    same files every time; kept when already there) and the target file."""
    try:
        from tiltfit.experiments import reproduce
    except ImportError:  # --base code from before tiltfit/experiments/
        from tiltfit import reproduce
    from tiltfit.calibrate.model import LensCamera, random_poses, synthesize_observations
    try:
        from tiltfit.target.design import design_centre_mm
    except ImportError:  # --base code from before tiltfit.target.design
        from tiltfit.target.layout import design_centre_mm

    target_file = os.path.join(out_dir, "target.json")
    dets = [os.path.join(out_dir, f"view{v:05d}.json") for v in range(n)]
    if all(os.path.exists(p) for p in dets + [target_file]):
        return dets, target_file
    os.makedirs(out_dir, exist_ok=True)
    target = reproduce.calibration_target(reproduce.SetValues())
    rvec, T = random_poses(n, seed=1, distance_mm=(480.0, 760.0), max_angle_deg=25.0,
                           board_centre_mm=design_centre_mm(target))
    cam = LensCamera.from_tilted_lens(n, size, SETS["synthetic_tilted_60"]["pitch_mm"], 55.39, 50.84,
                                          18.81, math.radians(5.0), rvec=rvec, T_mm=T)
    obs = synthesize_observations(cam, torch.tensor(target.feature_points()), noise_px=0.05, noise_blur_px=0.1,
                                  noise_blur_rel=0.03, seed=2, margin_px=5.0)
    for v, path in enumerate(dets):
        c, b = obs.corners_px[v].numpy(), obs.blur_px[v].numpy()
        det = {"image_size_px": list(size), "grid_found": True,
               "corners_px": [[float(p[0]), float(p[1])] if np.isfinite(p).all() else None for p in c],
               "blur_px": [float(x) if np.isfinite(x) else None for x in b]}
        with open(path, "w") as f:
            json.dump(det, f)
    with open(target_file, "w") as f:
        json.dump(target.to_dict(), f)
    return dets, target_file


def observations(dets: list, target_file: str, pitch_mm: float):
    """`Observations` of DET files (views with fewer than 6 corners left out, as `calibrate` does)."""
    from tiltfit.calibrate.model import Observations
    from tiltfit.target.layout import load_target

    points = load_target(target_file).feature_points()
    corners, blur, names, size = [], [], [], None
    for p in dets:
        with open(p) as f:
            d = json.load(f)
        c = np.array([q if q is not None else [np.nan, np.nan] for q in d["corners_px"]], dtype=np.float64)
        if np.isfinite(c).all(-1).sum() < 6:
            continue
        corners.append(c)
        blur.append([b if b is not None else np.nan for b in d["blur_px"]])
        names.append(os.path.basename(p))
        size = tuple(d["image_size_px"])
    return Observations(points, np.array(corners), np.array(blur, dtype=np.float64), size, pitch_mm, names)


# --------------------------------------------------------------------------------------------- the fits

def opencv_calibrate(obs, model: str):
    """cv2.calibrateCamera on the detected corners of every view (one focal length, free principal point)."""
    obj, img = [], []
    pts = obs.points_mm.numpy().astype(np.float32)
    for v in range(obs.n_views):
        m = obs.corner_mask[v].numpy()
        obj.append(pts[m])
        img.append(obs.corners_px[v].numpy()[m].astype(np.float32))
    W, H = obs.image_size_px
    K0 = np.array([[1.0, 0, (W - 1) / 2], [0, 1.0, (H - 1) / 2], [0, 0, 1]])
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    flags = OPENCV_FLAGS[model] | cv2.CALIB_FIX_ASPECT_RATIO
    rms, K, dist, _, _ = cv2.calibrateCamera(obj, img, (W, H), K0, None, flags=flags, criteria=crit)
    return {"rms_px": float(rms), "f_px": float(K[0, 0]), "c_px": [float(K[0, 2]), float(K[1, 2])],
            "distortion": [float(x) for x in dist.ravel()]}


def ours(obs, model: str, blur: bool):
    from tiltfit.calibrate.fit import FitOptions, without_blur

    try:
        from tiltfit.calibrate.flow import calibrate
    except ImportError:  # --base code from before tiltfit.calibrate.flow existed
        from tiltfit.calibrate.fit import calibrate

    opts = FitOptions(distortion=model, free_principal_point=True, max_rms_px=None, model_selection=False)
    res = calibrate(obs if blur else without_blur(obs), "unified", options=opts)
    v, s = res.values, res.sigma
    out = {"f_px": float(res.camera.focal_px.detach()), "sigma_f_px": s["w_mm"] / obs.pixel_pitch_mm,
           "c_px": v["principal_point_px"], "sigma_c_px": s["principal_point_px"],
           "rms_px": math.sqrt(res.rss["corners"] / max(res.rss["n_corners"] / 2, 1)),
           "distortion": [float(x) for x in res.camera.distortion.detach()], "undetermined": res.undetermined,
           "iterations": res.iterations}
    if blur and "U_mm" not in res.undetermined:
        out.update({"U_mm": v["U_mm"], "sigma_U_mm": s["U_mm"], "d_mm": v["d_mm"], "sigma_d_mm": s["d_mm"]})
    return out


def default_command(dets: list, target: str, pitch_mm: float, out: str) -> dict:
    from tiltfit.cli import main as cli

    rc = cli.main(["calibrate", *dets, "--target", target, "--pixel-pitch-mm", str(pitch_mm), "-q", "-o", out])
    if rc != 0:
        raise RuntimeError(f"tiltfit calibrate exited with {rc}")
    with open(out) as f:
        d = json.load(f)
    return {"distortion_model": d.get("distortion_model"), "rms_px": d.get("rms_reprojection_px"),
            "w_mm": d.get("w_mm"), "U_mm": d.get("U_mm"), "d_mm": d.get("d_mm"),
            "principal_point_px": d.get("principal_point_px"), "held_out_px": (d.get("held_out") or {}).get("rms_px")}


def measure(sets: dict, repeats: int, default_repeats: int) -> dict:
    """Every timing of every set, in this process (whatever `tiltfit` is on the path)."""
    import tiltfit

    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    out = {"tiltfit": os.path.dirname(os.path.abspath(tiltfit.__file__)), "sets": {}}
    tmp = tempfile.mkdtemp(prefix="calib_speed_")
    for name, s in sets.items():
        obs = observations(s["dets"], s["target"], s["pitch_mm"])
        model = s["model"]
        ours(obs, model, blur=False)  # warm-up: lazy imports, first-call costs
        cv, w_cv, t_cv, all_cv = timed(lambda: opencv_calibrate(obs, model), repeats, samples=True)
        geo, w_geo, t_geo, all_geo = timed(lambda: ours(obs, model, blur=False), repeats, samples=True)
        blr, w_blur, t_blur, all_blur = timed(lambda: ours(obs, model, blur=True), repeats, samples=True)
        calib = os.path.join(tmp, f"{name}.json")
        dflt, w_default, t_default, all_default = timed(
            lambda: default_command(s["dets"], s["target"], s["pitch_mm"], calib), default_repeats, samples=True)
        t0, c0 = time.perf_counter(), resource.getrusage(resource.RUSAGE_CHILDREN)
        proc = subprocess.run([sys.executable, "-m", "tiltfit", "calibrate", *s["dets"], "--target", s["target"],
                               "--pixel-pitch-mm", str(s["pitch_mm"]), "-q", "-o", calib],
                              env={**os.environ, "OMP_NUM_THREADS": "1"}, capture_output=True, text=True)
        t_process = time.perf_counter() - t0
        c1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu_process = (c1.ru_utime + c1.ru_stime) - (c0.ru_utime + c0.ru_stime)
        if proc.returncode != 0:
            raise RuntimeError(f"tiltfit calibrate (process) failed: {proc.stderr.strip()}")
        out["sets"][name] = {
            "views": obs.n_views, "corners": int(obs.corner_mask.sum()), "blur_widths": int(obs.blur_mask.sum()),
            "model": model,
            "opencv": {**cv, "time_s": t_cv, "wall_s": w_cv, "times_s": all_cv},
            "geometric": {**geo, "time_s": t_geo, "wall_s": w_geo, "times_s": all_geo, "ratio": t_geo / t_cv,
                          "wall_ratio": w_geo / w_cv},
            "with_blur": {**blr, "time_s": t_blur, "wall_s": w_blur, "times_s": all_blur, "ratio": t_blur / t_cv,
                          "wall_ratio": w_blur / w_cv},
            "default": {**dflt, "time_s": t_default, "wall_s": w_default, "times_s": all_default,
                        "ratio": t_default / t_cv, "process_s": cpu_process, "process_wall_s": t_process,
                        "calib_file": calib},
        }
        log(f"{name}: CPU s: OpenCV {t_cv:.3f}, geometric {t_geo:.3f} ({t_geo / t_cv:.1f}×), with blur {t_blur:.3f}, "
            f"default {t_default:.2f} (process {cpu_process:.2f}, wall {t_process:.2f})")
    return out


def calib_difference(after_file: str, before_file: str) -> dict:
    """Largest |after − before| / σ (σ from `after_file`) over w, U, d, θF, the principal point, the distortion
    coefficients and the views' translations of two CALIB.json files, and where it is."""
    with open(after_file) as f:
        a = json.load(f)
    with open(before_file) as f:
        b = json.load(f)
    diffs = []
    for k in ("w_mm", "U_mm", "d_mm", "theta_F_deg", "blur_offset_px"):
        s = a["sigma"].get(k)
        if isinstance(s, (int, float)) and s > 0 and a.get(k) is not None and b.get(k) is not None:
            diffs.append((abs(a[k] - b[k]) / s, k))
    for i, s in enumerate(a["sigma"].get("principal_point_px") or []):
        if s:
            diffs.append((abs(a["principal_point_px"][i] - b["principal_point_px"][i]) / s, f"principal_point[{i}]"))
    for i, s in enumerate(a["sigma"].get("distortion") or []):
        if s:
            diffs.append((abs(a["distortion"]["coefficients"][i] - b["distortion"]["coefficients"][i]) / s,
                          f"distortion[{i}]"))
    for va, vb in zip(a["views"], b["views"]):
        for i, s in enumerate(va.get("sigma_T_mm") or []):
            if s:
                diffs.append((abs(va["T_mm"][i] - vb["T_mm"][i]) / s, "T_mm"))
    worst = max(diffs)
    return {"max_delta_over_sigma": worst[0], "at": worst[1], "same_distortion_model":
            a.get("distortion_model") == b.get("distortion_model"),
            "same_model_selection": {k: v.get("justified") for k, v in (a.get("model_selection") or {}).items()}
            == {k: v.get("justified") for k, v in (b.get("model_selection") or {}).items()}}


def _base_checkout(ref: str) -> str:
    """The tree of `ref` in a temporary folder (git archive: no worktree is registered)."""
    folder = tempfile.mkdtemp(prefix="calib_speed_base_")
    archive = subprocess.run(["git", "-C", ROOT, "archive", ref], check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", folder], input=archive, check=True)
    commit = subprocess.run(["git", "-C", ROOT, "rev-parse", ref], check=True, capture_output=True,
                            text=True).stdout.strip()
    return folder, commit


# --------------------------------------------------------------------------------------------- the report

def _fmt_s(t: float) -> str:
    return f"{t:.3f} s" if t < 10 else f"{t:.1f} s"


def write_markdown(path: str, res: dict) -> None:
    after, before = res["after"], res.get("before")
    lines = [
        "# Calibration speed after detection: tiltfit vs cv2.calibrateCamera on the same corners", "",
        f"- machine: {res['machine']}; torch {res['torch']}, OpenCV {res['opencv']}; 1 torch thread",
        f"- date: {res['date']}; command: `{res['command']}`; run time {res['run_time_s']:.0f} s",
        f"- after: this checkout (`{res['commit']}`)" + (f"; before: `{res['base']}` ({res['base_commit'][:10]}), "
                                                          "same script, a child process of the same run"
                                                          if before else ""),
        f"- CPU seconds (`time.process_time`; the 2 cores are shared with other jobs, whose load stretches wall "
        f"time, not CPU time), medians of {res['repeats']} runs (default command: {res['default_repeats']}); "
        "ratio = ours / OpenCV measured in the same process; wall-clock medians and ratios are in the JSON; "
        "fresh process: CPU of the child (wall in brackets), Python's start and imports included", "",
        "| set | views / corners | model | OpenCV | geometric (ratio) | with blur (ratio) | default command "
        "(in process) | default (fresh process) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for label, r in (("after", after), ("before", before)):
        if not r:
            continue
        for name, s in r["sets"].items():
            lines.append(
                f"| {name} ({label}) | {s['views']} / {s['corners']} | {s['model']} | "
                f"{_fmt_s(s['opencv']['time_s'])} | "
                f"{_fmt_s(s['geometric']['time_s'])} ({s['geometric']['ratio']:.1f}×) | "
                f"{_fmt_s(s['with_blur']['time_s'])} ({s['with_blur']['ratio']:.1f}×) | "
                f"{_fmt_s(s['default']['time_s'])} | {_fmt_s(s['default']['process_s'])} "
                f"({_fmt_s(s['default']['process_wall_s'])}) |")
    if before:
        lines += ["", "## Before / after (same run)", "",
                  "| set | geometric | with blur | default command | geometric: Δf / σ_f, Δc / σ_c | default "
                  "command: largest Δ / σ (where); same choices |",
                  "|---|---|---|---|---|---|"]
        for name, a in after["sets"].items():
            b = before["sets"].get(name)
            if not b:
                continue
            df = (a["geometric"]["f_px"] - b["geometric"]["f_px"]) / a["geometric"]["sigma_f_px"]
            dc = max(abs(a["geometric"]["c_px"][i] - b["geometric"]["c_px"][i]) / a["geometric"]["sigma_c_px"][i]
                     for i in range(2))
            vb = a["default"].get("versus_before") or {}
            same = "yes" if vb.get("same_distortion_model") and vb.get("same_model_selection") else "no"
            lines.append(f"| {name} | {b['geometric']['time_s'] / a['geometric']['time_s']:.1f}× faster | "
                         f"{b['with_blur']['time_s'] / a['with_blur']['time_s']:.1f}× faster | "
                         f"{b['default']['time_s'] / a['default']['time_s']:.1f}× faster | {df:+.1e}, {dc:.1e} | "
                         f"{vb.get('max_delta_over_sigma', math.nan):.1e} ({vb.get('at', '–')}); {same} |")
    lines += ["", "## Results (after)", "",
              "| set | f ours ± σ | f OpenCV | RMS ours / OpenCV (px per corner) | with blur: U ± σ, d ± σ | "
              "default: model, RMS, held-out |", "|---|---|---|---|---|---|"]
    for name, s in after["sets"].items():
        g, cv, wb, d = s["geometric"], s["opencv"], s["with_blur"], s["default"]
        focus = (f"{wb['U_mm']:.1f} ± {wb['sigma_U_mm']:.1f} mm, {wb['d_mm']:.2f} ± {wb['sigma_d_mm']:.2f} mm"
                 if "U_mm" in wb else "undetermined (" + ", ".join(wb["undetermined"]) + ")")
        held = f"{d['held_out_px']:.4f}" if d.get("held_out_px") is not None else "–"
        lines.append(f"| {name} | {g['f_px']:.2f} ± {g['sigma_f_px']:.2f} | {cv['f_px']:.2f} | "
                     f"{g['rms_px']:.4f} / {cv['rms_px']:.4f} | {focus} | {d['distortion_model']}, "
                     f"{d['rms_px']:.4f}, {held} |")
    lines += ["", "Geometric and with-blur fits: `calibrate(..., FitOptions(distortion=model, "
              "free_principal_point=True, model_selection=False))`; the default command adds distortion "
              "auto (candidate fits while the tests justify them, up to five), the θF and principal-point tests and the 5-fold held-out error. "
              "Detection is not timed (DET files from `tiltfit detect`, cached).", ""]
    with open(path, "w") as f:
        f.write("\n".join(lines))


def prepare_sets(cache: str) -> dict:
    sets = {}
    for name, spec in SETS.items():
        dets, target = _synthetic(cache) if spec["folder"] is None else _detect_real(name, spec, cache)
        sets[name] = {**spec, "dets": dets, "target": target}
    return sets


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5, help="runs per fit (median) [5]")
    ap.add_argument("--default-repeats", type=int, default=3, help="runs of the default command (median) [3]")
    ap.add_argument("--base", default="main", help="git ref of the 'before' code, or 'none' [main]")
    ap.add_argument("--base-default-repeats", type=int, default=1,
                    help="runs of the default command with the base code (it takes minutes) [1]")
    ap.add_argument("--cache", default=os.path.join(tempfile.gettempdir(), "tiltfit_bench_calib_speed"),
                    help="folder of the cached DET files")
    ap.add_argument("--quick", action="store_true", help="smoke run: 1 repeat, no base, to OUT_quick")
    ap.add_argument("--measure-only", metavar="JSON", help=argparse.SUPPRESS)  # the child process of --base
    ap.add_argument("--sets", metavar="JSON", help=argparse.SUPPRESS)
    add_output_options(ap, "calib_speed")
    args = ap.parse_args(argv)
    if markdown_only(args, write_markdown):
        return 0
    if args.quick:
        args.repeats, args.default_repeats, args.base, args.out = 1, 1, "none", args.out + "_quick"
    if args.measure_only:
        with open(args.sets) as f:
            sets = json.load(f)
        with open(args.measure_only, "w") as f:
            json.dump(measure(sets, args.repeats, args.default_repeats), f)
        return 0
    sets = prepare_sets(args.cache)
    log("measuring this checkout")
    after = measure(sets, args.repeats, args.default_repeats)
    before, base_commit = None, None
    if args.base != "none":
        base, base_commit = _base_checkout(args.base)
        log(f"measuring {args.base} ({base_commit[:10]}) in {base}")
        sets_file, result_file = os.path.join(base, "sets.json"), os.path.join(base, "result.json")
        with open(sets_file, "w") as f:
            json.dump(sets, f)
        subprocess.run([sys.executable, os.path.abspath(__file__), "--measure-only", result_file, "--sets", sets_file,
                        "--repeats", str(args.repeats), "--default-repeats", str(args.base_default_repeats)],
                       env={**os.environ, "PYTHONPATH": base, "OMP_NUM_THREADS": "1"}, check=True, cwd=base)
        with open(result_file) as f:
            before = json.load(f)
        for name, s in after["sets"].items():
            if name in before["sets"]:
                s["default"]["versus_before"] = calib_difference(s["default"]["calib_file"],
                                                                 before["sets"][name]["default"]["calib_file"])
    commit = subprocess.run(["git", "-C", ROOT, "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    res = {
        "machine": f"{platform.node() or 'vm'} {platform.machine()} ({os.cpu_count()} CPUs), Python "
                   f"{platform.python_version()}",
        "torch": torch.__version__, "opencv": cv2.__version__,
        "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "command": "python benchmarks/calibration/bench_calib_speed.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "run_time_s": time.perf_counter() - T0, "repeats": args.repeats, "default_repeats": args.default_repeats,
        "commit": commit[:10], "base": args.base, "base_commit": base_commit or "",
        "after": after, "before": before,
    }
    save(args.out, res, write_markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
