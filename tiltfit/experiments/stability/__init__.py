"""Where each method fails and how ours behaves there (`tiltfit stability [--quick] [-o DIR]`).

Five small sweeps, each with a closed-form prediction beside the measurement, a plot (PNG) and its numbers
(JSON and CSV), and one summary page (stability.md) that states every finding with its number:

(a) detectors    our detector (`tiltfit.detect.chessboard`) against OpenCV's findChessboardCornersSB and
                 findChessboardCorners + cornerSubPix on `tiltfit.experiments.synth` images of the target whose blur
                 diameter grows to the size of a projected square: success rate and corner RMS. (The
                 benchmark `benchmarks/detection/bench_detect_opencv.py` is not part of the installed package, so the
                 sweep is repeated here, small, with the same target, poses and scoring.)
(b) two-stage    the paper's two stages (stage 1 untilted; stage 2 with w, U, d held, eq. (4), θL from
                 eq. (1)) against the joint fit as the lens tilt grows, on `tiltfit.calibrate.model` observations made
                 with the exact physics: a thin lens tilted about its centre, so U follows the hinge rule and
                 θF the Scheimpflug rule, and the blur is the exact spot (`renderer.cameras.optics`). The two-stage
                 error is predicted by `two_stage_prediction` (a 1-D least-squares problem over the same
                 points, then eq. (1)).
(c) coverage     the accumulation-buffer camera (Barsky–Pasztor) against distributed ray tracing as the plane
                 of focus tilts past the last pixel with a finite focus distance: coverage against θF,
                 rendered, and in closed form: a pixel is renderable where D = w − y_s tan θF > 0, so the
                 first row is lost at tan θF = w / (h / 2) (`first_row_lost_theta_F`).
(d) singular     the inverted-perspective camera near its singular depth a3* = α p3 / (α − 1): projected
                 positions and rendered images stay finite (no NaN); the magnification q3 / ((α − 1) ε) at
                 a3 = a3* − ε blows up as 1 / ε.
(e) gamma, noise the blur measured on sRGB-encoded values instead of linear ones (bias against blur size,
                 with the prediction `srgb_blur_bias` from the disc edge model), and the stage-1 calibration
                 error against image noise, from rendered target photographs, detected and calibrated.

Outputs in DIR: per sweep `NAME.json` (findings, rows, closed forms), `NAME.csv` (rows) and `NAME.png`, for NAME in
detectors, two_stage, coverage, singular, gamma_noise (plus gamma_noise_calibration.csv); `stability.md` (every
finding with its number, then the tables and plots) and `run.json` (configuration, run times). Every number is
computed by the run; `--quick` keeps each sweep to a few points (under a minute on two cores), the full run takes
a few minutes. Progress goes to stderr, the findings to stdout.

Layout: `common` (StabilityConfig, the simulated lens, the Study record), `closed_forms` (the predictions),
one module per study (`detectors`, `two_stage`, `coverage`, `singular`, `gamma_noise`, each with its
`study_*` function), and this module: the run, the output files and the command line (also
`python -m tiltfit.experiments.stability`). An experiment built on the library (see tests/tiltfit/test_package_layers.py).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
from dataclasses import asdict, dataclass

import numpy as np
import torch

from tiltfit.photometric.profiles import markdown_table, save_figure, write_csv
from camio.progress import RunLog
from camio.errors import one_line, os_reason

from .closed_forms import (coverage_closed_form, first_row_lost_theta_F, inverted_magnification, singular_depth,
                           srgb_blur_bias, two_stage_prediction)
from .common import D_MM, F_MM, U0_MM, W_MM, StabilityConfig, Study
from .coverage import study_coverage
from .detectors import study_detectors
from .gamma_noise import study_gamma_noise
from .singular import study_singular
from .two_stage import study_two_stage

__all__ = ["StabilityConfig", "Study", "StabilityResult", "STUDIES", "run", "main", "write_study", "write_summary",
           "summary_text", "W_MM", "U0_MM", "D_MM", "F_MM", "first_row_lost_theta_F", "coverage_closed_form",
           "singular_depth", "inverted_magnification", "two_stage_prediction", "srgb_blur_bias"]


def _Log(enabled: bool = True) -> RunLog:
    return RunLog("stability", enabled)


def _json_clean(v):
    """JSON-safe copy: NaN -> None, ±inf -> "inf"/"-inf", numpy scalars and arrays -> Python."""
    if isinstance(v, dict):
        return {str(k): _json_clean(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_json_clean(x) for x in v]
    if isinstance(v, np.ndarray):
        return _json_clean(v.tolist())
    if isinstance(v, (np.floating, float)):
        v = float(v)
        if math.isnan(v):
            return None
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return v
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (np.bool_,)):
        return bool(v)
    return v


# ---------------------------------------------------------------------------------------------------- run

STUDIES = {"detectors": study_detectors, "two_stage": study_two_stage, "coverage": study_coverage,
           "singular": study_singular, "gamma_noise": study_gamma_noise}


@dataclass
class StabilityResult:
    """What `run` returns: the studies (rows, findings), the files written and the run time."""

    studies: dict
    files: dict
    runtime_s: float


def run(out_dir: str, quick: bool = False, progress: bool = True, config: StabilityConfig | None = None,
        only=None, threads: int | None = 1, cluster: str | None = None) -> StabilityResult:
    """Run the sweeps, write every output into `out_dir` and print the summary.

    Args:
        out_dir: output folder (created).
        quick: a few points per sweep (about a minute on two cores) instead of the full run.
        progress: progress lines on stderr.
        config: override the run size.
        only: names of STUDIES to run [all].
        threads: torch (and OpenCV) threads for the run, restored afterwards; None keeps the settings [1].
        cluster: None, or `auto` / a Ray address: the studies run as Ray tasks (`tiltfit.experiments.cluster`), same outputs.
    Returns:
        StabilityResult.
    """
    previous = torch.get_num_threads()
    cv2_previous = None
    if threads is not None:
        torch.set_num_threads(threads)
        try:
            import cv2

            cv2_previous = cv2.getNumThreads()
            cv2.setNumThreads(threads)
        except ImportError:
            pass
    try:
        return _run(out_dir, quick, progress, config, only, cluster)
    finally:
        torch.set_num_threads(previous)
        if cv2_previous is not None:
            import cv2

            cv2.setNumThreads(cv2_previous)


def _run(out_dir, quick, progress, config, only, cluster=None) -> StabilityResult:
    cfg = config or (StabilityConfig.quick() if quick else StabilityConfig.full())
    names = list(STUDIES) if only is None else list(only)
    unknown = [n for n in names if n not in STUDIES]
    if unknown:
        raise ValueError(f"only: unknown study {unknown[0]!r} (expected some of {', '.join(STUDIES)})")
    log = _Log(progress)
    os.makedirs(out_dir, exist_ok=True)
    studies, files = {}, {}
    from ..cluster import run_studies

    for name, study in run_studies(STUDIES, names, cfg, log, cluster):
        studies[name] = study
        files[name] = write_study(out_dir, study)
        log(f"{name}: done in {study.runtime_s:.1f} s")
    runtime = log.elapsed
    files["summary"] = write_summary(out_dir, studies, cfg, quick, runtime)
    with open(os.path.join(out_dir, "run.json"), "w", encoding="utf-8") as f:
        json.dump(_json_clean({"config": asdict(cfg), "quick": quick, "runtime_s": runtime,
                               "study_runtime_s": {n: s.runtime_s for n, s in studies.items()},
                               "torch_threads": torch.get_num_threads(), "files": files}), f, indent=1)
    files["run"] = "run.json"
    print(summary_text(studies))
    log(f"done: outputs in {out_dir}")
    return StabilityResult(studies, files, runtime)


def write_study(out_dir: str, study: Study) -> dict:
    """`name`.json (rows, findings, data), `name`.csv (rows) and `name`.png; returns {kind: file}."""
    files = {}
    with open(os.path.join(out_dir, f"{study.name}.json"), "w", encoding="utf-8") as f:
        json.dump(_json_clean({"title": study.title, "findings": study.findings, "rows": study.rows,
                               "data": study.data, "runtime_s": study.runtime_s}), f, indent=1)
    files["json"] = f"{study.name}.json"
    write_csv(study.rows, os.path.join(out_dir, f"{study.name}.csv"))
    files["csv"] = f"{study.name}.csv"
    if study.name == "gamma_noise":
        write_csv(study.data["noise"], os.path.join(out_dir, "gamma_noise_calibration.csv"))
        files["csv_calibration"] = "gamma_noise_calibration.csv"
    if study.figure is not None:
        save_figure(study.figure, os.path.join(out_dir, f"{study.name}.png"))
        files["png"] = f"{study.name}.png"
    return files


def summary_text(studies: dict) -> str:
    """The findings, one bullet each, under each study's title (plain Markdown)."""
    parts = []
    for s in studies.values():
        parts.append(f"## {s.title}\n")
        parts += [f"- {x}" for x in s.findings]
        parts.append("")
    return "\n".join(parts)


