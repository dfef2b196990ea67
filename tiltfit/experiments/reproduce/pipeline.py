"""(f) The experiment end to end (`run`, `tiltfit reproduce`): every stage in order, the tables, the figure
data, the run record and report.md."""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import asdict, dataclass, replace

import torch

from tiltfit.photometric.profiles import write_csv, write_markdown, markdown_table
from ..scenes import profile_lines
from .config import LENS_STATES, RunConfig, SetValues, SimulatedCamera, run_log
from .targets import stage_targets
from .calibration import stage1_rows, stage_calibrate, table1_rows
from .boxes import NOISE_FLOOR, TRUE_LENS, stage_boxes
from .figures import figures_json, plot_all, stage_speed


TABLE2_COLUMNS = ["state", "theta_L_set_deg", "parameters", "theta_L_deg", "red", "green"]

@dataclass
class ReproduceResult:
    """What `run` returns: the tables as rows, the files written and the stages skipped."""

    table1: list
    table2: list
    speed: list
    files: dict
    skipped: list
    runtime_s: float

def run(out_dir: str, quick: bool = False, progress: bool = True, config: RunConfig | None = None,
        camera: SimulatedCamera | None = None, set_values: SetValues | None = None,
        threads: int | None = 1) -> ReproduceResult:
    """Run the experiment, write every output into `out_dir` and print the two tables.

    Args:
        out_dir: output folder (created).
        quick: small images and few samples (about a minute on two cores) instead of the full run.
        progress: progress lines on stderr.
        config, camera, set_values: override the run size, the simulated truth, the set values.
        threads: torch threads for the run (restored afterwards); None keeps torch's setting [1]. The
            batches here are small: a second thread gains at most 2x, while on a loaded machine torch's
            spinning worker threads made a 171 x 114 render 60x slower (36 s instead of 0.6 s).
    Returns:
        ReproduceResult.
    """
    previous = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(threads)
    try:
        return _run(out_dir, quick, progress, config, camera, set_values)
    finally:
        torch.set_num_threads(previous)

