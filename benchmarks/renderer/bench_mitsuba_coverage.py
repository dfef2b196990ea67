"""What `renderer render --backend mitsuba` carries over, scene by scene: Mitsuba's mean intensity against ours.

Scenes: every shipped scene file (renderer/scenes/*.json, benchmarks/scenes/*.json) and the case reported in
issue 20 (`ISSUE_SCENE`: a tilted lens above an infinite checkered floor with a sphere and one point light).
For each, two renders by each renderer at the same size and spp (ours: `render(..., intersector="torch")`,
sobol samples; Mitsuba: `renderer.cli.backends.render_mitsuba`, independent samples):
- as is: the scene file unchanged; Mitsuba's list of what it did not map is recorded, and the list this
  module expects from the scene file itself (`expected_not_mapped`, written from the file, not from the
  exporter) beside it;
- mapped part: the same scene with each element in that list neutralised (`neutral_overrides`: the mirror
  and refraction weights set to 0, layers removed, ...), so what remains is what the exporter claims
  to map, and the two images should agree to sampling noise.
The difference is Mitsuba's mean over ours, minus 1. `--before OLD.json` adds the as-is column of a run of
this script on the exporter before issue 20 (its `dropped` list came from `to_mitsuba` alone; where that
exporter failed, the error).

    PYTHONPATH=. .venv/bin/python benchmarks/renderer/bench_mitsuba_coverage.py --before benchmarks/results/mitsuba_backend_coverage_before.json
    # writes benchmarks/results/mitsuba_backend_coverage.{json,md}

tests/renderer/test_mitsuba_coverage.py runs the same comparisons at a smaller size.
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)

SHIPPED = sorted(glob.glob(os.path.join(ROOT, "renderer", "scenes", "*.json"))
                 + glob.glob(os.path.join(ROOT, "benchmarks", "scenes", "*.json")))

# Issue 20: tilted lens (plane of focus through the floor's far part), an infinite checkered floor, a sphere
# standing on it, one point light; nothing Mitsuba lacks (Lambert only, black background).
ISSUE_SCENE = {
    "image": {"width": 150, "height": 100, "spp": 64, "max_depth": 0},
    "camera": {"type": "thin_lens", "position": [0, -150, 0], "look_at": [0, 0, 500],
               "w": 50, "U": 304.51, "d": 25, "sensor_size": [36, 24], "theta_F_deg": -73.30},
    "lights": [{"type": "point", "position": [-300, -800, 100], "intensity": [2.5e6, 2.5e6, 2.5e6]}],
    "objects": [
        {"name": "floor", "shape": {"type": "plane", "point": [0, 0, 0], "normal": [0, -1, 0]},
         "material": {"texture": {"type": "checker", "size": 25, "colors": [[0.85, 0.82, 0.72], [0.35, 0.35, 0.4]]}}},
        {"name": "ball", "shape": {"type": "sphere", "center": [0, -40, 500], "radius": 40},
         "material": {"color": [0.9, 0.5, 0.3]}},
    ],
}


def scene_files() -> list[str]:
    """The shipped scene files (a JSON list, the gallery manifest, is not a scene)."""
    out = []
    for path in SHIPPED:
        with open(path) as f:
            if isinstance(json.load(f), dict):
                out.append(path)
    return out


def scene_config(source) -> dict:
    """The merged scene dict of a file (its `extends` chain resolved) or a copy of a dict."""
    from renderer.scene.file import read_scene_json

    return read_scene_json(source) if isinstance(source, str) else json.loads(json.dumps(source))


def small(cfg: dict, side: int) -> list[str]:
    """Overrides setting the image's longer side to `side` pixels, keeping its aspect ratio."""
    w, h = cfg["image"]["width"], cfg["image"]["height"]
    k = side / max(w, h)
    return [f"image.width={max(1, round(w * k))}", f"image.height={max(1, round(h * k))}"]


def expected_not_mapped(cfg: dict) -> list[str]:
    """What Mitsuba cannot reproduce of a scene, read off the scene file (the exporter's `dropped` list should
    name exactly these): per object its mirror and refraction terms, and layers."""
    out = []
    if cfg.get("layers"):
        out.append("layers")
    for obj in cfg.get("objects", []):
        material = obj.get("material", {})
        out += [f"{obj['name']}: {key}" for key in ("reflect", "transmit") if material.get(key, 0) > 0]
    return out


def neutral_overrides(cfg: dict) -> list[str]:
    """`--set` overrides removing what `expected_not_mapped` names, leaving what the exporter maps."""
    out = []
    if cfg.get("layers"):
        out.append("layers=[]")
    for obj in cfg.get("objects", []):
        material = obj.get("material", {})
        out += [f"objects.{obj['name']}.material.{key}=0" for key in ("reflect", "transmit")
                if material.get(key, 0) > 0]
    return out


