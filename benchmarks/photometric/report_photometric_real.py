"""`tiltfit report`'s photometric residual images on a few views of the shipped real sets (issue 30 §5: when the
refinement is rejected on real photos, the report shows why).

For each set: `tiltfit calibrate` with `--refine photometric` on the first N photos with a board (detections from the
cache beside the photos, `tests/real_detections.py`, as bench_photometric_real_bounds.py does), then
`tiltfit report CALIB.json --views 0,..,N-1` (the real-against-rendered page at spp 2); what report.md says on the
refinement (kept, the trust-bound sentence, each view's residual RMS) and the time the residual images took, and the
residual images copied beside the results. No peer: neither OpenCV nor mrcal renders a photometric residual.

    python benchmarks/photometric/report_photometric_real.py [--views 3]

Writes OUT.{json,md} and OUT/SET_view_KK.png (OUT: --out, default benchmarks/results/report_photometric_real).
"""
from __future__ import annotations

import os
import re
import shutil
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)

from benchmarks.results_io import run_benchmark, write_lines  # noqa: E402

#: Set -> pixel pitch (mm), as bench_photometric_real_bounds.py takes them.
SETS = {"industrial_ds1": 0.0048, "gopro_wide": 0.005}


def run_set(name: str, pitch_mm: float, n_views: int, figures_dir: str) -> dict:
    from benchmarks.photometric.photometric_start import calibrate_refined_cached

    from tiltfit.cli import main as cli
    from tiltfit.report import photometric as report

    timings = []
    plain = report.photometric_residual

    def timed_residual(*a, **k):
        t = time.perf_counter()
        out = plain(*a, **k)
        timings.append({"s": time.perf_counter() - t, "pixels": out.n_pixels, "stride": out.stride})
        return out

    with tempfile.TemporaryDirectory() as tmp:
        calib, out = os.path.join(tmp, "CALIB.json"), os.path.join(tmp, "report")
        names, _, status, calibrate_s = calibrate_refined_cached(name, pitch_mm, n_views, calib)
        report.photometric_residual = timed_residual
        t0 = time.perf_counter()
        try:
            report_status = cli.main(["report", calib, "-o", out, "--views", ",".join(map(str, range(len(names)))),
                                      "--spp", "2", "-q"])
        finally:
            report.photometric_residual = plain
        report_s = time.perf_counter() - t0
        md = open(os.path.join(out, "report.md"), encoding="utf-8").read()
        os.makedirs(figures_dir, exist_ok=True)
        figures = []
        for f in sorted(os.listdir(out)):
            m = re.fullmatch(r"photometric_residual_view_(\d+)\.png", f)
            if m:
                figures.append(f"{os.path.basename(figures_dir)}/{name}_view_{m.group(1)}.png")
                shutil.copy(os.path.join(out, f), os.path.join(os.path.dirname(figures_dir), figures[-1]))
    section = md[md.index("## Photometric refinement"):md.index("## Real against rendered")]
    section = "\n".join(line for line in section.splitlines() if not line.startswith("!["))
    return {"set": name, "views": names, "calibrate_exit": status, "calibrate_s": calibrate_s,
            "report_exit": report_status, "report_s": report_s, "residual_timings": timings,
            "report_md_photometric": section.strip(), "figures": figures}


def measure(args) -> dict:
    rows = []
    for name, pitch in SETS.items():
        print(f"set {name}", file=sys.stderr, flush=True)
        rows.append(run_set(name, pitch, args.views, args.out))
    return {"command": f"python benchmarks/photometric/report_photometric_real.py --views {args.views}",
            "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "sets": rows}


def write_markdown(path: str, res: dict) -> None:
    L = ["# `tiltfit report`'s photometric residual images on the shipped real sets (issue 30 §5)", "",
         f"`{res['command']}`, {res['created']}: `tiltfit calibrate --refine photometric` on the first views with a "
         "board (cached detections), then `tiltfit report` on them. No peer: neither OpenCV nor mrcal draws a "
         "photometric residual.", ""]
    for s in res["sets"]:
        t = s["residual_timings"]
        per_view = sorted(x["s"] for x in t)
        median = per_view[len(per_view) // 2] if per_view else float("nan")
        L += [f"## {s['set']} ({', '.join(s['views'])})", "",
              f"- calibrate: exit {s['calibrate_exit']}, {s['calibrate_s']:.0f} s; report: exit {s['report_exit']}, "
              f"{s['report_s']:.0f} s in all, residual images median {median:.1f} s a view "
              "(" + ", ".join(f"{x['pixels']} pixels, stride {x['stride']}" for x in t) + ")", "",
              "report.md's section:", "", *("> " + line for line in s["report_md_photometric"].splitlines()), "",
              *(f"![{f}]({f})" for f in s["figures"]), ""]
    write_lines(path, L)


if __name__ == "__main__":
    sys.exit(run_benchmark(__doc__, "report_photometric_real", measure, write_markdown, views=3))
