"""Rebuild the calibrations of the shipped real sets that tests, the report's examples and benchmarks read:

    .venv/bin/python tests/data/calibrations/make.py      # writes industrial_ds1.json, gopro_wide.json here

Each is `tiltfit calibrate`'s CALIB.json with the defaults (distortion auto, board auto) from tiltfit's cached
detections of the set's photos (data/real/SET/detections_tiltfit.json), the views' `image` the photo's file
name in data/real/SET/. Pixel pitch as in docs/real_cameras.md: industrial_ds1 0.00155 mm, gopro_wide 0.005 mm.
"""
from __future__ import annotations

import json
import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(os.path.dirname(HERE)))
SETS = {"industrial_ds1": 0.00155, "gopro_wide": 0.005}


def main() -> int:
    sys.path.insert(0, os.path.join(ROOT, "tests"))
    from real_detections import observations

    from tiltfit.files.calib import calib_dict, write_calib
    from tiltfit.calibrate.flow import calibrate
    from tiltfit.calibrate.fit import FitOptions

    for name, pitch in SETS.items():
        folder = os.path.join(ROOT, "data", "real", name)
        obs, _ = observations(folder, pitch)
        res = calibrate(obs, "unified", options=FitOptions(distortion="auto", board="auto"))
        with open(os.path.join(folder, "target.json"), encoding="utf-8") as f:
            target = json.load(f)
        data = calib_dict(res, obs=obs, target=target)
        data.pop("created", None)
        data["runtime_s"] = None
        write_calib(os.path.join(HERE, f"{name}.json"), data)
        print(f"{name}: {obs.n_views} views, RMS {data['rms_reprojection_px']:.3f} px, "
              f"distortion {data['distortion_model']}, board {(data.get('board') or {}).get('model')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