def compare(source, overrides, spp: int, seed: int = 0) -> dict:
    """Render `source` (a scene file or dict) with `overrides` by ours and by Mitsuba (scalar_rgb where no JIT
    variant runs): mean intensities, their relative difference, mean |ours − Mitsuba| over our mean, what the
    exporter dropped, and the seconds each took."""
    import numpy as np

    from renderer import render
    from renderer.cli.backends import render_mitsuba
    from renderer.mitsuba import load_mitsuba, to_mitsuba
    from renderer.scene.file import load_scene

    base_dir = None if isinstance(source, str) else ROOT
    scene = load_scene(source, overrides, base_dir=base_dir)
    load_mitsuba()
    dropped = to_mitsuba(scene, spp)[1]
    t0 = time.perf_counter()
    ours = render(scene, spp=spp, intersector="torch", progress=False).image.numpy()
    t1 = time.perf_counter()
    theirs = render_mitsuba(scene, spp, "independent", seed=seed, progress=False).image.numpy()
    t2 = time.perf_counter()
    mean_ours, mean_theirs = float(ours.mean()), float(theirs.mean())
    return {"ours_mean": mean_ours, "mitsuba_mean": mean_theirs, "rel_diff": mean_theirs / mean_ours - 1,
            "pixel_diff": float(np.abs(ours - theirs).mean()) / mean_ours, "dropped": list(dropped),
            "seconds": {"ours": t1 - t0, "mitsuba": t2 - t1}}


def cases() -> list[tuple[str, object]]:
    """(name, source) of every scene compared: the shipped files, then the issue-20 scene."""
    return [(os.path.relpath(p, ROOT), p) for p in scene_files()] + [("issue 20: tilted lens, checker plane, sphere",
                                                                      ISSUE_SCENE)]


def run(side: int, spp: int) -> dict:
    from renderer.mitsuba import load_mitsuba

    mi = load_mitsuba()
    rows = []
    for name, source in cases():
        cfg = scene_config(source)
        size = small(cfg, side)
        row = {"scene": name, "size": size, "expected_not_mapped": expected_not_mapped(cfg)}
        try:
            row["as_is"] = compare(source, size, spp)
            neutral = neutral_overrides(cfg)
            row["mapped_part"] = compare(source, size + neutral, spp) if neutral else row["as_is"]
        except Exception as e:  # the exporter before issue 20 raised for some scenes: record, go on
            row["error"] = f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"
        rows.append(row)
        if "error" in row:
            print(name, row["error"], file=sys.stderr)
        else:
            print(name, f"as is {_pct(row['as_is']['rel_diff'])}, mapped part {_pct(row['mapped_part']['rel_diff'])}",
                  file=sys.stderr)
    return {"side_px": side, "spp": spp, "mitsuba": mi.__version__, "variant": mi.variant(), "rows": rows}


def _pct(x):
    return f"{100 * x:+.2f} %"


def write_markdown(path: str, res: dict) -> None:
    before = {row["scene"]: row for row in res.get("before", {}).get("rows", [])}
    lines = [
        "# `--backend mitsuba`: mean intensity of Mitsuba's render against ours, per scene",
        "",
        f"Images {res['side_px']} px on the longer side, {res['spp']} spp, Mitsuba {res['mitsuba']} "
        f"({res['variant']}); difference = Mitsuba's mean / ours − 1. *As is*: the scene file unchanged; "
        "*mapped part*: the elements Mitsuba does not reproduce (last column) neutralised, so the two should "
        "agree to sampling noise. *Before*: the exporter before issue 20 on the unchanged scene. "
        "Made by `benchmarks/renderer/bench_mitsuba_coverage.py`.",
        "",
        "| scene | before (as is) | after (as is) | after (mapped part) | per-pixel mean abs. diff. (mapped part) "
        "| not mapped (named on stderr) |",
        "|---|---|---|---|---|---|",
    ]
    for row in res["rows"]:
        old = before.get(row["scene"])
        if old is None:
            was = "–"
        elif "error" in old:
            was = f"failed ({old['error'][:60]})"
        else:
            was = _pct(old["as_is"]["rel_diff"])
        if "error" in row:
            lines.append(f"| {row['scene']} | {was} | failed: {row['error']} | | | |")
            continue
        dropped = "; ".join(row["as_is"]["dropped"]) or "nothing"
        lines.append(f"| {row['scene']} | {was} | {_pct(row['as_is']['rel_diff'])} | "
                     f"{_pct(row['mapped_part']['rel_diff'])} | {100 * row['mapped_part']['pixel_diff']:.1f} % | "
                     f"{dropped} |")
    lines += ["", "Before issue 20 the exporter cut an infinite plane to a 1000-unit square about its point (the "
              "millimetre floor of the tilt scenes and of the issue's case ended half a metre from the camera, "
              "unnamed), put the checker cells of a sphere (and of a plane whose 500-unit half side is not a "
              "whole number of checker periods) elsewhere than ours, named the ambient light and the background "
              "as dropped, kept the full diffuse weight of mirrors and glass, could not export a CSG solid, and "
              "failed on cones, polyhedra and meshes in Mitsuba's scalar variant. Its column is the same script "
              "run on that exporter (`mitsuba_backend_coverage_before.json`).", ""]
    with open(path, "w") as f:
        f.write("\n".join(lines))


def main(argv=None) -> int:
    from benchmarks.results_io import add_output_options, markdown_only, save

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--side", type=int, default=96, help="longer image side, pixels [96]")
    ap.add_argument("--spp", type=int, default=64, help="samples per pixel [64]")
    ap.add_argument("--before", help="a JSON written by this script on the exporter before issue 20")
    ap.add_argument("--json-only", action="store_true", help="write OUT.json only (for the --before run)")
    add_output_options(ap, "mitsuba_backend_coverage")
    args = ap.parse_args(argv)
    if markdown_only(args, write_markdown):
        return 0
    res = run(args.side, args.spp)
    if args.before:
        with open(args.before) as f:
            res["before"] = json.load(f)
    if args.json_only:
        with open(args.out + ".json", "w") as f:
            json.dump(res, f, indent=1)
        return 0
    save(args.out, res, write_markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
