"""Untilted thin lens: speed against accuracy, ours against Mitsuba 3's `thinlens`, and a cross-check.

The scene (`scene_config`) shows defocus at several depths: checker cards in front of, on and behind the
plane of focus (U = 1000), a checker floor running through it, three diffuse spheres and a checker backdrop,
lit by one point light, diffuse materials only. Both renderers compute the same estimator: direct light from
the point light with one shadow ray per camera sample (ours `max_depth` 0; Mitsuba's `direct` integrator with
emitter_samples=1, bsdf_samples=0), box pixel filter, so the only randomness is the pixel × lens sample.

Measured, in one run (ours and Mitsuba interleaved: for each repeat and each spp, every method in a
rotating order, so busy spells of other jobs on the machine fall on all of them):
- RMSE against a high-spp reference of the same renderer and median wall time over the repeats, for spp
  1, 2, 4, ..., 256, for our samplers (independent, stratified, sobol) and Mitsuba's (independent,
  stratified, multijitter, orthogonal, ldsampler; those that round spp to squares or primes² use the spp
  they accept, recorded as `spp_actual`);
- ours / Mitsuba time at EQUAL RMSE, interpolating each curve in log-log (median wall time, the
  headline; also median CPU time and the fastest repeat's wall time);
- the cross-check: the two references' mean absolute difference as a fraction of the mean intensity;
- the conventions: Mitsuba's rays against ours for the same film position (pixel grid, axes, plane of
  focus, aperture), and an in-focus (d = 0, pinhole) image with and without flips.

RMSE is over all pixels and channels of the linear image. Each reference is the mean of two independent
halves (different seeds), so its own noise is known, MSE_ref = mean((a − b)²) / 4, and is subtracted from
every measured MSE (`rmse`; `rmse_raw` keeps the uncorrected value).

Usage (writes benchmarks/results/thin_lens_speed_accuracy.{json,md,png} and thin_lens_crosscheck.png):
    .venv/bin/python benchmarks/renderer/bench_thin_lens.py            # 320 × 213, spp 1 ... 256, 3 repeats
    .venv/bin/python benchmarks/renderer/bench_thin_lens.py --quick    # smoke run: 64 × 43, spp ≤ 16, under a minute
Timed runs use 2 torch and 2 Dr.Jit threads (`--threads`) and OMP_WAIT_POLICY=PASSIVE for torch unless the
environment sets it (see the comment at the imports).
Mitsuba's LLVM backend needs LLVM ≥ 16 (LLVM 14/15 abort with "Cannot select ... fmaximum"); on Debian 12
`apt-get install libllvm19`, or point DRJIT_LIBLLVM_PATH at one.
"""
from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import platform
import subprocess
import sys
import time

if __name__ == "__main__" and not os.environ.get("THIN_LENS_BENCH_KEEP_OMP"):
    # torch's OpenMP workers spin while they wait for each other. On a machine shared with other jobs a
    # spinning worker holds the core its partner needs, and 2 threads ran 5-20× slower than 1 here (the
    # `thread_probe` numbers in the results); sleeping waits cost nothing measurable on an idle machine.
    # It has to be set before torch loads OpenMP.
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np
import torch

from renderer import render
from renderer.scene.file import load_scene
from renderer.core.transforms import euler_xyz_deg

# Lens and sensor, scene units (mm): 50 mm lens-to-sensor distance, focused at 1 m, f/2.8 aperture,
# a 36 mm wide sensor (39.6° horizontal field of view). Blur diameters: 5 px at z = 600, 0 at 1000,
# 4 px at z = 2500 on the 320-pixel-wide image (half that at 160).
W_MM, U_MM, SENSOR_W_MM = 50.0, 1000.0, 36.0
D_MM = W_MM / 2.8

OUR_SAMPLERS = ("independent", "stratified", "sobol")
MI_SAMPLERS = ("independent", "stratified", "multijitter", "orthogonal", "ldsampler")
# Mitsuba's peer for each of ours (ldsampler: Kollig–Keller scrambled (0, 2)-sequences, the nearest to Sobol).
PEER = {"independent": "independent", "stratified": "stratified", "sobol": "ldsampler"}
# Sample counts each Mitsuba sampler accepts as given (others are rounded up; see `mi_spp_levels`).
_SQUARE_POW2 = (1, 4, 16, 64, 256, 1024)
_PRIME_SQUARES = (4, 9, 25, 49, 121, 169, 289)  # orthogonal (strength 2): 1 is rounded up to 4
_LDSAMPLER = (4, 16, 64, 256, 1024)  # ldsampler rounds 1 up to 4

# Largest Mitsuba wavefront (samples) rendered at once; bigger counts are split into passes with new seeds.
MI_MAX_SAMPLES = 1 << 22


# ------------------------------------------------------------------------------------------------ scene