def _run(out_dir, quick, progress, config, camera, set_values) -> ReproduceResult:
    cfg = config or (RunConfig.quick() if quick else RunConfig.full())
    camera = camera or SimulatedCamera()
    set_values = set_values or SetValues()
    log = run_log(progress)
    os.makedirs(out_dir, exist_ok=True)
    torch_threads = torch.get_num_threads()
    width, height = camera.sensor.binned(cfg.downscale).size_px
    lines = profile_lines(width, height)
    target_w, target_h = camera.sensor.binned(cfg.target_downscale).size_px
    true = camera.untilted
    log(f"(a) simulated camera: w {true.w} mm, U {true.U} mm, d {true.d} mm (f "
        f"{camera.f_mm:.2f} mm); boxes images {width}x{height} (1/{cfg.downscale}), target photographs "
        f"{target_w}x{target_h} (1/{cfg.target_downscale}), {torch_threads} threads")

    skipped = [] if cfg.calibrate else ["(b) target photographs", "(c) calibration"]
    targets = stage_targets(camera, set_values, cfg, out_dir, log)    # (b)
    calibration = stage_calibrate(targets, set_values, cfg, log)      # (c)
    table1 = table1_rows(camera, calibration)
    table_s1 = stage1_rows(camera, set_values, calibration)

    param_sets = {"set": {s.label: set_values.lens(s.theta_L_set_deg) for s in LENS_STATES},
                  TRUE_LENS: {s.label: camera.lens(s.theta_L_set_deg) for s in LENS_STATES}}
    param_sets.update(calibration["lenses"])
    results = stage_boxes(camera, param_sets, cfg, lines, out_dir, log)                   # (d)
    table2 = [row for res in results for row in res.rows]
    rec_b = calibration.get("records", {}).get("b", {})
    joint_s = (rec_b.get("joint") or {}).get("runtime_s", 0.0)
    calib_seconds = {"calibrated (joint)": joint_s,
                     "calibrated (photometric)": joint_s + (rec_b.get("photometric") or {}).get("runtime_s", 0.0)}
    speed = stage_speed(results, cfg, lines, log, calib_seconds, camera)         # (e)
    files = plot_all(results, speed, lines, out_dir)

    # (f) tables, figure data, run record, report
    files.update(write_tables(out_dir, table1, table_s1, table2, speed))
    with open(os.path.join(out_dir, "figures.json"), "w", encoding="utf-8") as f:
        json.dump(figures_json(results, speed, lines, files), f)
    files["figures"] = "figures.json"
    runtime = log.elapsed
    record = {
        "config": asdict(cfg), "quick": quick, "runtime_s": runtime, "skipped": skipped,
        "truth": {**asdict(camera), **camera.untilted.record(), "U0_mm": camera.untilted.U, "f_mm": camera.f_mm,
                  "lens_states": {s.label: camera.lens(s.theta_L_set_deg).record() for s in LENS_STATES}},
        "set_values": {s.label: set_values.lens(s.theta_L_set_deg).record() for s in LENS_STATES},
        "calibration": calibration["records"], "calibration_errors": calibration["errors"],
        "target_photographs": targets["files"] if targets else None,
        "image_size_px": [width, height], "target_image_size_px": [target_w, target_h],
    }
    record["truth"]["sensor"] = asdict(camera.sensor)
    with open(os.path.join(out_dir, "run.json"), "w", encoding="utf-8") as f:
        json.dump(record, f, indent=1)
    files["run"] = "run.json"
    files["report"] = write_report(out_dir, table1, table_s1, table2, speed, files, skipped, cfg, runtime)
    print("Stage 1: w, U, d (mm)\n")
    print(markdown_table(table_s1))
    print("Table 1: lens tilt, set -> estimated (degrees)\n")
    print(markdown_table(table1))
    print("Table 2: average brightness error along the lines (0-255 grey levels)\n")
    print(markdown_table(table2, TABLE2_COLUMNS, floatfmt=".3f"))
    if skipped:
        print("Skipped: " + "; ".join(skipped))
    log(f"done: outputs in {out_dir}")
    return ReproduceResult(table1, table2, speed, files, skipped, runtime)

def write_tables(out_dir: str, table1, table_s1, table2, speed) -> dict:
    """Markdown and CSV of Table 1, the stage-1 lens, Table 2 and the speed–accuracy sweep."""
    files = {}
    for stem, rows, cols, title in (
            ("table1", table1, None, "Table 1: lens tilt, set -> estimated (degrees)"),
            ("table_stage1", table_s1, None, "Stage 1: w, U, d (mm)"),
            ("table2", table2, None, "Table 2: average brightness error along the lines (0-255 grey levels)"),
            ("speed_accuracy", speed, None, "Speed and accuracy of the CG (lens state (b))")):
        write_markdown(rows, os.path.join(out_dir, f"{stem}.md"), cols, title)
        write_csv(rows, os.path.join(out_dir, f"{stem}.csv"), cols)
        files[stem] = f"{stem}.md"
    return files

def true_lens_sentence(table2: list[dict]) -> str:
    """What the true-lens rows show against the noise floor, measured (not assumed), as one sentence."""
    by = {(r["state"], r["parameters"]): r for r in table2}
    diffs = [by[(s, TRUE_LENS)][line] - by[(s, NOISE_FLOOR)][line]
             for (s, p) in by if p == TRUE_LENS and (s, NOISE_FLOOR) in by for line in ("red", "green")]
    if not diffs:
        return ""
    above = sum(d > 0 for d in diffs)
    return (f"In this run the true-lens CG lands above the noise floor in {above} of {len(diffs)} line profiles "
            f"(true lens − floor from {min(diffs):+.2f} to {max(diffs):+.2f} grey levels).")

