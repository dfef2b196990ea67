"""Render a CG object into a real photo through the photo's calibration, and check the calibrated camera first.

    python examples/composite.py [--set gopro_wide|industrial_ds1] [--view IMAGE] [--spp 8] [--out DIR]
                                 [--picture docs/composite.png]

1. Calibrate the shipped photo set from its cached detections (`data/real/SET/detections_tiltfit.json`, what
   `tiltfit detect` finds in each photo) with `tiltfit calibrate`'s defaults, the board held flat: the board
   rendered below is the flat printed target, so the calibration must describe that board. Written to
   DIR/calib.json.
2. The check: the board rendered alone through the calibrated camera of one view (distortion and defocus
   included), its corners measured as `tiltfit detect` measures a photo's, must lie where the photo's corners
   are, within the calibration's reprojection error of that view (times 1.5), and where the calibration projects
   them (0.1 px). Exit status 1 otherwise.
3. The composite: a glossy sphere and a box standing on the board, lit by a point light above the camera (where
   the room's ceiling lights are) and an ambient fill, rendered through the same camera; the board and the wall
   it hangs on (a plane just behind it) catch their shadows. Differential rendering (Debevec 1998): the objects'
   pixels come from the render at the photo's exposure and white balance; elsewhere the photo is multiplied by
   the ratio of the board and wall rendered with and without the objects, which lays their shadows onto the real
   ones. Only a window around the objects and their shadows is rendered.
Writes DIR/calib.json, DIR/alignment.json, DIR/composite.png (full size) and, with --picture, a small copy for
the docs. Uses only the public API: `tiltfit.calibrate.flow.calibrate`, `tiltfit.files.calibrated.Calibration`,
`tiltfit.report.composite`, `renderer.load_scene`.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
REAL = os.path.join(HERE, "..", "data", "real")
#: Pixel pitch (mm) assumed for each shipped set (not published for either; pixel results do not depend on it).
PITCH_MM = {"gopro_wide": 0.005, "industrial_ds1": 0.00155}
DEFAULT_VIEW = {"gopro_wide": "GOPR0043.jpg", "industrial_ds1": "Image__2018-09-17__16-39-17.png"}
#: Largest rendered-against-photo corner RMS, as a multiple of the calibration's RMS for that view, and largest
#: rendered-against-projected RMS (px): the check's thresholds.
PHOTO_FACTOR, PROJECTION_PX = 1.5, 0.1


def calibrate_from_cache(folder: str, pixel_pitch_mm: float):
    """(CALIB.json dict, target) of a shipped set from its cached detections, the board flat."""
    from tiltfit.files.calib import calib_dict
    from tiltfit.calibrate.flow import calibrate
    from tiltfit.calibrate.fit import FitOptions
    from tiltfit.calibrate.model import Observations
    from tiltfit.target.layout import load_target

    target = load_target(os.path.join(folder, "target.json"))
    with open(os.path.join(folder, "detections_tiltfit.json"), encoding="utf-8") as f:
        cache = json.load(f)
    names = sorted(n for n, det in cache.items() if "no_board" not in det)

    def table(key, missing):
        return np.array([[v if v is not None else missing for v in cache[n][key]] for n in names], dtype=np.float64)

    obs = Observations(target.feature_points(), table("corners_px", [math.nan] * 2), table("blur_px", math.nan),
                       tuple(cache[names[0]]["image_size_px"]), pixel_pitch_mm, names)
    result = calibrate(obs, "unified", options=FitOptions(distortion="auto", board="flat"))
    data = calib_dict(result, obs=obs, target=target.to_dict())
    for v in data["views"]:
        v["image"] = os.path.abspath(os.path.join(folder, v["image"]))
    return data, target, cache


def photo_corners(cache: dict, view_name: str) -> np.ndarray:
    """(N, 2) the photo's detected corners (NaN where none) from the detection cache."""
    return np.array([c if c is not None else [math.nan] * 2 for c in cache[os.path.basename(view_name)]["corners_px"]],
                    dtype=np.float64)


