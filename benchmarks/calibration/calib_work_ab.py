"""The default calibration's work and CPU time with the code of two trees, alternating (issue 32 §0): a change's
own stage measured where the whole calibration's CPU time is noisier than the change (a loaded 2-core machine).

    python benchmarks/calibration/calib_work_ab.py count TREE SET     -> linear solves of the LM fits, blur-stage fits
    python benchmarks/calibration/calib_work_ab.py time TREE SET      -> [[whole, blur stage] CPU s] of 2 timed runs
    (TREE: a folder whose tiltfit/, renderer/, camio/ are imported, e.g. `git archive COMMIT tiltfit renderer camio
    | tar -x -C DIR`; SET: as `bench_calib_real_speed.observations`, its data read from this checkout)

`time` makes one warm-up calibration, then two timed ones (`time.process_time`, one torch thread); call it for
each tree in turn, several rounds, and take medians (benchmarks/results/calib_blurstage_ab.md).
"""
import collections
import json
import os
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))


def main(what: str, code: str, name: str):
    sys.path.insert(0, os.path.abspath(code))
    sys.path.insert(1, HERE)
    import torch

    torch.set_num_threads(1)
    from bench_calib_real_speed import observations

    import tiltfit.calibrate.blur_stage as bs
    import tiltfit.calibrate.flow as flow
    from tiltfit.calibrate.fit import FitOptions
    from tiltfit.calibrate.photos import fit_with_held_out
    from tiltfit.solve import blocks, points

    assert flow.__file__.startswith(os.path.abspath(code)), flow.__file__
    obs = observations(name, ROOT)
    run = lambda: fit_with_held_out(obs, "unified", options=FitOptions(distortion="auto", board="auto"))  # noqa: E731
    if what == "count":
        count = collections.Counter()
        for cls in (blocks.DenseNormal, blocks.SchurNormal, points.PointSchurNormal):
            def solve(self, damping, rhs, _solve=cls.solve):
                count["linear solves"] += 1
                return _solve(self, damping, rhs)
            cls.solve = solve
        fit = bs._fit_camera

        def counted(cam, *a, **k):
            count["blur-stage fits, offset " + ("free" if cam.blur_offset_px.requires_grad else "held")] += 1
            return fit(cam, *a, **k)
        bs._fit_camera = counted
        run()
        print(json.dumps({"set": name, "tree": code, **count}))
        return
    stage = []
    blur_stage = flow.blur_stage

    def timed(*a, **k):
        t = time.process_time()
        out = blur_stage(*a, **k)
        stage.append(time.process_time() - t)
        return out
    flow.blur_stage = timed
    run()
    out = []
    for _ in range(2):
        stage.clear()
        t = time.process_time()
        run()
        out.append([time.process_time() - t, sum(stage)])
    print(json.dumps({"set": name, "tree": code, "cpu_s": out}))


if __name__ == "__main__":
    main(*sys.argv[1:4])