def scene_config(width: int = 320, height: int = 213, d: float = D_MM) -> dict:
    """The benchmark scene as a scene-file dict (see docs/file_formats.md); camera frame = world frame (y down).

    Args:
        width, height: image size, pixels (square pixels: the sensor height is 36 mm · height / width).
        d: aperture diameter, mm (0: the pinhole with screen distance w).
    """
    checker = lambda size, a, b: {"texture": {"type": "checker", "size": size, "colors": [a, b]}}  # noqa: E731
    return {
        "description": "Untilted thin-lens benchmark: defocus at z = 550 ... 2500 around the plane of focus U = 1000.",
        "image": {"width": width, "height": height, "spp": 1, "max_depth": 0, "sampler": "sobol"},
        "camera": {"type": "thin_lens", "w": W_MM, "U": U_MM, "d": d,
                   "sensor_size": [SENSOR_W_MM, SENSOR_W_MM * height / width]},
        "lights": [{"type": "point", "position": [-600.0, -800.0, 200.0], "intensity": [1.2e7] * 3}],
        "objects": [
            {"name": "backdrop", "shape": {"type": "rectangle", "center": [0, 0, 2500], "size": [2400, 1600]},
             "material": checker(200, [0.8, 0.8, 0.75], [0.15, 0.2, 0.4])},
            {"name": "floor", "shape": {"type": "rectangle", "center": [0, 150, 1500], "size": [1600, 2000],
                                        "rotation_deg": [90, 0, 0]},
             "material": checker(100, [0.7, 0.7, 0.7], [0.2, 0.2, 0.2])},
            {"name": "card_near", "shape": {"type": "rectangle", "center": [-200, -100, 550], "size": [200, 140]},
             "material": checker(20, [0.9, 0.2, 0.1], [0.9, 0.9, 0.9])},
            {"name": "card_focus", "shape": {"type": "rectangle", "center": [200, -140, 1000], "size": [200, 160]},
             "material": checker(20, [0.1, 0.5, 0.9], [0.9, 0.9, 0.9])},
            {"name": "sphere_near", "shape": {"type": "sphere", "center": [-150, 80, 700], "radius": 70},
             "material": {"color": [0.9, 0.6, 0.1]}},
            {"name": "sphere_focus", "shape": {"type": "sphere", "center": [50, 50, 1000], "radius": 100},
             "material": {"color": [0.2, 0.8, 0.3]}},
            {"name": "sphere_far", "shape": {"type": "sphere", "center": [350, 0, 1800], "radius": 150},
             "material": {"color": [0.8, 0.2, 0.6]}},
        ],
    }


# -------------------------------------------------------------------------------------- Mitsuba scene

def _mi():
    import mitsuba as mi

    if mi.variant() is None:
        mi.set_variant("llvm_ad_rgb")
    return mi


def _rgb(c) -> dict:
    return {"type": "rgb", "value": [float(v) for v in c]}


def _mi_shape(shape: dict) -> dict:
    """Mitsuba shape dict for our `rectangle` or `sphere` (the shapes this benchmark uses)."""
    mi = _mi()
    if shape["type"] == "sphere":
        return {"type": "sphere", "center": [float(v) for v in shape["center"]], "radius": float(shape["radius"])}
    if shape["type"] == "rectangle":
        # Mitsuba's rectangle is [−1, 1]² in its local z = 0 plane with uv = (local + 1) / 2; ours is
        # [−sx/2, sx/2] × [−sy/2, sy/2] with x_world = R · x_local + center, R = Rz·Ry·Rx.
        sx, sy = shape["size"]
        m = np.eye(4)
        m[:3, :3] = euler_xyz_deg(shape.get("rotation_deg", (0, 0, 0))).numpy() @ np.diag([sx / 2, sy / 2, 1.0])
        m[:3, 3] = shape["center"]
        return {"type": "rectangle", "to_world": mi.ScalarTransform4f(m.tolist())}
    raise ValueError(f"shape type {shape['type']!r} is not exported by this benchmark")


def _mi_bsdf(material: dict, shape: dict) -> dict:
    """Two-sided diffuse BSDF (our surfaces shade both sides) with the colour or the checker texture."""
    mi = _mi()
    texture = material.get("texture")
    if texture is None:
        reflectance = _rgb(material.get("color", (0.8, 0.8, 0.8)))
    else:
        # Ours: colour index (floor(u / c) + floor(v / c)) mod 2 with u, v in scene units from the corner.
        # Mitsuba: colour 0 where frac(u') > 1/2 equals frac(v') > 1/2, uv' = to_uv · uv, uv ∈ [0, 1]²:
        # so scale uv by size / (2 c).
        if texture["type"] != "checker" or shape["type"] != "rectangle":
            raise ValueError("only checker textures on rectangles are exported by this benchmark")
        sx, sy = shape["size"]
        c = texture["size"]
        reflectance = {"type": "checkerboard", "color0": _rgb(texture["colors"][0]),
                       "color1": _rgb(texture["colors"][1]),
                       "to_uv": mi.ScalarTransform4f().scale([sx / (2 * c), sy / (2 * c), 1.0])}
    return {"type": "twosided", "material": {"type": "diffuse", "reflectance": reflectance}}


def mitsuba_scene(cfg: dict, integrator: str = "direct"):
    """Mitsuba scene (shapes, point lights, integrator) of a scene dict, without a sensor (see `mitsuba_sensor`).

    integrator: `direct` (emitter_samples 1, bsdf_samples 0) or `path` (max_depth 2): both are direct light
    with one shadow ray per camera sample, the estimator of ours at max_depth 0.
    """
    mi = _mi()
    objects = {}
    for o in cfg["objects"]:
        m = o.get("material", {})
        if any(m.get(k, 0) for k in ("specular", "reflect", "transmit")) or m.get("diffuse", 1.0) != 1.0:
            raise ValueError(f"objects.{o['name']}: only plain diffuse materials are exported")
        objects[o["name"]] = {**_mi_shape(o["shape"]), "bsdf": _mi_bsdf(m, o["shape"])}
    for i, light in enumerate(cfg["lights"]):
        if light["type"] != "point":
            raise ValueError(f"lights[{i}]: only point lights are exported")
        objects[f"light_{i}"] = {"type": "point", "position": [float(v) for v in light["position"]],
                                 "intensity": _rgb(light["intensity"])}
    if integrator == "direct":
        integ = {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0}
    elif integrator == "path":
        integ = {"type": "path", "max_depth": 2}
    else:
        raise ValueError(f"integrator: expected direct or path, got {integrator!r}")
    return mi.load_dict({"type": "scene", "integrator": integ, **objects})