def object_scene(calib_path: str, view, target_path: str, cal, objects_only: bool = False, lights: bool = True):
    """The scene dict: the board and the wall it hangs on (unless objects_only) and the CG objects standing on
    it, lit from above the camera; with lights=False, white objects under unit ambient light (their render is
    their coverage). Returns (scene, the objects' bounding-box corners (16, 3), the light's position)."""
    R, T = cal.pose(view)
    camera_centre = -R.T @ T                         # target frame
    front = -1.0 if camera_centre[2] < 0 else 1.0    # the board's side facing the camera (Z sign)
    up = R.T @ np.array([0.0, -1.0, 0.0])            # the photo's up, in the target frame
    up -= up[2] * np.array([0, 0, 1.0])
    up /= np.linalg.norm(up)
    side = np.cross(up, [0, 0, front])
    x0, y0, x1, y1 = cal.target.extent_mm
    centre = np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0])
    size = min(x1 - x0, y1 - y0)
    r = 0.16 * size
    ball = centre - 0.12 * size * side + [0, 0, front * r]
    box_size = 0.22 * size
    box = centre + 0.22 * size * side - 0.18 * size * up + [0, 0, front * box_size / 2]
    light = centre + 4.0 * size * up + 1.0 * size * side + [0, 0, front * 3.0 * size]
    gloss = {"color": [0.75, 0.12, 0.05], "specular": 0.5, "shininess": 80}
    matte = {"color": [0.15, 0.35, 0.75]}
    if not lights:
        gloss = matte = {"color": [1, 1, 1], "specular": 0}
    objects = [{"name": "ball", "shape": {"type": "sphere", "center": ball.tolist(), "radius": r}, "material": gloss},
               {"name": "box", "shape": {"type": "box", "center": box.tolist(), "size": [box_size] * 3,
                                         "rotation_deg": [0, 0, 30]}, "material": matte}]
    if not objects_only:
        # the local scene that catches the shadows: the board, and the wall 0.1 mm behind it (so close that the
        # board's edge casts no visible shadow on it)
        objects[:0] = [{"name": "board", "shape": {"type": "target", "file": target_path}},
                       {"name": "wall", "shape": {"type": "plane", "point": [0, 0, -0.1 * front], "normal": [0, 0, front]}}]
    distance = float(np.linalg.norm(light - centre))
    scene = {"image": {"spp": 1, "max_depth": 2},
             "camera": {"type": "calibrated", "file": calib_path, "view": view},
             "lights": ([{"type": "point", "position": light.tolist(), "intensity": [2.0 * distance ** 2] * 3},
                         {"type": "ambient", "intensity": [0.35] * 3}] if lights else
                        [{"type": "ambient", "intensity": [1, 1, 1]}]),
             "objects": objects}
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)
    extent = np.concatenate([ball + r * corners, box + 0.9 * box_size * corners])  # the objects' bounding boxes
    return scene, extent, light


def shadow_points(points, light):
    """Where the rays from the light through `points` (N, 3) meet the board plane Z = 0."""
    t = -light[2] / (points[:, 2] - light[2])
    return light + t[:, None] * (points - light)