def write_summary(out_dir: str, studies: dict, cfg: StabilityConfig, quick: bool, runtime: float) -> str:
    """stability.md: every finding with its number, then each study's table and plot."""
    folder = os.path.basename(os.path.abspath(out_dir))
    parts = ["# Where each method fails, and how ours behaves there\n",
             f"Command: `tiltfit stability{' --quick' if quick else ''} -o {folder}`"
             f"; {runtime:.0f} s, {torch.get_num_threads()} torch thread(s). Every number below is computed by the "
             f"run; the closed forms are in `tiltfit/experiments/stability/closed_forms.py`.\n", summary_text(studies), "# Tables\n"]
    for s in studies.values():
        parts.append(f"## {s.title}\n")
        parts.append(f"![{s.name}]({s.name}.png)\n" if s.figure is not None else "")
        parts.append(markdown_table(s.rows, floatfmt=".4g"))
        if s.name == "gamma_noise":
            parts.append("\nCalibration against noise (`gamma_noise_calibration.csv`):\n")
            parts.append(markdown_table(s.data["noise"], floatfmt=".4g"))
    with open(os.path.join(out_dir, "stability.md"), "w", encoding="utf-8") as f:
        f.write("\n".join(parts))
    return "stability.md"


def main(argv=None) -> int:
    """`tiltfit stability [--quick] [-o DIR] [--only NAME ...]` (also `python -m tiltfit.experiments.stability`)."""
    ap = argparse.ArgumentParser(prog="tiltfit stability", description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="a few points per sweep (about a minute)")
    ap.add_argument("-o", "--output", default="stability_out", help="output folder [stability_out]")
    ap.add_argument("--only", nargs="+", choices=list(STUDIES), metavar="NAME",
                    help=f"run only these sweeps ({', '.join(STUDIES)})")
    ap.add_argument("--threads", type=int, default=1, help="torch threads [1]; 0 keeps torch's default")
    ap.add_argument("--cluster", metavar="auto|ADDRESS",
                    help="run the studies as Ray tasks (auto: the running cluster, else a local one)")
    args = ap.parse_args(argv)
    if os.path.exists(args.output) and not os.path.isdir(args.output):
        print(f"tiltfit stability: {args.output}: not a folder", file=sys.stderr)
        return 2
    try:
        run(args.output, quick=args.quick, only=args.only, threads=args.threads or None, cluster=args.cluster)
    except (ImportError, ConnectionError) as e:
        print(f"tiltfit stability: {one_line(e)}", file=sys.stderr)
        return 2
    except OSError as e:
        print(f"tiltfit stability: {e.filename or args.output}: cannot write ({os_reason(e)})", file=sys.stderr)
        return 2
    return 0