def write_report(out_dir, table1, table_s1, table2, speed, files, skipped, cfg, runtime) -> str:
    """report.md: the tables and the figures in one page."""
    parts = ["# Tilt-lens paper, reproduced on a simulated camera\n",
             f"Run: boxes images 1/{cfg.downscale}, target photographs 1/{cfg.target_downscale}, "
             f"{cfg.spp_capture} spp photographs, {cfg.spp_cg} spp CG, "
             f"{runtime:.0f} s.\n"]
    if skipped:
        parts.append("**Skipped:** " + "; ".join(skipped) + ".\n")
    parts += ["## Stage 1: w, U, d (mm)\n", markdown_table(table_s1),
              "\n## Table 1: lens tilt, set -> estimated (degrees)\n", markdown_table(table1),
              "\n## Table 2: average brightness error (0-255 grey levels)\n",
              "Average error = mean |photo − CG| of the BT.601 luma of the 8-bit sRGB images along the line, "
              "sampled every step_px. The noise floor compares two photographs of the same scene (independent "
              "render samples and sensor noise); the true-lens row is the CG rendered with the simulation's own "
              "lens, what a perfect calibration would score. " + true_lens_sentence(table2) + "\n",
              markdown_table(table2, TABLE2_COLUMNS),
              "\n## Figures\n"]
    for key in ("images", "red", "green", "speed"):
        if key in files:
            parts.append(f"![{key}]({files[key]})\n")
    parts += ["\n## Speed and accuracy\n", markdown_table(speed)]
    with open(os.path.join(out_dir, "report.md"), "w", encoding="utf-8") as f:
        f.write("\n".join(parts))
    return "report.md"

def main(argv=None) -> int:
    """`tiltfit reproduce [--quick] [--scale N] [--target-scale N] [--device cpu|cuda] [-o DIR]` (also
    `python -m tiltfit.experiments.reproduce`)."""
    ap = argparse.ArgumentParser(prog="tiltfit reproduce", description=(  # the package docstring's first line
        "The tilt-lens paper's experiment end to end on a simulated camera (`tiltfit reproduce [--quick] [-o DIR]`)."))
    ap.add_argument("--quick", action="store_true", help="small images and few samples (about a minute)")
    ap.add_argument("-o", "--output", default="reproduce_out", help="output folder [reproduce_out]")
    ap.add_argument("--threads", type=int, default=1, help="torch threads [1]; 0 keeps torch's default")
    ap.add_argument("--scale", type=int, default=None,
                    help="pixel binning of the boxes images only (the target photographs: --target-scale): "
                         "1 is the paper's 5472x3648 [16; --quick 32]")
    ap.add_argument("--target-scale", type=int, default=None,
                    help="pixel binning of the calibration target photographs: 1 is the paper's 5472x3648 [8]")
    ap.add_argument("--device", default="cpu", help="torch device of the boxes renders: cpu, cuda or cuda:N [cpu]")
    args = ap.parse_args(argv)
    if args.scale is not None and not 1 <= args.scale <= 256:
        ap.error(f"--scale: expected an integer from 1 to 256, got {args.scale}")
    if args.target_scale is not None and not 1 <= args.target_scale <= 256:
        ap.error(f"--target-scale: expected an integer from 1 to 256, got {args.target_scale}")
    from camio.checks import parse_device
    from camio.errors import UsageError

    try:
        parse_device(args.device)
    except UsageError as e:
        ap.error(str(e))
    cfg = RunConfig.quick() if args.quick else RunConfig.full()
    cfg = replace(cfg, device=args.device, **({} if args.scale is None else {"downscale": args.scale}),
                  **({} if args.target_scale is None else {"target_downscale": args.target_scale}))
    t0 = time.perf_counter()
    run(args.output, quick=args.quick, threads=args.threads or None, config=cfg)
    print(f"reproduce: {time.perf_counter() - t0:.1f} s in all (boxes images 1/{cfg.downscale}, targets "
          f"1/{cfg.target_downscale}, {cfg.device})", file=sys.stderr)
    return 0