def check_args(args) -> str | None:
    """The first problem with the command line as one line naming the option, or None."""
    from renderer.core.params import MAX_SPP

    if not 1 <= args.spp <= MAX_SPP:
        return f"--spp: expected an integer in 1..{MAX_SPP}, got {args.spp}"
    if os.path.exists(args.out) and not os.path.isdir(args.out):
        return f"--out: {args.out}: not a folder"
    if args.picture:
        folder = os.path.dirname(os.path.abspath(args.picture))
        if not os.path.isdir(folder):
            return f"--picture: {args.picture}: no folder {folder}"
        if not args.picture.lower().endswith((".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr")):
            return f"--picture: {args.picture}: expected a .png, .jpg, .tif or .exr file name"
    if args.view:
        with open(os.path.join(REAL, args.set, "detections_tiltfit.json"), encoding="utf-8") as f:
            names = sorted(n for n, det in json.load(f).items() if "no_board" not in det)
        if not any(args.view in (n, os.path.basename(n)) for n in names):
            return (f"--view: no photo {args.view!r} with the board in {args.set} ({', '.join(names[:3])}, ... "
                    f"{len(names)} in all)")
    return None


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--set", default="gopro_wide", choices=sorted(PITCH_MM), help="shipped photo set [gopro_wide]")
    p.add_argument("--view", help="photo to composite into [a view with the board large and off-centre]")
    p.add_argument("--spp", type=int, default=8, help="samples per pixel [8; docs/composite.png: 16]")
    p.add_argument("--out", default=os.path.join(HERE, "composite_out"), help="output folder [examples/composite_out]")
    p.add_argument("--picture", help="also write a small copy of the composite here (the docs' picture)")
    args = p.parse_args(argv)
    problem = check_args(args)
    if problem:  # before the calibration: nothing is written
        print(f"composite.py: {problem}", file=sys.stderr)
        return 2

    from renderer import load_scene, read_image, write_image
    from tiltfit.files.calib import write_calib
    from tiltfit.files.calibrated import Calibration
    from tiltfit.report import composite

    t_start = time.perf_counter()
    folder = os.path.abspath(os.path.join(REAL, args.set))
    os.makedirs(args.out, exist_ok=True)
    data, target, cache = calibrate_from_cache(folder, PITCH_MM[args.set])
    calib_path = os.path.abspath(os.path.join(args.out, "calib.json"))
    write_calib(calib_path, data)
    cal = Calibration.read(calib_path)
    try:
        view = cal.view_index(args.view or DEFAULT_VIEW[args.set])
    except ValueError as e:
        print(f"composite.py: --view: {e}", file=sys.stderr)
        return 2
    image_path = cal.views[view]["image"]
    print(f"calibrated {len(cal.views)} views of {args.set} in {time.perf_counter() - t_start:.1f} s: RMS "
          f"{data['rms_reprojection_px']:.3f} px, distortion {data['distortion_model']}, "
          f"blur {'rendered (U, d fitted)' if cal.blur_known else 'not determined: rendered sharp'}")

    # --- the check: the board rendered through the calibrated camera against the photo ----------------------
    t0 = time.perf_counter()
    check = composite.board_alignment(cal, view, photo_corners(cache, image_path), spp=args.spp)
    ok = (check.rms_photo_px <= PHOTO_FACTOR * check.rms_reprojection_px
          and check.rms_projection_px <= PROJECTION_PX)
    print(f"board rendered through view {view} ({os.path.basename(image_path)}), {check.n_corners} corners, "
          f"{time.perf_counter() - t0:.1f} s: against the photo {check.rms_photo_px:.3f} px RMS (calibration's "
          f"{check.rms_reprojection_px:.3f} px), against the calibration's projection {check.rms_projection_px:.3f} "
          f"px: {'ok' if ok else 'FAILED'}")
    with open(os.path.join(args.out, "alignment.json"), "w", encoding="utf-8") as f:
        json.dump({"set": args.set, "view": os.path.basename(image_path), "spp": args.spp,
                   "n_corners": check.n_corners, "rms_rendered_vs_photo_px": check.rms_photo_px,
                   "rms_reprojection_px": check.rms_reprojection_px,
                   "rms_rendered_vs_projected_px": check.rms_projection_px,
                   "thresholds": {"photo_factor": PHOTO_FACTOR, "projection_px": PROJECTION_PX}, "ok": ok}, f, indent=1)
    if not ok:
        return 1

    # --- the composite ----------------------------------------------------------------------------------------
    t0 = time.perf_counter()
    target_path = os.path.join(folder, "target.json")
    full, extent, light = object_scene(calib_path, view, target_path, cal)
    board_only = dict(full, objects=full["objects"][:2])
    mask, _, _ = object_scene(calib_path, view, target_path, cal, objects_only=True, lights=False)
    footprint = np.concatenate([extent, shadow_points(extent, light)])
    window = composite.window_around(cal.project(footprint, view), cal.image_size_px, margin_px=12)
    with_objects, without, alpha = (composite.render_window(load_scene(s), cal, view, window, args.spp)
                                    for s in (full, board_only, mask))
    photo = np.asarray(read_image(image_path), dtype=np.float64)[..., :3]
    x0, y0, w, h = window
    region = photo[y0:y0 + h, x0:x0 + w]
    gain = composite.photo_gain(region, without)
    if np.ptp(region, axis=-1).max() < 1e-6:  # a monochrome camera (industrial_ds1): the objects in grey too
        with_objects = with_objects.mean(-1, keepdims=True).repeat(3, -1)
    photo[y0:y0 + h, x0:x0 + w] = composite.differential_composite(region, with_objects, without, alpha[..., 0], gain)
    out = os.path.join(args.out, "composite.png")
    write_image(out, np.clip(photo, 0, 1).astype(np.float32))
    print(f"composite: window {w}x{h} px at ({x0}, {y0}), 3 renders at {args.spp} spp in "
          f"{time.perf_counter() - t0:.1f} s -> {out}")
    if args.picture:
        import cv2

        small = cv2.resize(np.clip(photo, 0, 1).astype(np.float32), (photo.shape[1] // 2, photo.shape[0] // 2),
                           interpolation=cv2.INTER_AREA)
        write_image(args.picture, small)
        print(f"picture -> {args.picture}")
    print(f"total {time.perf_counter() - t_start:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
