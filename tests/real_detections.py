"""Test fixture: tiltfit's own detections (corners and blur widths) of the shipped real photo sets, cached beside
the photos, and the Observations built from them.

    python tests/real_detections.py [SET ...]      (default: every folder under data/real/ with a target.json)

Writes data/real/SET/detections_tiltfit.json: {image basename: DET.json dict | {"no_board": reason}}, one image
per line. The detections are made through the public API (`renderer.read_image`, `tiltfit.detect.charuco.detect_board`,
`Detection.to_json_dict`), the steps `tiltfit detect` takes, so `tiltfit calibrate` run on the photos detects
exactly these (tests/tiltfit/test_calibrate_defaults.py checks one image against a fresh `tiltfit detect`). Tests
and benchmarks read the cache instead of detecting again (about 3 s per photo):

    sys.path.insert(0, "tests"); from real_detections import observations          (tests)
    sys.path.insert(0, ROOT);    from tests.real_detections import observations    (benchmarks)
"""
from __future__ import annotations

import glob
import json
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
REAL = os.path.join(ROOT, "data", "real")
CACHE_NAME = "detections_tiltfit.json"


def photos(folder: str) -> list[str]:
    """The photo files of a set (JPEG or PNG), sorted."""
    return sorted(p for p in glob.glob(os.path.join(folder, "*")) if p.lower().endswith((".jpg", ".jpeg", ".png")))


def detect_one(path: str, target) -> dict:
    """The DET.json dict of `path` (corners and blur widths, as `tiltfit detect` finds them), or
    {"no_board": reason} where no corner could be placed."""
    from renderer import read_image
    from tiltfit.detect.charuco import detect_board
    from tiltfit.files.det import MAX_IMAGE_PIXELS

    found = detect_board(read_image(path, None, MAX_IMAGE_PIXELS), target)
    det = found.to_json_dict()
    if det.get("grid_found") and any(c is not None for c in det["corners_px"]):
        return det
    why = getattr(found, "message", "") or ""
    return {"no_board": "no board found" + (f" ({why})" if why else "")}


def read_cache(folder: str, name: str = CACHE_NAME) -> dict:
    """The cache file `name` of a set folder as a dict."""
    with open(os.path.join(folder, name), encoding="utf-8") as f:
        return json.load(f)


def write_cache(folder: str, say=print) -> dict:
    """Detect every photo of a set folder and write its cache; returns the dict written."""
    from tiltfit.target.layout import load_target

    target = load_target(os.path.join(folder, "target.json"))
    out = {}
    for p in photos(folder):
        out[os.path.basename(p)] = det = detect_one(p, target)
        say(f"{os.path.basename(p)}: " + ("no board" if "no_board" in det else
                                          f"{sum(c is not None for c in det['corners_px'])} corners"))
    with open(os.path.join(folder, CACHE_NAME), "w", encoding="utf-8") as f:
        f.write("{\n" + ",\n".join(f"{json.dumps(k)}: {json.dumps(v)}" for k, v in sorted(out.items())) + "\n}\n")
    return out


def observations(folder: str, pixel_pitch_mm: float, cache_name: str = CACHE_NAME):
    """(Observations of the photos with a board from the cache, names of those without).

    `cache_name`: this module's cache, or another of the same layout whose photos without a board are null
    (corners_opencv.json, benchmarks/calibration/bench_real_calib.py's cv2.findChessboardCornersSB corners).
    """
    import numpy as np

    from tiltfit.calibrate.model import Observations
    from tiltfit.target.layout import load_target

    target = load_target(os.path.join(folder, "target.json"))
    cache = {n: d or {"no_board": "no board found"} for n, d in read_cache(folder, cache_name).items()}
    names = [n for n in sorted(cache) if "no_board" not in cache[n]]
    corners = np.array([[c if c is not None else [np.nan, np.nan] for c in cache[n]["corners_px"]] for n in names],
                       dtype=np.float64)
    blur = np.array([[b if b is not None else np.nan for b in cache[n]["blur_px"]] for n in names], dtype=np.float64)
    size = tuple(cache[names[0]]["image_size_px"])
    return (Observations(target.feature_points(), corners, blur, size, pixel_pitch_mm, names),
            [n for n in sorted(cache) if "no_board" in cache[n]])


def main(argv=None) -> int:
    sets = (argv if argv is not None else sys.argv[1:]) or sorted(
        d for d in os.listdir(REAL) if os.path.isfile(os.path.join(REAL, d, "target.json")))
    for s in sets:
        write_cache(os.path.join(REAL, s), say=lambda m, s=s: print(f"[{s}] {m}", file=sys.stderr, flush=True))
    return 0


if __name__ == "__main__":
    # run as a script, Python puts tests/ first on sys.path, where tests/renderer (a folder of tests, no package)
    # would be taken for the renderer package by a path search that ends there: the repository's root goes first
    sys.path.insert(0, ROOT)
    sys.exit(main())
