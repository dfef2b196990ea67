"""Real against rendered on the shipped photo sets: how many samples per pixel the report's renderings need.

    python benchmarks/renderer/bench_real_vs_rendered.py [--sets industrial_ds1 gopro_wide] [--views 2] [--spp 1 2 4 8]
        [--reference-spp 32] [--calib SET=CALIB.json ...]

For each set: a calibration with the defaults from the cached detections (tests/real_detections.py; or the
given CALIB.json), then for a few views spread over the set the report's comparison (`tiltfit.report.real_vs_rendered`,
at its default resolution) at each spp and at the reference spp (the peer: the converged rendering, same run).
Reported per spp: the median over views of |profile error − the reference's| and |RMS over the board − the
reference's| (grey levels) and the median render time per view (s). The default spp is the smallest whose
profile errors are within STABLE_GREY of the reference's.

Writes benchmarks/results/real_vs_rendered.{json,md}.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))

from benchmarks.results_io import ROOT, add_output_options, markdown_only, save  # noqa: E402

#: The profile error a reader can tell apart (grey levels): spp whose errors move less than this are enough.
STABLE_GREY = 0.1
PIXEL_PITCH_MM = 0.00155  # as benchmarks/calibration/bench_real_calib.py; pixels and profiles do not depend on it


def calibration_file(name: str, given: dict, say) -> str:
    """A CALIB.json of the set (the given one, else the defaults from the cached detections, cached in /tmp)."""
    if name in given:
        return given[name]
    path = os.path.join(tempfile.gettempdir(), f"bench_real_vs_rendered_{name}.json")
    if os.path.exists(path):
        return path
    from tests.real_detections import observations
    from tiltfit.files.calib import calib_dict, write_calib
    from tiltfit.calibrate.flow import calibrate
    from tiltfit.calibrate.fit import FitOptions

    folder = os.path.join(ROOT, "data", "real", name)
    obs, _ = observations(folder, PIXEL_PITCH_MM)
    t = time.perf_counter()
    res = calibrate(obs, "unified", options=FitOptions())
    with open(os.path.join(folder, "target.json"), encoding="utf-8") as f:
        d = calib_dict(res, obs=obs, target=json.load(f))
    for v in d["views"]:
        v["image"] = os.path.join(folder, v["image"])
    write_calib(path, d)
    say(f"[{name}] calibrated in {time.perf_counter() - t:.0f} s")
    return path


def run(args) -> dict:
    from tiltfit.files.calibrated import Calibration
    from tiltfit.report.real_vs_rendered import RealVsRenderedOptions, compare_view, find_photo, pick_views

    say = lambda m: print(m, file=sys.stderr, flush=True)  # noqa: E731
    given = dict(s.split("=", 1) for s in args.calib)
    res = {"spp": args.spp, "reference_spp": args.reference_spp, "stable_grey": STABLE_GREY, "sets": {}}
    for name in args.sets:
        path = calibration_file(name, given, say)
        cal = Calibration.read(path)
        views = pick_views(len(cal.views), RealVsRenderedOptions(max_views=args.views))
        rows = []
        for v in views:
            photo = find_photo(cal.views[v]["image"], path, [os.path.join(ROOT, "data", "real", name)])
            per = {}
            for spp in list(args.spp) + [args.reference_spp]:
                c = compare_view(cal, cal.target, v, photo, RealVsRenderedOptions(spp=spp))
                per[spp] = {"profile_error": c.profile_error, "profile_errors": {r["line"]: r["average_error"]
                                                                                 for r in c.rows},
                            "rms_board": c.rms_board, "render_s": c.render_s, "scale": c.scale}
                say(f"[{name}] view {v} spp {spp}: profile error {c.profile_error:.3f}, RMS {c.rms_board:.3f}, "
                    f"{c.render_s:.1f} s")
            rows.append({"view": v, "image": os.path.basename(photo), "by_spp": per})
        res["sets"][name] = {"calibration": path, "views": rows}
    summary = {}
    for spp in args.spp:
        dp, dr, ts = [], [], []
        for s in res["sets"].values():
            for row in s["views"]:
                a, ref = row["by_spp"][spp], row["by_spp"][args.reference_spp]
                dp += [abs(a["profile_errors"][k] - ref["profile_errors"][k]) for k in ref["profile_errors"]]
                dr.append(abs(a["rms_board"] - ref["rms_board"]))
                ts.append(a["render_s"])
        summary[spp] = {"median_abs_profile_change": statistics.median(dp), "max_abs_profile_change": max(dp),
                        "median_abs_rms_change": statistics.median(dr), "median_render_s": statistics.median(ts)}
    res["summary"] = summary
    ref_t = [row["by_spp"][args.reference_spp]["render_s"] for s in res["sets"].values() for row in s["views"]]
    res["reference_median_render_s"] = statistics.median(ref_t)
    stable = [spp for spp in args.spp if summary[spp]["max_abs_profile_change"] <= STABLE_GREY]
    res["smallest_stable_spp"] = min(stable) if stable else None
    return res


def write_markdown(path: str, res: dict) -> None:
    lines = ["# Real against rendered: samples per pixel of the report's renderings", "",
             f"Reference: spp {res['reference_spp']} (median {res['reference_median_render_s']:.1f} s per view). "
             f"Profile errors (grey levels, 3 lines per view) and RMS over the board against the reference's; "
             f"stable = every line within {res['stable_grey']} grey level. Smallest stable spp: "
             f"{res['smallest_stable_spp']}.", "",
             "| spp | median abs change of a profile error | max | median abs change of RMS over the board | "
             "median render s per view |", "|---|---|---|---|---|"]
    for spp, s in res["summary"].items():
        lines.append(f"| {spp} | {s['median_abs_profile_change']:.3f} | {s['max_abs_profile_change']:.3f} | "
                     f"{s['median_abs_rms_change']:.3f} | {s['median_render_s']:.1f} |")
    lines += ["", "| set | view | image | profile error (spp → value) | RMS over the board at the reference |",
              "|---|---|---|---|---|"]
    for name, s in res["sets"].items():
        for row in s["views"]:
            by = row["by_spp"]
            seq = ", ".join(f"{k}: {v['profile_error']:.2f}" for k, v in by.items())
            ref = by[str(res["reference_spp"])] if str(res["reference_spp"]) in by else by[res["reference_spp"]]
            lines.append(f"| {name} | {row['view']} | {row['image']} | {seq} | {ref['rms_board']:.2f} |")
    lines += ["", "Reproduce: `python benchmarks/renderer/bench_real_vs_rendered.py` (machine load changes the times, not the "
                  "errors)."]
    with open(path, "w", encoding="utf-8") as f:
        f.write("\n".join(lines) + "\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sets", nargs="+", default=["industrial_ds1", "gopro_wide"])
    ap.add_argument("--views", type=int, default=2, help="views per set, spread over the set [2]")
    ap.add_argument("--spp", type=int, nargs="+", default=[1, 2, 4, 8])
    ap.add_argument("--reference-spp", type=int, default=32)
    ap.add_argument("--calib", nargs="*", default=[], metavar="SET=CALIB.json")
    add_output_options(ap, "real_vs_rendered")
    args = ap.parse_args(argv)
    if markdown_only(args, write_markdown):
        return 0
    save(args.out, json.loads(json.dumps(run(args))), write_markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