def mitsuba_sensor(cfg: dict, sampler: str = "independent", spp: int = 1):
    """Mitsuba sensor matching our camera: `thinlens` (or `perspective` for d = 0), box filter, RGB film.

    Conventions (checked by `check_conventions`): our camera frame is x right, y down, z forward; Mitsuba's
    look_at(origin, target, up) frame has x left, y up, so up = (0, −1, 0) makes the two images agree (image
    x = world +x, image y = world +y). Our sensor of width s at distance w is Mitsuba's horizontal fov
    2 atan(s / 2w) (fov_axis x, square pixels); Mitsuba's `focus_distance` is, like our U, the depth of the
    plane of focus along the axis (not a distance along each ray); aperture_radius = d / 2.
    """
    mi = _mi()
    cam, img = cfg["camera"], cfg["image"]
    assert cam["type"] == "thin_lens" and not cam.get("theta_F_deg") and not cam.get("theta_L_deg"), \
        "only the untilted thin lens has a Mitsuba counterpart"
    sx, sy = cam["sensor_size"]
    assert abs(sy / sx - img["height"] / img["width"]) < 1e-9, "Mitsuba needs square pixels"
    sensor = {"fov": math.degrees(2 * math.atan(sx / (2 * cam["w"]))), "fov_axis": "x",
              "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 0], target=[0, 0, 1], up=[0, -1, 0]),
              "sampler": {"type": sampler, "sample_count": int(spp)},
              "film": {"type": "hdrfilm", "width": img["width"], "height": img["height"],
                       "rfilter": {"type": "box"}, "pixel_format": "rgb"}}
    if cam["d"] > 0:
        sensor.update(type="thinlens", aperture_radius=cam["d"] / 2, focus_distance=cam["U"])
    else:
        sensor.update(type="perspective")
    return mi.load_dict(sensor)


# -------------------------------------------------------------------------------------------- renders

def render_ours(scene, spp: int, sampler: str, seed: int = 0) -> np.ndarray:
    """(H, W, 3) float64 linear image from our renderer (float32 tracing)."""
    return render(scene, spp, sampler, seed=seed).image.double().numpy()


def render_mitsuba(scene, sensor, seed: int = 0) -> np.ndarray:
    """(H, W, 3) float64 linear image from Mitsuba with the sensor's own sampler and sample count."""
    mi = _mi()
    return np.array(mi.render(scene, sensor=sensor, seed=seed), dtype=np.float64)


