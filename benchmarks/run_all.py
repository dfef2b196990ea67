"""Run every current benchmark, group by group; each writes its numbers to benchmarks/results/ (README.md: the index).

    .venv/bin/python benchmarks/run_all.py                        # everything, full size (hours on 2 cores)
    .venv/bin/python benchmarks/run_all.py --group detection      # one group (repeat --group for more)
    .venv/bin/python benchmarks/run_all.py --quick                # small sizes and repeats, to --quick-out
    .venv/bin/python benchmarks/run_all.py --quick --dry-run      # list the commands, run nothing

`--quick` is a smoke run: every benchmark at its smallest sizes and repeats, writing to a scratch folder
(`--quick-out`, default $TMPDIR/benchmarks_quick) so the committed results stay as they are; its figures are
not results. The full runs time ours against a named peer in the same run (Mitsuba 3, OpenCV) and need the
`bench` extra (Mitsuba); see the Makefile. benchmarks/history/ is not run: those scripts compare against old
revisions or were one-off diagnostics (docs/history.md).
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass

HERE = os.path.dirname(os.path.abspath(__file__))
RESULTS = os.path.join(HERE, "results")
GROUPS = ("renderer", "detection", "calibration", "photometric", "robustness")


@dataclass(frozen=True)
class Benchmark:
    """One script and its arguments. `{q}` in `quick` is the quick-output folder, `{r}` in either the results
    folder; `quick` None: the script has no smaller size and no output option, so the quick run skips it."""
    group: str
    script: str
    full: tuple = ()
    quick: tuple | None = ()


BENCHMARKS = (
    # renderer: speed and accuracy against Mitsuba 3
    Benchmark("renderer", "bench_speed_mitsuba.py", ("--equal-error",),
              ("--size", "128", "--repeats", "3", "--out", "{q}/speed_thin_lens")),
    Benchmark("renderer", "bench_fig6_mitsuba.py", (),
              ("--sizes", "320x240", "--repeats", "3", "--modes", "eager", "--out", "{q}/fig6_mitsuba")),
    Benchmark("renderer", "bench_thin_lens.py", (), ("--quick", "--out", "{q}")),
    Benchmark("renderer", "bench_mitsuba_coverage.py", (),
              ("--side", "32", "--spp", "4", "--out", "{q}/mitsuba_backend_coverage")),
    Benchmark("renderer", "bench_fresh_machine.py", (),
              ("--size", "128", "--repeats", "1", "--rounds", "1", "--out", "{q}/fresh_machine_speed")),
    Benchmark("renderer", "bench_calibrated_render.py", (),
              ("--spp", "1", "--repeats", "1", "--out", "{q}/calibrated_render")),
    Benchmark("renderer", "bench_composite_alignment.py", (),
              ("--views", "1", "--spp", "2", "--out", "{q}/composite_alignment")),
    Benchmark("renderer", "bench_real_vs_rendered.py", (),
              ("--sets", "industrial_ds1", "--views", "1", "--spp", "1", "2", "--reference-spp", "4",
               "--out", "{q}/real_vs_rendered")),
    Benchmark("renderer", "bench_beam.py", (), ("--quick", "--out", "{q}/beam")),
    Benchmark("renderer", "bench_cluster.py", (), ("--quick",)),  # writes results/cluster_quick.*
    Benchmark("renderer", "bench_batch_io.py", (), ("--repeats", "1", "--out", "{q}/batch_io")),
    Benchmark("renderer", "bench_allocator.py", (), ("--repeats", "1", "--out", "{q}/allocator")),
    # detection: against OpenCV
    Benchmark("detection", "bench_detect_opencv.py", (), ("--quick", "--out", "{q}")),
    Benchmark("detection", "bench_real_detect.py", (), ("--quick", "--out", "{q}")),
    Benchmark("detection", "bench_real_speed.py", (),
              ("--repeats", "1", "--every", "6", "--out", "{q}/real_speed_detect")),
    Benchmark("detection", "bench_detect_speed.py", (), ("--repeats", "1", "--images", "1", "--out", "{q}/detect_speed")),
    Benchmark("detection", "bench_blur_smoothness.py", (), ("--every", "12", "--out", "{q}/blur_smoothness")),
    Benchmark("detection", "bench_charuco.py", (), ("--quick", "--out", "{q}/charuco")),
    Benchmark("detection", "bench_charuco_webcam.py", (), None),
    # calibration: against OpenCV on the same corners
    Benchmark("calibration", "bench_calib_opencv.py", (), ("--quick", "--out", "{q}")),
    Benchmark("calibration", "bench_real_calib.py", (), ("--repeats", "1", "--out", "{q}")),
    Benchmark("calibration", "bench_real_defaults.py", (), ("--sets", "industrial_ds1", "--out", "{q}")),
    Benchmark("calibration", "bench_calib_speed.py", ("--base", "none"), ("--quick", "--out", "{q}/calib_speed")),
    Benchmark("calibration", "bench_calib_real_speed.py", (),
              ("--repeats", "1", "--cv-repeats", "1", "--sets", "industrial_ds1",
               "--name", "calib_real_speed_quick")),  # writes results/calib_real_speed_quick.*
    Benchmark("calibration", "bench_calib_scale.py", (),
              ("--sizes", "20,50", "--repeats", "1", "--out", "{q}/calib_scale")),
    Benchmark("calibration", "bench_selection.py", (), ("--out", "{q}/selection")),
    Benchmark("calibration", "bench_rational_terms.py", (), ("--out", "{q}/rational_terms")),
    Benchmark("calibration", "rational_views.py", (), ("-o", "{q}/rational_views.json")),
    Benchmark("calibration", "bench_sigma_honesty.py", (), ("--draws", "4", "--out", "{q}/sigma_honesty")),
    Benchmark("calibration", "bench_board_shape.py", (), ("--repeats", "1", "--out", "{q}/board_shape")),
    Benchmark("calibration", "bench_small_boards.py", (), ("--sets", "sony_small", "--out", "{q}/small_boards")),
    Benchmark("calibration", "bench_blur_decision.py", (), ("--out", "{q}/blur_decision")),
    Benchmark("calibration", "bench_lens_axis.py", (), ("--seeds", "1", "--out", "{q}/lens_axis")),
    Benchmark("calibration", "bench_lens_axis_independent.py", (),
              ("--seeds", "1", "--out", "{q}/lens_axis_independent")),
    # photometric refinement: against the corner fit (OpenCV has none)
    Benchmark("photometric", "bench_photometric.py", (), ("--quick", "--out", "{q}")),
    Benchmark("photometric", "bench_photometric_forward.py", (), ("--quick", "1", "--out", "{q}/photometric_forward")),
    Benchmark("photometric", "bench_photometric_refine.py", (), ("--quick", "1", "--out", "{q}/photometric_refine")),
    Benchmark("photometric", "bench_photometric_trust.py", ("--views", "6"),
              ("--views", "2", "--no-variants", "--out", "{q}")),
    Benchmark("photometric", "bench_photometric_sigma.py", (),
              ("--draws", "2", "--views", "2", "--sets", "industrial_ds1", "--out", "{q}/photometric_sigma")),
    Benchmark("photometric", "bench_photometric_real_bounds.py", (),
              ("--views", "2", "--out", "{q}/photometric_real_bounds")),
    Benchmark("photometric", "report_photometric_real.py", (), ("--views", "1", "--out", "{q}/report_photometric_real")),
    # robustness: bad input, interrupts, memory, start-up of the commands
    Benchmark("robustness", "bench_startup.py", (), ("--repeats", "1", "--out", "{q}/startup")),
    Benchmark("robustness", "bench_bad_view.py", (), ("--repeats", "1", "--out", "{q}/bad_view")),
    Benchmark("robustness", "bench_print_memory.py", (), ("--repeats", "1", "--out", "{q}/print_memory")),
    Benchmark("robustness", "probe_group_interrupt.py", ("-o", "{r}/group_interrupt_now.json"),
              ("--trials", "2", "-o", "{q}/group_interrupt.json")),
    Benchmark("robustness", "fuzz_counts.py", ("--label", "now", "-o", "{r}/fuzz_now.json"),
              ("--label", "quick", "--only", "renderer", "--timeout", "5", "-o", "{q}/fuzz.json")),
)


def command(b: Benchmark, quick: bool, quick_out: str) -> list[str] | None:
    """The command line of one benchmark (None: skipped in this mode)."""
    args = b.quick if quick else b.full
    if args is None:
        return None
    path = os.path.join(HERE, b.group, b.script)
    return [sys.executable, path, *(a.replace("{q}", quick_out).replace("{r}", RESULTS) for a in args)]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smallest sizes and repeats, written to --quick-out")
    ap.add_argument("--group", action="append", choices=GROUPS, help="run only this group (repeatable)")
    ap.add_argument("--only", action="append", metavar="SCRIPT", help="run only this script (repeatable)")
    ap.add_argument("--dry-run", action="store_true", help="print the commands, run nothing")
    ap.add_argument("--quick-out", default=os.path.join(tempfile.gettempdir(), "benchmarks_quick"),
                    help="folder of the quick run's files [$TMPDIR/benchmarks_quick]")
    args = ap.parse_args(argv)
    chosen = [b for b in BENCHMARKS if (not args.group or b.group in args.group)
              and (not args.only or b.script in args.only or b.script[:-3] in args.only)]
    if not chosen:
        ap.error("no benchmark matches --group/--only")
    if args.quick and not args.dry_run:
        os.makedirs(args.quick_out, exist_ok=True)
    env = dict(os.environ, OMP_WAIT_POLICY=os.environ.get("OMP_WAIT_POLICY", "PASSIVE"))
    failed, skipped = [], []
    for i, b in enumerate(chosen, 1):
        cmd = command(b, args.quick, args.quick_out)
        name = f"{b.group}/{b.script}"
        if cmd is None:
            skipped.append(name)
            print(f"[{i}/{len(chosen)}] {name}: skipped (no quick mode)", file=sys.stderr, flush=True)
            continue
        shown = " ".join([os.path.relpath(cmd[1], os.path.dirname(HERE)), *cmd[2:]])
        if args.dry_run:
            print(shown)
            continue
        if not os.path.isfile(cmd[1]):
            print(f"[{i}/{len(chosen)}] {name}: missing", file=sys.stderr, flush=True)
            failed.append(name)
            continue
        print(f"[{i}/{len(chosen)}] {shown}", file=sys.stderr, flush=True)
        t0 = time.perf_counter()
        if subprocess.call(cmd, env=env) != 0:
            failed.append(name)
        print(f"[{i}/{len(chosen)}] {name}: {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
    if skipped:
        print("skipped (no quick mode): " + ", ".join(skipped), file=sys.stderr)
    if failed:
        print("benchmarks failed: " + ", ".join(failed), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
