"""Where the default calibration's CPU time goes, without a profiler's overhead (issue 32 §0).

    cd TREE && python benchmarks/history/diag_calib_cost_split.py [--set industrial_60] [--repeats 2]

`cProfile` charges every Python call its own overhead, so code made of many small calls (`copy.deepcopy` of a
camera, `_Problem`'s set-up) looks several times dearer under it than it is: on industrial_60 it gave the camera
copies 0.46 s and `_Problem.__init__` 0.39 s of 12 s, where they take 0.09 s and 0.15 s of 10 s unprofiled. Here
each named function is wrapped by a timer (`time.process_time`, one torch thread; nested ones counted in each) and
`fit_with_held_out` (the default calibration: distortion auto, board auto) runs once to warm up, then `--repeats`
times; prints the last run's CPU seconds and calls per function, and the LM iterations of each held-out fold and
prediction. The code is the tree in the cwd (the "before" of a change: run it from that checkout). Writes nothing.
"""
from __future__ import annotations

import argparse
import collections
import functools
import os
import sys
import time

ROOT = os.getcwd()
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, "benchmarks", "calibration"))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--set", default="industrial_60")
    ap.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args()

    import torch

    torch.set_num_threads(1)
    from bench_calib_real_speed import observations

    import tiltfit.calibrate.fit as fit
    import tiltfit.calibrate.problem as problem
    import tiltfit.select.held_out as held_out
    from renderer.cameras.lens_model import LensCamera
    from tiltfit.calibrate.fit import FitOptions
    from tiltfit.calibrate.photos import fit_with_held_out

    spent = collections.defaultdict(lambda: [0.0, 0])
    folds = []

    def timed(owner, name, label):
        f = getattr(owner, name)

        @functools.wraps(f)
        def g(*a, **k):
            t = time.process_time()
            try:
                return f(*a, **k)
            finally:
                spent[label][0] += time.process_time() - t
                spent[label][1] += 1

        setattr(owner, name, g)

    for owner, name in ((LensCamera, "copy"), (LensCamera, "jacobian"), (problem._Problem, "__init__"),
                        (problem._Problem, "_raw_jacobian_matrix"), (problem, "solve_lm"), (fit, "_fit_camera"),
                        (fit, "residuals"), (fit, "uncertainties"), (held_out, "initialize"),
                        (held_out, "predict_views"), (held_out, "held_out_rms")):
        timed(owner, name, f"{getattr(owner, '__name__', '')}.{name}")
    fold_fit = held_out.fit_geometry

    def counted(*a, **k):
        out = fold_fit(*a, **k)
        folds.append(("predictions" if k.get("hold_distortion") else a[2].distortion, out.iterations))
        return out

    held_out.fit_geometry = counted  # the candidates' fits on all views, the folds' and the held-out predictions
    obs = observations(args.set, ROOT)
    options = FitOptions(distortion="auto", board="auto")
    fit_with_held_out(obs, "unified", options=options)
    for _ in range(args.repeats):
        spent.clear()
        folds.clear()
        t0 = time.process_time()
        fit_with_held_out(obs, "unified", options=options)
        total = time.process_time() - t0
        print(f"{args.set}: {total:.2f} s CPU")
    for label, (t, n) in sorted(spent.items(), key=lambda kv: -kv[1][0]):
        print(f"  {label:40s} {t:7.3f} s {n:5d} calls {1e3 * t / max(n, 1):8.2f} ms a call")
    by_model = collections.defaultdict(list)
    for model, iterations in folds:
        by_model[model].append(iterations)
    print("  LM iterations of the distortion candidates' fits (on all views, then their folds) and of the held-out "
          "predictions, by model:",
          {m: its for m, its in by_model.items()})


if __name__ == "__main__":
    main()