def mitsuba_high_spp(cfg: dict, scene, spp: int, seed: int, sampler: str = "independent") -> np.ndarray:
    """Mitsuba at high spp, in passes of at most MI_MAX_SAMPLES samples (seeds seed·1000 + pass), averaged."""
    pixels = cfg["image"]["width"] * cfg["image"]["height"]
    per_pass = max(1, min(spp, MI_MAX_SAMPLES // pixels))
    passes = -(-spp // per_pass)
    sensor = mitsuba_sensor(cfg, sampler, per_pass)
    return sum(render_mitsuba(scene, sensor, seed * 1000 + k) for k in range(passes)) / passes


# --------------------------------------------------------------------------------------- conventions

def ray_agreement(width: int = 33, height: int = 21) -> dict:
    """Mitsuba's `thinlens` rays against ours for the same film positions and aperture samples.

    For film positions at the corners, edges and centre of an odd, non-square image and several aperture
    samples, the point where Mitsuba's ray meets the plane z = U must equal our chief ray's (pixel grid, fov,
    axes and plane of focus agree); the lens points are compared as they are and rotated by 180°.
    Returns lengths in mm: focus_point_max_err_mm, lens_point_max_err_mm {identity, rotate_180} and
    lens_map, the better of the two.
    """
    mi = _mi()
    cfg = scene_config(width, height)
    ours = load_scene(cfg).camera
    sensor = mitsuba_sensor(cfg, "independent", 1)
    # Film positions in [0, 1]² (Mitsuba) = pixels x = fx · W − 1/2 (ours: pixel centres at integers).
    fx = np.array([0.0, 1.0, 0.0, 1.0, 0.5, 0.5, 0.25, 0.8])
    fy = np.array([0.0, 0.0, 1.0, 1.0, 0.5, 0.0, 0.75, 0.3])
    uv_px = torch.tensor(np.stack([fx * width - 0.5, fy * height - 0.5], -1), dtype=torch.float64)
    lens = [(0.5, 0.5), (0.9, 0.5), (0.5, 0.9), (0.1, 0.2), (0.7, 0.35)]
    focus_err, lens_err = 0.0, {"identity": 0.0, "rotate_180": 0.0}
    for lu, lv in lens:
        ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(fx, fy), mi.Point2f([lu] * len(fx), [lv] * len(fx)))
        o, d = np.array(ray.o).T.astype(np.float64), np.array(ray.d).T.astype(np.float64)
        p_focus = o + d * ((U_MM - o[:, 2]) / d[:, 2])[:, None]
        r = ours.generate_rays(uv_px, torch.tensor([[lu, lv]] * len(fx), dtype=torch.float64))
        ro, rd = r.origin.numpy(), r.direction.numpy()
        our_focus = ro + rd * ((U_MM - ro[:, 2]) / rd[:, 2])[:, None]
        focus_err = max(focus_err, float(np.abs(p_focus - our_focus).max()))
        # Mitsuba starts rays at the near clip plane: take its lens point where the ray crosses z = 0.
        lens_mi = o - d * (o[:, 2] / d[:, 2])[:, None]
        lens_err["identity"] = max(lens_err["identity"], float(np.abs(lens_mi[:, :2] - ro[:, :2]).max()))
        lens_err["rotate_180"] = max(lens_err["rotate_180"], float(np.abs(lens_mi[:, :2] + ro[:, :2]).max()))
    return {"image_px": [width, height], "focus_point_max_err_mm": focus_err, "lens_point_max_err_mm": lens_err,
            "lens_map": min(lens_err, key=lens_err.get)}


def image_difference(cfg: dict, spp: int, mi_spp: int, seed: int = 5, mitsuba_image=None) -> dict:
    """Mean |ours − Mitsuba| / mean intensity of one scene: ours sobol at spp, Mitsuba independent at mi_spp.

    Also with Mitsuba's image flipped left-right and upside-down: a convention error (a mirrored axis)
    shows as `as_is` far above the noise and a flip far below it. Returns {as_is, flip_x, flip_y}.
    `mitsuba_image`: Mitsuba's (H, W, 3) image of this scene, mi_spp and seed where already rendered.
    """
    a = render_ours(load_scene(cfg), spp, "sobol", seed=seed)
    b = mitsuba_high_spp(cfg, mitsuba_scene(cfg), mi_spp, seed=seed) if mitsuba_image is None else mitsuba_image
    mean = float(b.mean())
    mad = lambda x, y: float(np.abs(x - y).mean() / mean)  # noqa: E731
    return {"as_is": mad(a, b), "flip_x": mad(a, b[:, ::-1]), "flip_y": mad(a, b[::-1])}


def check_conventions(width: int = 33, height: int = 21, spp: int = 1024, mi_spp: int = 8192) -> dict:
    """Do Mitsuba's sensor and ours agree on pixels, axes, plane of focus and aperture?

    `ray_agreement` on an odd, non-square image, then the in-focus (d = 0: our pinhole against Mitsuba's
    `perspective`) image difference, unflipped and flipped (`image_difference`).
    Returns a dict of the numbers (lengths in mm; differences as fractions of the mean intensity).
    """
    out = ray_agreement(width, height)
    out["pinhole_spp"] = {"ours_sobol": spp, "mitsuba_independent": mi_spp}
    out["pinhole_mean_abs_diff_rel"] = image_difference(scene_config(width, height, d=0.0), spp, mi_spp)
    return out


# -------------------------------------------------------------------------------------------- sweeps

def mi_spp_levels(sampler: str, levels: list[int]) -> list[int]:
    """The spp Mitsuba's sampler accepts unrounded, within the range of `levels` (stratified and ldsampler:
    squares of powers of two, ldsampler from 4; orthogonal: squares of primes; the others: `levels`
    themselves, though multijitter still rounds some, e.g. 32 to 35: `spp_actual` records it)."""
    lo, hi = min(levels), max(levels)
    if sampler == "stratified":
        return [n for n in _SQUARE_POW2 if lo <= n <= hi]
    if sampler == "ldsampler":
        return [n for n in _LDSAMPLER if n <= hi]
    if sampler == "orthogonal":
        return [n for n in _PRIME_SQUARES if n <= hi]
    return list(levels)


def _rmse(img: np.ndarray, ref: np.ndarray, mse_ref: float) -> tuple[float, float]:
    """(RMSE with the reference's own noise removed, raw RMSE) of img against ref."""
    mse = float(np.mean((img - ref) ** 2))
    return math.sqrt(max(mse - mse_ref, 1e-3 * mse)), math.sqrt(mse)


def sweep(cfg: dict, refs: dict, levels: list[int], repeats: int, log=print) -> dict:
    """Time and error of every method at every spp, interleaved; medians over the repeats.

    time_s is wall time; cpu_s the process's CPU time over all its threads (less sensitive to other jobs
    on the machine, but it also counts threads that spin while waiting).
    Returns {method: {"renderer", "sampler", "points": [{spp, spp_actual, time_s: [...], cpu_s: [...],
    rmse: [...], rmse_raw: [...], time_s_median, time_s_min, cpu_s_median, rmse_median, rmse_raw_median}]}}.
    """
    ours_scene = load_scene(cfg)
    mscene = mitsuba_scene(cfg)
    methods = [("ours", s) for s in OUR_SAMPLERS] + [("mitsuba", s) for s in MI_SAMPLERS]
    sensors, out = {}, {}
    for renderer, sampler in methods:
        key = f"{renderer}/{sampler}"
        spps = levels if renderer == "ours" else mi_spp_levels(sampler, levels)
        out[key] = {"renderer": renderer, "sampler": sampler, "points": {}}
        for spp in spps:
            point = {"spp": spp, "time_s": [], "cpu_s": [], "rmse": [], "rmse_raw": []}
            if renderer == "mitsuba":
                sensors[key, spp] = mitsuba_sensor(cfg, sampler, spp)
                point["spp_actual"] = int(sensors[key, spp].sampler().sample_count())
                t0 = time.perf_counter()
                render_mitsuba(mscene, sensors[key, spp], seed=999)  # JIT compilation of this kernel
                point["warmup_s"] = time.perf_counter() - t0
            else:
                point["spp_actual"] = spp
            out[key]["points"][spp] = point
    render_ours(ours_scene, 1, "independent", seed=999)  # warm-up (allocator, first-call costs)
    turn = 0
    for rep in range(repeats):
        for spp in sorted({s for m in out.values() for s in m["points"]}):
            todo = [(r, s) for r, s in methods if spp in out[f"{r}/{s}"]["points"]]
            turn += 1
            todo = todo[turn % len(todo):] + todo[:turn % len(todo)]  # rotate who goes first
            for renderer, sampler in todo:
                key = f"{renderer}/{sampler}"
                point = out[key]["points"][spp]
                seed = 100 + rep
                t0, c0 = time.perf_counter(), time.process_time()
                if renderer == "ours":
                    img = render_ours(ours_scene, spp, sampler, seed)
                else:
                    img = render_mitsuba(mscene, sensors[key, spp], seed)
                point["time_s"].append(time.perf_counter() - t0)
                point["cpu_s"].append(time.process_time() - c0)
                rmse, raw = _rmse(img, refs[renderer]["image"], refs[renderer]["mse_noise"])
                point["rmse"].append(rmse)
                point["rmse_raw"].append(raw)
            log(f"  repeat {rep + 1}/{repeats} spp {spp}: " + ", ".join(
                f"{r}/{s} {out[f'{r}/{s}']['points'][spp]['time_s'][-1]:.3f}s" for r, s in todo))
    for m in out.values():
        m["points"] = [m["points"][s] for s in sorted(m["points"])]
        for p in m["points"]:
            for k in ("time_s", "cpu_s", "rmse", "rmse_raw"):
                p[f"{k}_median"] = float(np.median(p[k]))
            p["time_s_min"] = float(np.min(p["time_s"]))
    return out


def references(cfg: dict, ours_spp: int, mi_spp: int, log=print) -> dict:
    """Each renderer's reference: two independent halves (seeds 1001, 1002) averaged.

    Ours: sobol at ours_spp / 2 per half; Mitsuba: independent at mi_spp / 2 per half. Returns per renderer
    the image, mse_noise = mean((a − b)²) / 4 (the reference's own MSE) and the time taken.
    """
    ours_scene, mscene = load_scene(cfg), mitsuba_scene(cfg)
    out = {}
    for name, fn, spp in (
            ("ours", lambda s, n: render_ours(ours_scene, n, "sobol", seed=s), ours_spp),
            ("mitsuba", lambda s, n: mitsuba_high_spp(cfg, mscene, n, seed=s), mi_spp)):
        t0 = time.perf_counter()
        a, b = fn(1001, spp // 2), fn(1002, spp // 2)
        dt = time.perf_counter() - t0
        out[name] = {"image": (a + b) / 2, "mse_noise": float(np.mean((a - b) ** 2)) / 4, "spp": spp,
                     "sampler": "sobol" if name == "ours" else "independent", "time_s": dt}
        log(f"  reference {name}: {spp} spp in {dt:.1f} s, own RMSE {math.sqrt(out[name]['mse_noise']):.2e}")
    return out


def crosscheck(refs: dict) -> dict:
    """Mean absolute (and signed) difference of the two references, as fractions of the mean intensity.

    `expected_from_noise_rel` is what the references' own noise alone gives (mean |N(0, σ²)| = σ·sqrt(2/π),
    σ² the sum of both references' MSE), so a difference near it means no systematic disagreement.
    """
    a, b = refs["ours"]["image"], refs["mitsuba"]["image"]
    mean = float(b.mean())
    diff = a - b
    noise = refs["ours"]["mse_noise"] + refs["mitsuba"]["mse_noise"]
    mse = float(np.mean(diff ** 2))
    return {
        "mean_intensity": mean,
        "mean_abs_diff": float(np.abs(diff).mean()),
        "mean_abs_diff_rel": float(np.abs(diff).mean()) / mean,
        "mean_signed_diff_rel": float(diff.mean()) / mean,
        "expected_from_noise_rel": math.sqrt(noise * 2 / math.pi) / mean,
        "rmse_diff": math.sqrt(mse),
        "rmse_systematic": math.sqrt(max(0.0, mse - noise)),
        "threshold_rel": 0.01,
        "pass": float(np.abs(diff).mean()) / mean < 0.01,
    }


# ------------------------------------------------------------------------------------ equal-error ratio

def _curve(method: dict, time_key: str = "time_s_median") -> tuple[np.ndarray, np.ndarray]:
    """(log RMSE, log time) of a method, cut to the points where RMSE keeps falling (interpolable)."""
    e = np.array([p["rmse_median"] for p in method["points"]])
    t = np.array([p[time_key] for p in method["points"]])
    keep = np.concatenate([[True], e[1:] < np.minimum.accumulate(e)[:-1]])
    return np.log(e[keep]), np.log(t[keep])


def time_at_rmse(method: dict, rmse: np.ndarray, time_key: str = "time_s_median") -> np.ndarray:
    """Time (s) at which the method reaches each RMSE, interpolated in log-log; NaN outside its range."""
    le, lt = _curve(method, time_key)
    x = np.log(np.asarray(rmse, dtype=np.float64))
    out = np.exp(np.interp(x, le[::-1], lt[::-1]))
    return np.where((x >= le.min()) & (x <= le.max()), out, np.nan)


def stalls(curves: dict, factor: float = 0.9) -> list[str]:
    """Methods whose RMSE falls by less than `factor` between consecutive sample counts (2× or more spp
    should give at most 1/sqrt(2) ≈ 0.71 even for plain Monte Carlo): a sampler that stops converging."""
    out = []
    for key, m in curves.items():
        pts = m["points"]
        for p, q in zip(pts, pts[1:]):
            if q["spp_actual"] >= 2 * p["spp_actual"] and q["rmse_median"] > factor * p["rmse_median"]:
                out.append(f"{key}: RMSE {p['rmse_median']:.3e} at {p['spp_actual']} spp, "
                           f"{q['rmse_median']:.3e} at {q['spp_actual']} spp")
    return out


def equal_error_ratios(curves: dict, n_levels: int = 9, time_key: str = "time_s_median") -> dict:
    """ours / Mitsuba time (`time_key`) at equal RMSE, for every pair and against Mitsuba's best sampler.

    For each pair the ratio is evaluated at n_levels RMSE values spaced evenly in log over the range both
    curves cover; reported as the geometric mean, min and max over those levels. `vs_best_mitsuba` uses, at
    each level, the fastest Mitsuba sampler that reaches it.
    """
    ours = [k for k in curves if curves[k]["renderer"] == "ours"]
    theirs = [k for k in curves if curves[k]["renderer"] == "mitsuba"]
    out = {}
    for a in ours:
        ea = np.exp(_curve(curves[a])[0])
        row = {}
        for b in theirs + ["best"]:
            if b == "best":
                lo, hi = ea.min(), ea.max()
            else:
                eb = np.exp(_curve(curves[b])[0])
                lo, hi = max(ea.min(), eb.min()), min(ea.max(), eb.max())
            if not lo < hi:
                row[b] = None
                continue
            levels = np.exp(np.linspace(math.log(lo), math.log(hi), n_levels))
            ta = time_at_rmse(curves[a], levels, time_key)
            if b == "best":
                tb = np.fmin.reduce(np.stack([time_at_rmse(curves[k], levels, time_key) for k in theirs]), 0)
            else:
                tb = time_at_rmse(curves[b], levels, time_key)
            ok = np.isfinite(ta) & np.isfinite(tb)
            if not ok.any():
                row[b] = None
                continue
            r = ta[ok] / tb[ok]
            row[b] = {"geomean": float(np.exp(np.log(r).mean())), "min": float(r.min()), "max": float(r.max()),
                      "rmse_range": [float(levels[ok].min()), float(levels[ok].max())],
                      "levels": [[float(e), float(x)] for e, x in zip(levels[ok], r)]}
        out[a] = row
    return out


# ------------------------------------------------------------------------------------------ threads

def probe_threads(width: int, height: int, spp: int = 16, repeats: int = 3) -> dict:
    """Median wall and CPU time of our sobol render at 1 and 2 torch threads, interleaved, in this process."""
    scene = load_scene(scene_config(width, height))
    render_ours(scene, 1, "sobol")
    runs = {1: [], 2: []}
    for rep in range(repeats):
        for n in (1, 2):
            torch.set_num_threads(n)
            t0, c0 = time.perf_counter(), time.process_time()
            render_ours(scene, spp, "sobol", seed=rep)
            runs[n].append((time.perf_counter() - t0, time.process_time() - c0))
    return {f"{n}_threads": {"wall_s": float(np.median([r[0] for r in v])), "cpu_s": float(np.median([r[1] for r in v]))}
            for n, v in runs.items()}


def thread_probe(width: int, height: int) -> dict:
    """`probe_threads` in child processes with OpenMP's default wait policy (spinning) and with PASSIVE.

    Shows what the wait policy does to ours at 2 threads on this (shared) machine; spp 16, medians of 3.
    """
    out = {}
    for policy in ("default", "PASSIVE"):
        env = dict(os.environ, THIN_LENS_BENCH_KEEP_OMP="1")
        env.pop("OMP_WAIT_POLICY", None)
        if policy == "PASSIVE":
            env["OMP_WAIT_POLICY"] = "PASSIVE"
        cmd = [sys.executable, os.path.abspath(__file__), "--probe-threads", "--width", str(width),
               "--height", str(height)]
        try:
            proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600, check=True)
            out[policy] = json.loads(proc.stdout.strip().splitlines()[-1])
        except (OSError, subprocess.SubprocessError, ValueError, IndexError) as e:
            out[policy] = {"error": f"{type(e).__name__}: {e}"}
    return out


# ------------------------------------------------------------------------------------------ reporting

def machine_info() -> dict:
    cpu = platform.processor()
    try:
        for line in subprocess.run(["lscpu"], capture_output=True, text=True, timeout=5).stdout.splitlines():
            if line.startswith("Model name"):
                cpu = line.split(":", 1)[1].strip()
    except (OSError, subprocess.SubprocessError):
        pass
    import drjit as dr
    import mitsuba as mi

    return {"cpu": cpu, "cpu_count": os.cpu_count(), "platform": platform.platform(),
            "python": platform.python_version(), "torch": torch.__version__, "mitsuba": mi.__version__,
            "drjit": dr.__version__, "mitsuba_variant": mi.variant(),
            "torch_threads": torch.get_num_threads(), "drjit_threads": dr.thread_count(),
            "OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY", "(default)"),
            "date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")}


def _label(key: str, method: dict) -> str:
    return f"{'ours' if method['renderer'] == 'ours' else 'Mitsuba'} {method['sampler']}"


def plot(curves: dict, path: str, title: str) -> None:
    """Log-log RMSE against median wall time (left) and CPU time (right), one curve per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axs = plt.subplots(1, 2, figsize=(12, 5.2), sharey=True)
    colors = {"independent": "C0", "stratified": "C1", "sobol": "C2", "multijitter": "C3",
              "orthogonal": "C4", "ldsampler": "C5"}
    for ax, key_t, xlabel in ((axs[0], "time_s_median", "wall time per image, s (median)"),
                              (axs[1], "cpu_s_median", "CPU time per image over all threads, s (median)")):
        for key, m in curves.items():
            t = [p[key_t] for p in m["points"]]
            e = [p["rmse_median"] for p in m["points"]]
            ours = m["renderer"] == "ours"
            ax.loglog(t, e, "-o" if ours else "--s", color=colors[m["sampler"]], ms=4 if ours else 3,
                      lw=1.8 if ours else 1.2, label=_label(key, m))
            for p, ti, ei in zip(m["points"], t, e):
                if p["spp_actual"] in (1, 16, 256) or p is m["points"][-1]:
                    ax.annotate(str(p["spp_actual"]), (ti, ei), fontsize=6, xytext=(2, 2), textcoords="offset points")
        ax.set_xlabel(xlabel)
        ax.grid(True, which="both", alpha=0.3)
    axs[0].set_ylabel("RMSE against the renderer's own reference (linear radiance)")
    axs[0].legend(fontsize=7, ncol=2)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def plot_crosscheck(refs: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    a, b = refs["ours"]["image"], refs["mitsuba"]["image"]
    srgb = lambda x: np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.clip(x, 0.0031308, None) ** (1 / 2.4) - 0.055)  # noqa: E731
    fig, axs = plt.subplots(1, 3, figsize=(12, 3.2))
    axs[0].imshow(np.clip(srgb(a), 0, 1))
    axs[0].set_title(f"ours, sobol {refs['ours']['spp']} spp", fontsize=8)
    axs[1].imshow(np.clip(srgb(b), 0, 1))
    axs[1].set_title(f"Mitsuba thinlens, independent {refs['mitsuba']['spp']} spp", fontsize=8)
    d = (a - b).mean(-1)
    lim = float(np.percentile(np.abs(d), 99.5)) or 1e-3
    im = axs[2].imshow(d, cmap="RdBu_r", vmin=-lim, vmax=lim)
    axs[2].set_title("ours − Mitsuba (mean of RGB)", fontsize=8)
    fig.colorbar(im, ax=axs[2], fraction=0.03)
    for ax in axs:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _thread_line(probe: dict) -> str:
    parts = []
    for policy, r in probe.items():
        if "error" in r:
            parts.append(f"{policy}: {r['error']}")
        else:
            parts.append(f"{policy} policy {r['1_threads']['wall_s']:.2f} s at 1 thread, "
                         f"{r['2_threads']['wall_s']:.2f} s at 2")
    return "Ours, sobol 16 spp, median wall time: " + "; ".join(parts) + "."


def _fmt(x, digits=3) -> str:
    return "—" if x is None else f"{x:.{digits}g}"


def write_markdown(res: dict, path: str) -> None:
    c, cx, conv, ratios = res["config"], res["crosscheck"], res["conventions"], res["equal_rmse_ratio"]
    mi_names = [f"mitsuba/{s}" for s in MI_SAMPLERS]
    L = [
        "# Thin lens (untilted): ours against Mitsuba 3 `thinlens`",
        "",
        f"Written by `{res['command']}` on {res['machine']['date_utc']}.",
        "",
        f"Machine: {res['machine']['cpu']}, {res['machine']['cpu_count']} cores shared with other jobs "
        f"(load average {res['load_average_start'][0]:.1f} at the start, {res['load_average_end'][0]:.1f} at the end); "
        f"torch {res['machine']['torch']} with {res['machine']['torch_threads']} threads, Mitsuba "
        f"{res['machine']['mitsuba']} `{res['machine']['mitsuba_variant']}` with {res['machine']['drjit_threads']} "
        f"threads. Total run {res['total_s']:.0f} s.",
        "",
        f"OpenMP wait policy for ours: {res['machine']['OMP_WAIT_POLICY']}. " + _thread_line(res["thread_probe"]),
        "",
        f"Scene: {c['width']}×{c['height']} px, w = {c['w_mm']} mm, U = {c['U_mm']} mm, d = {c['d_mm']:.3f} mm, "
        f"sensor {c['sensor_mm'][0]}×{c['sensor_mm'][1]:.3f} mm; direct light from one point light, one shadow "
        f"ray per sample (ours max_depth 0; Mitsuba `{c['mitsuba_integrator']}`), box pixel filter. "
        f"Medians over {c['repeats']} repeats, ours and Mitsuba interleaved in the same run.",
        "",
        "## Ours / Mitsuba time at equal RMSE",
        "",
        "Geometric mean over the RMSE range both curves cover (min–max over that range in brackets); "
        "< 1 means ours is faster. `best` = at each RMSE the fastest Mitsuba sampler. RMSE is the median over "
        "the repeats in every table; only the time differs.",
        "",
    ]
    for title, table in (("median wall time (the headline)", ratios), ("median CPU time", res["equal_rmse_ratio_cpu"]),
                         ("fastest of the repeats, wall time (least disturbed by other jobs)",
                          res["equal_rmse_ratio_min_wall"])):
        L += [f"{title}:", "", "| ours \\ Mitsuba | " + " | ".join(s.split("/")[1] for s in mi_names) + " | best |",
              "|---|" + "---|" * (len(mi_names) + 1)]
        for a, row in table.items():
            cells = []
            for b in mi_names + ["best"]:
                r = row.get(b)
                cells.append("—" if r is None else f"{r['geomean']:.1f} ({r['min']:.1f}–{r['max']:.1f})")
            L.append(f"| {a.split('/')[1]} | " + " | ".join(cells) + " |")
        L.append("")
    ind = res["time_ratio_equal_spp_vs_mitsuba_independent"]["ours/independent"]
    L += ["", "Raw speed at the same spp (ours independent / Mitsuba independent wall time): " + ", ".join(
        f"{k} spp {v:.1f}×" for k, v in ind.items()) + "."]
    L += ["", "Named peers (Mitsuba's counterpart of each of our samplers): " + ", ".join(
        f"{a} ↔ {b}: {_fmt((ratios[f'ours/{a}'].get(f'mitsuba/{b}') or {}).get('geomean'))}×"
        for a, b in PEER.items()) + ".", "",
        "RMSE that stops falling (doubling spp should give ≤ 0.71×; flagged above 0.9×): "
        + ("; ".join(res["rmse_stalls"]) if res["rmse_stalls"] else "none") + ".", "",
        "## Cross-check (references)", "",
        f"Mean |ours − Mitsuba| = {100 * cx['mean_abs_diff_rel']:.3f} % of the mean intensity "
        f"({cx['mean_intensity']:.4f}); threshold 1 % — {'PASS' if cx['pass'] else 'FAIL'}. "
        f"Signed mean difference {100 * cx['mean_signed_diff_rel']:+.3f} %. The references' own noise alone "
        f"would give {100 * cx['expected_from_noise_rel']:.3f} %; RMSE of the difference {cx['rmse_diff']:.2e}, "
        f"of which systematic {cx['rmse_systematic']:.2e}. References: ours sobol {res['references']['ours']['spp']} spp "
        f"(own RMSE {math.sqrt(res['references']['ours']['mse_noise']):.2e}), Mitsuba independent "
        f"{res['references']['mitsuba']['spp']} spp (own RMSE {math.sqrt(res['references']['mitsuba']['mse_noise']):.2e}).",
        "", "## Conventions", "",
        f"- Ray geometry ({conv['image_px'][0]}×{conv['image_px'][1]} px, corner/edge/centre film positions, 5 "
        f"aperture samples): Mitsuba's rays meet the plane z = U within {conv['focus_point_max_err_mm']:.1e} mm of "
        f"our chief rays' focus points. Mitsuba's lens point for the same aperture sample is "
        f"{'ours rotated by 180°' if conv['lens_map'] == 'rotate_180' else 'ours'} (max error {conv['lens_point_max_err_mm'][conv['lens_map']]:.1e} mm): its concentric disc is mapped "
        "into its x-left, y-up camera frame. Same distribution on the disc, different sample-to-point map.",
        f"- In-focus (d = 0) image, ours sobol {conv['pinhole_spp']['ours_sobol']} spp, Mitsuba independent "
        f"{conv['pinhole_spp']['mitsuba_independent']} spp: mean |ours − Mitsuba| "
        f"{100 * conv['pinhole_mean_abs_diff_rel']['as_is']:.3f} % as is, "
        f"{100 * conv['pinhole_mean_abs_diff_rel']['flip_x']:.1f} % with Mitsuba flipped left-right, "
        f"{100 * conv['pinhole_mean_abs_diff_rel']['flip_y']:.1f} % upside-down.",
        "", "## Points (medians)", "",
        "| method | spp | spp used | wall s | wall s (min) | CPU s | RMSE | RMSE raw | Mitsuba JIT warm-up s |",
        "|---|---|---|---|---|---|---|---|---|"]
    for key, m in res["curves"].items():
        for p in m["points"]:
            L.append(f"| {key} | {p['spp']} | {p['spp_actual']} | {p['time_s_median']:.4g} | {p['time_s_min']:.4g} | "
                     f"{p['cpu_s_median']:.4g} | {p['rmse_median']:.3e} | {p['rmse_raw_median']:.3e} | "
                     f"{_fmt(p.get('warmup_s'))} |")
    L += ["", "RMSE: the reference's own noise subtracted in quadrature (see the module docstring); "
          "`RMSE raw` without.", ""]
    with open(path, "w", encoding="utf-8") as f:
        f.write("\n".join(L))


# ----------------------------------------------------------------------------------------------- main

def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=213)
    ap.add_argument("--max-spp", type=int, default=256, help="largest spp of the sweep (powers of two from 1)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--ref-spp", type=int, default=1024, help="our reference, sobol (two halves)")
    ap.add_argument("--mi-ref-spp", type=int, default=8192, help="Mitsuba's reference, independent (two halves)")
    ap.add_argument("--threads", type=int, default=2, help="torch and Dr.Jit threads for everything timed")
    ap.add_argument("--quick", action="store_true", help="smoke run: 64×43, spp ≤ 16, small references")
    ap.add_argument("--out", default=os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "benchmarks", "results"))
    ap.add_argument("--probe-threads", action="store_true", help=argparse.SUPPRESS)  # child of `thread_probe`
    args = ap.parse_args(argv)
    if args.probe_threads:
        print(json.dumps(probe_threads(args.width, args.height)))
        return 0
    if args.quick:
        args.width, args.height, args.max_spp, args.ref_spp, args.mi_ref_spp = 64, 43, 16, 128, 1024
    import drjit as dr

    mi = _mi()
    mi.set_log_level(mi.LogLevel.Error)  # the rounding warnings of stratified/orthogonal/ldsampler are expected
    torch.set_num_threads(args.threads)
    dr.set_thread_count(args.threads)
    t_start, load_start = time.perf_counter(), os.getloadavg()
    log = lambda s: print(s, flush=True)  # noqa: E731
    cfg = scene_config(args.width, args.height)
    levels = [2 ** k for k in range(int(math.log2(args.max_spp)) + 1)]

    log("conventions ...")
    conventions = check_conventions()
    log(f"  {conventions}")
    log("threads ...")
    threads = thread_probe(args.width, args.height)
    log(f"  {threads}")
    log("references ...")
    refs = references(cfg, args.ref_spp, args.mi_ref_spp, log)
    cx = crosscheck(refs)
    log(f"  cross-check: mean |ours − Mitsuba| = {100 * cx['mean_abs_diff_rel']:.3f} % of the mean")
    log("sweep ...")
    curves = sweep(cfg, refs, levels, args.repeats, log)
    ratios = equal_error_ratios(curves)
    ratios_cpu = equal_error_ratios(curves, time_key="cpu_s_median")
    ratios_min = equal_error_ratios(curves, time_key="time_s_min")
    same_spp = {f"ours/{s}": {p["spp"]: p["time_s_median"] / q["time_s_median"]
                              for p in curves[f"ours/{s}"]["points"] for q in curves["mitsuba/independent"]["points"]
                              if p["spp"] == q["spp"]} for s in OUR_SAMPLERS}
    cam = cfg["camera"]
    command = "python benchmarks/renderer/bench_thin_lens.py " + " ".join(argv if argv is not None else sys.argv[1:])
    res = {
        "command": command.strip(),
        "machine": machine_info(),
        "load_average_start": list(load_start), "load_average_end": list(os.getloadavg()),
        "config": {"width": args.width, "height": args.height, "w_mm": cam["w"], "U_mm": cam["U"], "d_mm": cam["d"],
                   "sensor_mm": cam["sensor_size"], "spp_levels": levels, "repeats": args.repeats,
                   "mitsuba_integrator": "direct (emitter_samples=1, bsdf_samples=0)",
                   "ours_options": "max_depth 0, float32, default chunking and culling, no torch.compile"},
        "conventions": conventions,
        "thread_probe": threads,
        "references": {k: {kk: vv for kk, vv in v.items() if kk != "image"} for k, v in refs.items()},
        "crosscheck": cx,
        "curves": curves,
        "equal_rmse_ratio": ratios,
        "rmse_stalls": stalls(curves),
        "equal_rmse_ratio_cpu": ratios_cpu,
        "equal_rmse_ratio_min_wall": ratios_min,
        "time_ratio_equal_spp_vs_mitsuba_independent": same_spp,
        "total_s": time.perf_counter() - t_start,
    }
    os.makedirs(args.out, exist_ok=True)
    stem = os.path.join(args.out, "thin_lens_speed_accuracy" + ("_quick" if args.quick else ""))
    with open(stem + ".json", "w", encoding="utf-8") as f:
        json.dump(res, f, indent=1)
    write_markdown(res, stem + ".md")
    plot(curves, stem + ".png",
         f"Thin lens {args.width}×{args.height}: RMSE vs wall time, {args.threads} threads each "
         f"(medians of {args.repeats}); solid = ours, dashed = Mitsuba 3")
    plot_crosscheck(refs, os.path.join(args.out, "thin_lens_crosscheck" + ("_quick" if args.quick else "") + ".png"))
    log(f"wrote {stem}.{{json,md,png}} in {res['total_s']:.0f} s")
    for a, row in ratios.items():
        log(f"  {a}: ours/Mitsuba at equal RMSE: " + ", ".join(
            f"{b.split('/')[-1]} {r['geomean']:.2f}" for b, r in row.items() if r))
    return 0


if __name__ == "__main__":
    sys.exit(main())
