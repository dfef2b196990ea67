"""The tilt-lens paper's experiment end to end on a simulated camera (`tiltfit reproduce [--quick] [-o DIR]`).

Baba, Nakane, Hiura (IPSJ 2017), §4.2: calibrate a Canon EOS 6D with a TS-E 45 mm at f/2.8 from target
images (stage 1 untilted: w, U, d; stage 2 tilted: θL), photograph boxes on a floor at θL = 0, +5°, −5°,
re-render them as CG with the calibrated lens and compare brightness profiles along a red and a green
line (Table 1: lens tilt set → estimated; Table 2: mean brightness error per line). Here the "real"
camera is simulated, so every estimate can be checked against the truth:

(a) truth      `SimulatedCamera`: the paper's stage-1 values as the true lens (w = 55.39, U = 618.4,
               d = 18.81 mm), a tilt scale that is slightly off (the set ±5° are not the true tilts), the
               lens tilting about its centre so the focus distance moves with the tilt (hinge rule), and
               what a real camera adds to an image: vignetting, shot and read noise, 8-bit sRGB. The truth
               renders the photographs only; the calibration sees nothing but those images.
(b) targets    target photographs (the paper's Fig. 4 kind of board) at θL = 0, +5°, −5°, rendered by
               tiltfit.experiments.synth through the true lens and exposed by the simulated camera; corners and blur
               widths read back by tiltfit.detect.chessboard / tiltfit.detect.blur as from any photograph.
(c) calibrate  stage 1 (unified, eq. 3) + stage 2 (tilt, eq. 4, the paper) + joint (tiltfit.calibrate.fit), from the
               detections only, started from the set values; Table 1 and the stage-1 table.
(d) boxes      the boxes scene photographed with the true lens at the three lens states, re-rendered as
               CG with (i) the set values and (ii) the calibrated values; profiles along the red and the
               green line; Table 2 (mean brightness error per line, lens state and parameter set) and the
               noise floor (two independent photographs of the same scene compared).
(e) plots      photographs and CG side by side with the lines (Figs. 11–13), profiles real vs CG (Figs. 14,
               15), speed–accuracy (CG samples per pixel against error and render time).
(f) outputs    Markdown and CSV tables, PNG plots and images, the scene files of every render, a JSON with
               the data of every figure and a run record, all in DIR; the two tables on stdout, progress
               on stderr.

`RunConfig.calibrate` False skips stages (b) and (c) (a look at the set values alone): Table 1 then marks
the estimates "not run" and Table 2 has no calibrated rows. A fit that fails is reported, not papered over.
Nothing is filled in by hand: every number in the outputs is computed by the run.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
import zlib
from dataclasses import asdict, dataclass, field, replace

import numpy as np
import torch
from renderer import write_image
from renderer import render
from renderer.core.transforms import euler_xyz_deg
from renderer.cameras.sensor import SensorResponse

from tiltfit.photometric.profiles import (compare_profiles, linear_from_grey_levels, plot_images, plot_profiles,
                       save_figure, write_csv, write_markdown, markdown_table)
from .scenes import Lens, Sensor, boxes_scene, boxes_scene_dict, profile_lines
from tiltfit.experiments.runlog import RunLog

NOT_RUN = "not run"  # a table cell of a stage that was skipped (RunConfig.calibrate False) or failed


# ------------------------------------------------------------------------------------------ configuration

@dataclass(frozen=True)
class LensState:
    """One of the paper's three lens states (Fig. 10): a label and the tilt set on the lens scale."""

    label: str
    theta_L_set_deg: float


LENS_STATES = (LensState("a", 0.0), LensState("b", 5.0), LensState("c", -5.0))


@dataclass(frozen=True)
class RunConfig:
    """How much work a run does.

    Attributes:
        downscale: pixel binning of the boxes images (16: 342 x 228; 32: 171 x 114).
        spp_capture: samples per pixel of the simulated photographs.
        spp_cg: samples per pixel of the CG re-renders.
        spp_sweep: CG samples per pixel of the speed–accuracy sweep.
        step_px: spacing of the profile samples along the lines, pixels.
        seed: base seed of every render and noise draw.
        sampler: the renderer's sample pattern.
        target_downscale: pixel binning of the target photographs (detection wants more pixels; 8: 684 x 456,
            1: the paper's 5472 x 3648).
        target_views: target views per lens state (the first of TARGET_VIEWS).
        target_method: how `tiltfit.experiments.synth` renders the target (`analytic` or `renderer`).
        photometric_pixels, photometric_lens_samples: pixels per view and fixed lens samples of the
            photometric refinement (0 pixels: skip it).
        device: torch device of the boxes renders (`cpu` or `cuda`); the fits run on the CPU.
        calibrate: False skips the target photographs and the calibration, stages (b) and (c).
    """

    downscale: int = 16
    spp_capture: int = 64
    spp_cg: int = 32
    spp_sweep: tuple[int, ...] = (1, 2, 4, 8, 16, 32, 64)
    step_px: float = 0.5
    seed: int = 2016
    sampler: str = "sobol"
    target_downscale: int = 8
    target_views: int = 5
    target_method: str = "renderer"
    photometric_pixels: int = 2000
    photometric_lens_samples: int = 64
    device: str = "cpu"
    calibrate: bool = True

    @staticmethod
    def full() -> "RunConfig":
        return RunConfig()

    @staticmethod
    def quick() -> "RunConfig":
        """About a minute on two cores: small images, few samples."""
        # The target photographs keep the full run's size and views: Table 1 is the experiment's result and
        # its test holds the joint fit to 0.05°, which 3 views at 1/16 do not reach (0.1° at −5°). They come
        # from the noise-free analytic model: ray traced at 16 spp their Monte Carlo noise put the photometric
        # θL 0.12° off.
        return RunConfig(downscale=32, spp_capture=16, spp_cg=16, spp_sweep=(1, 4, 16), target_downscale=8,
                         target_views=5, target_method="analytic", photometric_pixels=800,
                         photometric_lens_samples=32)


# ------------------------------------------------------------------------------------- (a) the truth

@dataclass(frozen=True)
class SimulatedCamera:
    """The simulated camera: its true lens and what its sensor does to an image. Never shown to the fit.

    Attributes:
        untilted: the true lens untilted, with its sensor (`renderer.Lens.paper()`: the paper's stage-1 values
            on an EOS 6D).
        tilt_gain, tilt_offset_deg: the true tilt for a set tilt θs ≠ 0 is gain · θs + offset (a tilt scale
            that is slightly off); the 0 detent is exact.
        full_well: photo-electrons at linear value 1 per output pixel (shot noise, Poisson as Gaussian).
        read_noise: standard deviation of the read noise, linear units.
        vignetting: fall-off 1 − v r² with r the distance from the image centre, 1 at the corners.
    """

    untilted: Lens = Lens.paper()
    tilt_gain: float = 0.98
    tilt_offset_deg: float = -0.25
    full_well: float = 4000.0
    read_noise: float = 0.002
    vignetting: float = 0.05

    @property
    def sensor(self) -> Sensor:
        return self.untilted.sensor

    @property
    def f_mm(self) -> float:
        """Focal length of the true thin lens (1/f = 1/w + 1/U0)."""
        return self.untilted.f

    def theta_L_deg(self, theta_L_set_deg: float) -> float:
        """The true lens tilt for a tilt set on the lens scale, degrees."""
        if theta_L_set_deg == 0:
            return 0.0
        return self.tilt_gain * theta_L_set_deg + self.tilt_offset_deg

    def lens(self, theta_L_set_deg: float) -> Lens:
        """The true lens state: the lens (focal length f, sensor at w) tilted about its centre, so the
        focus distance follows the hinge rule U = f w / (w cos θL − f) (`Lens.from_tilt`)."""
        lens = self.untilted
        return Lens.from_tilt(lens.w, self.f_mm, math.radians(self.theta_L_deg(theta_L_set_deg)), lens.d,
                              sensor=lens.sensor)

    @property
    def response(self) -> SensorResponse:
        """The sensor's response (`renderer.cameras.sensor`): vignetting, shot and read noise, 8-bit sRGB."""
        return SensorResponse(vignetting=self.vignetting, read_noise=self.read_noise, full_well=self.full_well,
                              encoding="srgb8")

    def expose(self, radiance, rng) -> np.ndarray:
        """What the camera writes for a linear image: vignetting, shot + read noise, 8-bit sRGB.

        Args:
            radiance: (H, W, 3) linear float image as rendered (numpy, or a tensor exposed on its device).
            rng: the noise source (np.random.Generator; a torch.Generator on the device for a tensor).
        Returns:
            (H, W, 3) uint8 sRGB image.
        """
        return self.response.expose(radiance, rng)

    def expose_cg(self, radiance) -> np.ndarray:
        """A CG render written as the camera writes its photos, noise excepted: (H, W, 3) uint8 sRGB. The CG
        carries the lens's vignetting too: a user compositing CG into the photo flat-fields both alike."""
        return replace(self.response, read_noise=0.0, full_well=None).expose(radiance)


@dataclass(frozen=True)
class SetValues:
    """What the photographer knows without calibrating the blur.

    Attributes:
        nominal: w from a geometry-only calibration, rounded (55 mm); U read off the focus scale (600 mm); d the
            nominal aperture, focal length / f-number = 45 mm / 2.8 (16.07 mm).
    The tilt is the one set on the tilt scale, and U is taken to stay put when the lens is tilted.
    """

    nominal: Lens = Lens(55.0, 600.0, 45.0 / 2.8)

    def lens(self, theta_L_set_deg: float) -> Lens:
        n = self.nominal
        return Lens.from_theta_L(n.w, n.U, n.d, math.radians(theta_L_set_deg))


# ------------------------------------------------------------------------------------------ plumbing

def _Log(enabled: bool = True) -> RunLog:
    return RunLog("reproduce", enabled)


def render_boxes(lens: Lens, cfg: RunConfig, spp: int, seed: int):
    """Render the boxes scene through `lens`; returns the (H, W, 3) linear image and the render time, s.

    The image is a numpy array from a CPU render, and a tensor left on the device from a GPU render: the
    camera exposes it there (`SimulatedCamera.expose`): numpy takes 3 s a 5472 x 3648 photo on these cores
    (benchmarks/results/batch_io.md), as long as a 32-spp GPU render of it.
    """
    scene = boxes_scene(lens, downscale=cfg.downscale, spp=spp, sampler=cfg.sampler)
    t = time.perf_counter()
    image = render(scene, spp=spp, seed=seed, device=cfg.device).image
    if image.device.type == "cpu":
        image = image.numpy()
    else:
        torch.cuda.synchronize(image.device)  # the render's time, not its launch
    return image, time.perf_counter() - t


def _noise_source(radiance, seed: int):
    """The sensor-noise generator for an image: numpy's for a numpy image, torch's on the image's device for
    a tensor (another draw for the same seed)."""
    if isinstance(radiance, torch.Tensor):
        return torch.Generator(radiance.device).manual_seed(seed)
    return np.random.default_rng(seed)


def _save_png(path: str, image_u8: np.ndarray) -> None:
    """Write an 8-bit sRGB image exactly (`renderer.write_image` stores uint8 levels unchanged)."""
    write_image(path, np.asarray(image_u8, dtype=np.uint8), encoding="srgb")


def _seed(cfg: RunConfig, *keys) -> int:
    """A distinct, reproducible seed per render and noise draw (CRC-32 of the keys, not Python's hash)."""
    return zlib.crc32(repr((cfg.seed,) + keys).encode()) & 0x7FFFFFFF


# ------------------------------------------------------------------------------------ (b) target photos

#: Target views (the same for every lens state: camera and board stay put while the lens is tilted):
#: rotation of the board about the camera x and y axes (degrees) and the distance of its design centre
#: along the optical axis (mm). Inclined boards in front of and behind U give blur that varies across each
#: view, which is what separates U from d in stage 1 and measures θF in stage 2.
TARGET_VIEWS = ((40.0, 0.0, 560.0), (-25.0, 0.0, 480.0), (45.0, 0.0, 700.0), (-40.0, 0.0, 680.0),
                (20.0, 5.0, 540.0))

#: A view is used when at least this fraction of the board's corners was found: a partial grid is where a
#: wrong placement on the board is likeliest, and a real calibration would drop it too.
MIN_CORNER_FRACTION = 0.75


def calibration_target(set_values: SetValues):
    """The paper's kind of target (Fig. 4): a checkerboard whose row spacing makes the rows project evenly for
    an inclined view, designed with the set values (the designer does not know the true lens)."""
    from tiltfit.target.layout import design_target

    nominal = set_values.nominal
    return design_target(9, 6, 25.0, w_mm=nominal.w, distance_mm=nominal.U, inclination_deg=30.0)


def target_pose(target, rot_x_deg: float, rot_y_deg: float, distance_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """(R, T), X_cam = R X_target + T: the board's design centre on the optical axis at `distance_mm`, the
    board turned by rot_x then rot_y about the camera axes."""
    from tiltfit.target.layout import design_centre_mm

    R = euler_xyz_deg((rot_x_deg, rot_y_deg, 0.0)).numpy()  # Ry · Rx
    xc, yc = design_centre_mm(target)
    return R, np.array([0.0, 0.0, distance_mm]) - R @ np.array([xc, yc, 0.0])


def stage_targets(camera: SimulatedCamera, set_values: SetValues, cfg: RunConfig, out_dir: str, log) -> dict | None:
    """(b) Photograph the target at every lens state with the true lens, then detect corners and blur.

    The images come from `tiltfit.experiments.synth.render_view` seen through the true lens state (w, U from the hinge
    rule, d, θF from the exact Scheimpflug rule): by default (`cfg.target_method` `renderer`) ray traced by
    the renderer's thin lens at `cfg.spp_capture` samples, the same camera as the boxes photographs, so every
    fit is judged against the thin lens itself. (The `analytic` disc-gather model is exact for its disc but
    takes the blur diameter from paper (4) at the board point, a few percent off the thin lens's under a
    tilt: it biased the photometric θL by up to 5σ.) Then `camera.expose` adds vignetting, noise and 8-bit
    sRGB; `tiltfit.detect.chessboard.detect` reads them back like any photograph.
    Returns:
        {"target", "image_size_px", "pixel_pitch_mm", "detections": {state: [Detection]}, "files"}, or None
        when `cfg.calibrate` is False.
    """
    if not cfg.calibrate:
        log("(b) target photographs: skipped (calibrate off)")
        return None
    from tiltfit.experiments import synth
    from tiltfit.detect.chessboard import detect

    target = calibration_target(set_values)
    k = cfg.target_downscale
    sensor = camera.sensor.binned(k)
    out = {"target": target, "image_size_px": sensor.size_px, "pixel_pitch_mm": sensor.pixel_pitch, "detections": {},
           "files": {}, "linear": {}}
    target.save(os.path.join(out_dir, "target.json"))
    for state in LENS_STATES:
        synth_cam = camera.lens(state.theta_L_set_deg).with_(sensor=sensor)
        dets, files = [], []
        for v, (ax, ay, dist) in enumerate(TARGET_VIEWS[:cfg.target_views]):
            R, T = target_pose(target, ax, ay, dist)
            t0 = time.perf_counter()
            view = synth.render_view(target, synth_cam, R, T, method=cfg.target_method, spp=cfg.spp_capture,
                                     seed=_seed(cfg, "target", state.label, v))
            clean = np.repeat(np.asarray(view.clean, dtype=np.float64)[..., None], 3, axis=-1)
            photo = camera.expose(clean, np.random.default_rng(_seed(cfg, "target noise", state.label, v)))
            name = f"target_{state.label}_{v}.png"
            _save_png(os.path.join(out_dir, "images", name), photo)
            t1 = time.perf_counter()
            linear = linear_from_grey_levels(photo)
            det = detect(linear, target)
            dets.append(det)
            files.append(f"images/{name}")
            out["linear"][f"images/{name}"] = linear.mean(-1)
            log(f"(b) ({state.label}) θL set {state.theta_L_set_deg:+g}°: target view {v + 1}/{cfg.target_views}, "
                f"{sensor.width_px}x{sensor.height_px}, rendered {t1 - t0:.1f} s, detected {int(det.found.sum())}/{target.n_points} "
                f"corners in {time.perf_counter() - t1:.1f} s{'' if det.grid_found else ': ' + det.message}")
        out["detections"][state.label] = dets
        out["files"][state.label] = files
    return out


# ----------------------------------------------------------------------------------------- (c) calibrate

def observations(targets: dict, label: str):
    """`tiltfit.calibrate.model.Observations` of one lens state's target photographs; views where the board was not found,
    or less than MIN_CORNER_FRACTION of it, are left out. None when no view is left."""
    from tiltfit.calibrate.model import Observations

    target = targets["target"]
    dets = [(d, f) for d, f in zip(targets["detections"][label], targets["files"][label])
            if d.grid_found and d.found.sum() >= MIN_CORNER_FRACTION * target.n_points]
    if not dets:
        return None
    return Observations(target.feature_points(), np.stack([d.corners_px for d, _ in dets]),
                        np.stack([d.blur_px for d, _ in dets]), targets["image_size_px"],
                        targets["pixel_pitch_mm"], [f for _, f in dets])


def _photometric(targets: dict, result, cfg: RunConfig, log, label: str) -> dict | None:
    """Photometric refinement (`tiltfit.photometric`) of a corner-and-blur fit on the same photographs."""
    if not cfg.photometric_pixels:
        return None
    from ..photometric import PhotometricError, PhotometricOptions, refine_photometric

    images = [targets["linear"][view["image"]] for view in result.views]
    try:
        res = refine_photometric(images, targets["target"], result.camera,
                                 PhotometricOptions(lens_samples=cfg.photometric_lens_samples,
                                                    max_pixels=cfg.photometric_pixels))
    except PhotometricError as e:
        log(f"(c) ({label}) photometric refinement failed: {e}")
        return None
    rec = {k: res.values[k] for k in ("w_mm", "U_mm", "d_mm", "theta_F_deg", "theta_L_deg", "vignetting")}
    rec.update(sigma=dict(res.sigma), rms_linear=res.rms, iterations=res.iterations, runtime_s=res.runtime_s,
               kept=res.kept, held_out=res.held_out)
    log(f"(c) ({label}) photometric: θL {rec['theta_L_deg']:+.3f} ± {res.sigma['theta_L_deg']:.3f}°, "
        f"U {rec['U_mm']:.1f}, d {rec['d_mm']:.3f} mm, RMS {res.rms:.4f} ({res.runtime_s:.1f} s)")
    return rec


def _fit_record(result) -> dict:
    """The numbers of a FitResult that the tables and the run record need."""
    rec = {k: result.values[k] for k in ("w_mm", "U_mm", "d_mm", "f_mm", "theta_F_deg", "theta_L_deg",
                                          "theta_L_paper_deg")}
    rec["sigma"] = {k: result.sigma.get(k) for k in ("w_mm", "U_mm", "d_mm", "theta_F_deg", "theta_L_deg")}
    rec["rms_reprojection_px"] = [v["rms_reprojection_px"] for v in result.views]
    rec["rms_blur_px"] = [v["rms_blur_px"] for v in result.views]
    rec["n_views"] = len(result.views)
    rec["runtime_s"] = result.runtime_s
    return rec


def stage_calibrate(targets: dict | None, set_values: SetValues, cfg: RunConfig, log) -> dict:
    """(c) Stage 1 (unified), stage 2 (tilt, the paper) and joint fits from the target photographs only.

    - stage 1: the untilted views, eq. (3): w, U, d and the poses; the fit starts from the set w.
    - stage 2 (the paper): each tilted state's views, eq. (4) (`blur_model="paper"`), w, U, d held at
      stage 1; θF, and θL from the paper's eq. (1) and from the exact relation.
    - joint: each tilted state's views with w, U, d, θF free, started from stage 1 (exact blur model).
    The CG lens for state (a) is stage 1 in both parameter sets.
    Returns:
        {"lenses": {"calibrated (paper)": {label: Lens}, "calibrated (joint)": {...}},
         "records": {"stage1": {...}, label: {...}}, "errors": [...]}; empty when skipped.
    """
    out = {"lenses": {}, "records": {}, "errors": []}
    if targets is None:
        log("(c) calibration: skipped (calibrate off)")
        return out
    from tiltfit.calibrate.fit import FitError, FitOptions

    from tiltfit.calibrate.flow import calibrate

    quiet = FitOptions(model_selection=False, nominal_focal_mm=set_values.nominal.w)
    obs_a = observations(targets, "a")
    try:
        if obs_a is None:
            raise FitError("no target found in the untilted photographs")
        stage1 = calibrate(obs_a, "unified", options=quiet)
    except FitError as e:
        out["errors"].append(f"stage 1: {e}")
        log(f"(c) stage 1 failed: {e}")
        return out
    s1 = _fit_record(stage1)
    out["records"]["stage1"] = s1
    log(f"(c) stage 1 ({s1['n_views']} views): w {s1['w_mm']:.3f}, U {s1['U_mm']:.1f}, d {s1['d_mm']:.3f} mm "
        f"({stage1.runtime_s:.1f} s)")
    lens1 = Lens(s1["w_mm"], s1["U_mm"], s1["d_mm"], math.radians(0.0))
    paper, joint, photometric = {"a": lens1}, {"a": lens1}, {}
    ph = _photometric(targets, stage1, cfg, log, "a")
    if ph is not None:
        out["records"]["stage1"]["photometric"] = ph
        photometric["a"] = Lens(ph["w_mm"], ph["U_mm"], ph["d_mm"], math.radians(ph["theta_F_deg"]))
    for state in LENS_STATES:
        if state.label == "a":
            continue
        obs = observations(targets, state.label)
        rec = {}
        try:
            if obs is None:
                raise FitError(f"no target found in the photographs of state ({state.label})")
            st2 = calibrate(obs, "tilt", init=stage1.camera, init_sigma=stage1.sigma,
                            options=replace(quiet, blur_model="paper"))
            rec["stage2"] = _fit_record(st2)
            paper[state.label] = Lens(s1["w_mm"], s1["U_mm"], s1["d_mm"],
                                      math.radians(rec["stage2"]["theta_F_deg"]))
            jt = calibrate(obs, "joint", init=stage1.camera, options=quiet)
            rec["joint"] = _fit_record(jt)
            j = rec["joint"]
            joint[state.label] = Lens(j["w_mm"], j["U_mm"], j["d_mm"], math.radians(j["theta_F_deg"]))
            ph = _photometric(targets, jt, cfg, log, state.label)
            if ph is not None:
                rec["photometric"] = ph
                photometric[state.label] = Lens(ph["w_mm"], ph["U_mm"], ph["d_mm"],
                                                math.radians(ph["theta_F_deg"]))
            log(f"(c) ({state.label}) stage 2: θF {rec['stage2']['theta_F_deg']:+.3f}°, θL (1) "
                f"{rec['stage2']['theta_L_paper_deg']:+.3f}°, exact {rec['stage2']['theta_L_deg']:+.3f}°; joint: "
                f"θL {j['theta_L_deg']:+.3f}°, U {j['U_mm']:.1f} mm")
        except FitError as e:
            out["errors"].append(f"({state.label}): {e}")
            log(f"(c) ({state.label}) calibration failed: {e}")
        out["records"][state.label] = rec
    if len(paper) == len(LENS_STATES):
        out["lenses"]["calibrated (paper)"] = paper
    if len(joint) == len(LENS_STATES):
        out["lenses"]["calibrated (joint)"] = joint
    if len(photometric) == len(LENS_STATES):
        out["lenses"]["calibrated (photometric)"] = photometric
    return out


def table1_rows(camera: SimulatedCamera, calibration: dict) -> list[dict]:
    """Table 1: lens tilt set → estimated (the paper's), with the simulated truth beside it, degrees.

    Estimates: stage 2 through the paper's eq. (1) and through the exact Scheimpflug relation, and the joint
    fit (exact) and its photometric refinement, each with its one-σ; "not run" when stage (c) did not run, empty
    where it failed.
    """
    records = calibration.get("records", {})
    not_run = not records
    rows = []
    for state in LENS_STATES:
        row = {"state": f"({state.label})", "theta_L_set_deg": state.theta_L_set_deg,
               "theta_L_true_deg": camera.theta_L_deg(state.theta_L_set_deg)}
        rec = records.get(state.label, {})
        if state.label == "a" and "stage1" in records:
            # Stage 1 holds θF = 0 and is the CG lens of state (a) in both parameter sets.
            rec = {"stage2": {"theta_L_paper_deg": 0.0, "theta_L_deg": 0.0, "sigma": {}},
                   "joint": {"theta_L_deg": 0.0, "sigma": {}, "U_mm": records["stage1"]["U_mm"]}}
        st2, jt = rec.get("stage2"), rec.get("joint")
        row["stage2_paper_eq1_deg"] = NOT_RUN if not_run else (st2 or {}).get("theta_L_paper_deg")
        row["stage2_exact_deg"] = NOT_RUN if not_run else (st2 or {}).get("theta_L_deg")
        row["stage2_sigma_deg"] = NOT_RUN if not_run else (st2 or {}).get("sigma", {}).get("theta_L_deg")
        row["joint_deg"] = NOT_RUN if not_run else (jt or {}).get("theta_L_deg")
        row["joint_sigma_deg"] = NOT_RUN if not_run else (jt or {}).get("sigma", {}).get("theta_L_deg")
        row["joint_U_mm"] = NOT_RUN if not_run else (jt or {}).get("U_mm")
        ph = records.get("stage1", {}).get("photometric") if state.label == "a" else rec.get("photometric")
        row["photometric_deg"] = NOT_RUN if not_run else (ph or {}).get("theta_L_deg")
        row["photometric_sigma_deg"] = NOT_RUN if not_run else (ph or {}).get("sigma", {}).get("theta_L_deg")
        row["true_U_mm"] = camera.lens(state.theta_L_set_deg).U
        rows.append(row)
    return rows


def stage1_rows(camera: SimulatedCamera, set_values: SetValues, calibration: dict) -> list[dict]:
    """w, U, d of stage 1 against the truth and the set values (mm)."""
    s1 = calibration.get("records", {}).get("stage1")
    rows = []
    for key in ("w_mm", "U_mm", "d_mm"):
        true = camera.untilted.record()[key]
        rows.append({"parameter": key, "true": true, "set": set_values.nominal.record()[key],
                     "stage1": s1[key] if s1 else NOT_RUN,
                     "stage1_sigma": s1["sigma"][key] if s1 else NOT_RUN,
                     "stage1_error": s1[key] - true if s1 else NOT_RUN})
    return rows


# ---------------------------------------------------------------------------------------- (d) boxes

@dataclass
class StateResult:
    """Everything stage (d) made for one lens state (images uint8 sRGB, profiles per line)."""

    state: LensState
    true_lens: Lens
    captures: list                       # two independent photographs, (H, W, 3) uint8
    cg: dict = field(default_factory=dict)        # param-set name -> (H, W, 3) uint8
    lenses: dict = field(default_factory=dict)    # param-set name -> Lens
    rows: list = field(default_factory=list)      # Table 2 rows
    profiles: dict = field(default_factory=dict)  # line -> {label: Profile}
    render_s: dict = field(default_factory=dict)


NOISE_FLOOR = "noise floor (photo vs photo)"
TRUE_LENS = "true lens"  # CG with the simulation's own lens: what a perfect calibration would score


def _table2_row(state: LensState, name: str, lens: Lens | None, rows: list[dict], render_s=None) -> dict:
    row = {"state": f"({state.label})", "theta_L_set_deg": state.theta_L_set_deg, "parameters": name}
    rec = lens.record() if lens is not None else {}
    row["theta_L_deg"] = rec.get("theta_L_deg")
    row["theta_F_deg"] = rec.get("theta_F_deg")
    row["U_mm"] = rec.get("U_mm")
    for r in rows:
        row[r["line"]] = r["average_error"]
    for r in rows:
        row[f"{r['line']}_rmse"] = r["rmse"]
        row[f"{r['line']}_bias"] = r["bias"]
    row["render_s"] = render_s
    return row


def stage_boxes(camera: SimulatedCamera, param_sets: dict, cfg: RunConfig, lines: dict, out_dir: str,
                log) -> list[StateResult]:
    """(d) Photograph the boxes with the true lens, re-render with each parameter set, compare profiles.

    Args:
        param_sets: {name: {state label: Lens}}, e.g. {"set": ..., "calibrated (joint)": ...}.
        lines: {line name: (K, 2) polyline, pixels}.
    """
    results = []
    for state in LENS_STATES:
        true_lens = camera.lens(state.theta_L_set_deg)
        res = StateResult(state, true_lens, [])
        tag = f"({state.label}) θL set {state.theta_L_set_deg:+g}°"
        for k in range(2):
            radiance, dt = render_boxes(true_lens, cfg, cfg.spp_capture, _seed(cfg, "photo", state.label, k))
            res.captures.append(camera.expose(radiance, _noise_source(radiance, _seed(cfg, "noise", state.label, k))))
            _save_png(os.path.join(out_dir, "images", f"photo_{state.label}{'' if k == 0 else '_2'}.png"),
                      res.captures[-1])
            log(f"(d) {tag}: photograph {k + 1}/2 with the true lens (θL {math.degrees(true_lens.theta_L):+.3f}°, "
                f"U {true_lens.U:.1f} mm), {cfg.spp_capture} spp, {dt:.1f} s")
        _write_scene(out_dir, f"photo_{state.label}", true_lens, cfg, cfg.spp_capture)
        floor_rows, floor_prof = compare_profiles(res.captures[0], res.captures[1], lines, cfg.step_px)
        res.rows.append(_table2_row(state, NOISE_FLOOR, None, floor_rows))
        for line in lines:
            res.profiles[line] = {"photo": floor_prof[line][0], "photo 2": floor_prof[line][1]}
        rendered = {}  # lens -> (image, seconds): parameter sets that agree (state (a)) render once
        for name, lenses in param_sets.items():
            lens = lenses[state.label]
            if lens not in rendered:
                # One seed per state for every CG (common random numbers): the rows differ by the lens only.
                radiance, dt = render_boxes(lens, cfg, cfg.spp_cg, _seed(cfg, "cg", state.label))
                rendered[lens] = camera.expose_cg(radiance), dt
            cg, dt = rendered[lens]
            res.cg[name], res.lenses[name], res.render_s[name] = cg, lens, dt
            slug = _slug(name)
            _write_scene(out_dir, f"cg_{slug}_{state.label}", lens, cfg, cfg.spp_cg)
            _save_png(os.path.join(out_dir, "images", f"cg_{slug}_{state.label}.png"), cg)
            rows, prof = compare_profiles(res.captures[0], cg, lines, cfg.step_px)
            res.rows.append(_table2_row(state, name, lens, rows, dt))
            for line in lines:
                res.profiles[line][f"CG, {name}"] = prof[line][1]
            errs = ", ".join(f"{r['line']} {r['average_error']:.2f}" for r in rows)
            log(f"(d) {tag}: CG with the {name} values, {cfg.spp_cg} spp, {dt:.1f} s; average error {errs}")
        results.append(res)
    return results


def _slug(name: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in name).strip("_").replace("__", "_")


def _write_scene(out_dir: str, stem: str, lens: Lens, cfg: RunConfig, spp: int) -> None:
    """The scene file of a render, so `renderer render` can redo it."""
    path = os.path.join(out_dir, "scenes", f"{stem}.json")
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w", encoding="utf-8") as f:
        json.dump(boxes_scene_dict(lens, downscale=cfg.downscale, spp=spp, sampler=cfg.sampler), f, indent=1)


# ------------------------------------------------------------------------------------- (e) plots, sweep

SPEED_METHODS = (("calibrated (joint)", "corners + blur"), ("calibrated (photometric)", "photometric"),
                 ("set", "set values"))


def stage_speed(results: list[StateResult], cfg: RunConfig, lines: dict, log, calib_seconds=None,
                camera: SimulatedCamera | None = None) -> list[dict]:
    """Speed–accuracy: CG of lens state (b) at each `spp_sweep` against its photograph, per calibration method.

    Each row is one (method, spp): the mean Table-2 error of the CG and the time it took to get it, the
    calibration's own time (`calib_seconds[name]`) plus the render. Methods: the corner-and-blur joint fit,
    its photometric refinement (where they ran) and the set values (no calibration).
    """
    res = next(r for r in results if r.state.label == "b")
    calib_seconds = calib_seconds or {}
    rows = []
    for name, method in SPEED_METHODS:
        if name not in res.lenses:
            continue
        for spp in cfg.spp_sweep:
            radiance, dt = render_boxes(res.lenses[name], cfg, spp, _seed(cfg, "sweep", spp))
            cg = (camera or SimulatedCamera()).expose_cg(radiance)
            r, _ = compare_profiles(res.captures[0], cg, lines, cfg.step_px)
            calib_s = float(calib_seconds.get(name, 0.0))
            row = {"method": method, "parameters": name, "spp": spp, "render_s": dt, "calibration_s": calib_s,
                   "total_s": calib_s + dt}
            row.update({x["line"]: x["average_error"] for x in r})
            row["mean"] = float(np.mean([x["average_error"] for x in r]))
            rows.append(row)
            log(f"(e) speed–accuracy: {method}, {spp} spp, {calib_s + dt:.2f} s, mean average error {row['mean']:.2f}")
    return rows


def plot_all(results: list[StateResult], speed_rows: list[dict], lines: dict, out_dir: str) -> dict:
    """Figures 11–15 and the speed–accuracy plot as PNGs; returns {figure: file}."""
    from matplotlib.figure import Figure

    files = {}
    images = {}
    for res in results:
        s = res.state
        images[f"({s.label}) photo, θL set {s.theta_L_set_deg:+g}°"] = res.captures[0]
        for name, img in res.cg.items():
            tl = res.lenses[name].record()["theta_L_deg"]
            images[f"({s.label}) CG, {name}: θL {tl:+.2f}°"] = img
    fig = plot_images(images, lines, ncols=1 + len(results[0].cg))
    files["images"] = "fig11_12_photos_and_cg.png"
    save_figure(fig, os.path.join(out_dir, files["images"]))

    for line, fig_no in (("red", 14), ("green", 15)):
        if line not in lines:
            continue
        fig = Figure(figsize=(7.0, 2.6 * len(results)), layout="constrained")
        axes = fig.subplots(len(results), 1, squeeze=False)[:, 0]
        for ax, res in zip(axes, results):
            profs = {k: v for k, v in res.profiles[line].items() if k != "photo 2"}
            plot_profiles(profs, title=f"({res.state.label}) θL set {res.state.theta_L_set_deg:+g}°", ax=ax)
        fig.suptitle(f"Brightness along the {line} line (cf. the paper's Fig. {fig_no})")
        files[line] = f"fig{fig_no}_{line}_profiles.png"
        save_figure(fig, os.path.join(out_dir, files[line]))

    if speed_rows:
        fig = Figure(figsize=(6.5, 4.0), layout="constrained")
        ax = fig.subplots()
        for method in dict.fromkeys(r["method"] for r in speed_rows):
            sel = [r for r in speed_rows if r["method"] == method]
            ax.plot([r["total_s"] for r in sel], [r["mean"] for r in sel], "o-", label=method)
            for r in sel:
                ax.annotate(f"{r['spp']}", (r["total_s"], r["mean"]), fontsize="x-small",
                            xytext=(3, 3), textcoords="offset points")
        floor = next(r for r in results if r.state.label == "b").rows[0]
        ax.axhline(float(np.mean([floor[line] for line in lines])), ls=":", color="k", label="noise floor")
        ax.set_xscale("log")
        ax.set_xlabel("time to the CG: calibration + render [s] (labels: CG samples per pixel)")
        ax.set_ylabel("mean average error, red and green lines [grey level]")
        ax.legend(fontsize="small")
        ax.grid(alpha=0.3)
        ax.set_title("Speed and accuracy, lens state (b): one curve per method")
        files["speed"] = "speed_accuracy.png"
        save_figure(fig, os.path.join(out_dir, files["speed"]))
    return files


def figures_json(results: list[StateResult], speed_rows: list[dict], lines: dict, files: dict) -> dict:
    """The data behind every figure (profiles, lines, image files, sweep), for re-plotting elsewhere."""
    out = {"lines_px": {k: np.asarray(v).tolist() for k, v in lines.items()},
           "images": {"file": files.get("images"), "panels": {}}}
    for res in results:
        panel = {"photo": f"images/photo_{res.state.label}.png", "photo_2": f"images/photo_{res.state.label}_2.png"}
        panel.update({f"CG, {n}": f"images/cg_{_slug(n)}_{res.state.label}.png" for n in res.cg})
        out["images"]["panels"][res.state.label] = panel
    for line in lines:
        key = {"red": "fig14_red", "green": "fig15_green"}.get(line, f"profiles_{line}")
        out[key] = {"file": files.get(line), "states": {
            res.state.label: {label: p.to_dict() for label, p in res.profiles[line].items()} for res in results}}
    out["speed_accuracy"] = {"file": files.get("speed"), "rows": speed_rows}
    return out


# ------------------------------------------------------------------------------------------ (f) run

TABLE2_COLUMNS = ["state", "theta_L_set_deg", "parameters", "theta_L_deg", "red", "green"]


@dataclass
class ReproduceResult:
    """What `run` returns: the tables as rows, the files written and the stages skipped."""

    table1: list
    table2: list
    speed: list
    files: dict
    skipped: list
    runtime_s: float


def run(out_dir: str, quick: bool = False, progress: bool = True, config: RunConfig | None = None,
        camera: SimulatedCamera | None = None, set_values: SetValues | None = None,
        threads: int | None = 1) -> ReproduceResult:
    """Run the experiment, write every output into `out_dir` and print the two tables.

    Args:
        out_dir: output folder (created).
        quick: small images and few samples (about a minute on two cores) instead of the full run.
        progress: progress lines on stderr.
        config, camera, set_values: override the run size, the simulated truth, the set values.
        threads: torch threads for the run (restored afterwards); None keeps torch's setting [1]. The
            batches here are small: a second thread gains at most 2x, while on a loaded machine torch's
            spinning worker threads made a 171 x 114 render 60x slower (36 s instead of 0.6 s).
    Returns:
        ReproduceResult.
    """
    previous = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(threads)
    try:
        return _run(out_dir, quick, progress, config, camera, set_values)
    finally:
        torch.set_num_threads(previous)


def _run(out_dir, quick, progress, config, camera, set_values) -> ReproduceResult:
    cfg = config or (RunConfig.quick() if quick else RunConfig.full())
    camera = camera or SimulatedCamera()
    set_values = set_values or SetValues()
    log = _Log(progress)
    os.makedirs(out_dir, exist_ok=True)
    torch_threads = torch.get_num_threads()
    width, height = camera.sensor.binned(cfg.downscale).size_px
    lines = profile_lines(width, height)
    target_w, target_h = camera.sensor.binned(cfg.target_downscale).size_px
    true = camera.untilted
    log(f"(a) simulated camera: w {true.w} mm, U {true.U} mm, d {true.d} mm (f "
        f"{camera.f_mm:.2f} mm); boxes images {width}x{height} (1/{cfg.downscale}), target photographs "
        f"{target_w}x{target_h} (1/{cfg.target_downscale}), {torch_threads} threads")

    skipped = [] if cfg.calibrate else ["(b) target photographs", "(c) calibration"]
    targets = stage_targets(camera, set_values, cfg, out_dir, log)    # (b)
    calibration = stage_calibrate(targets, set_values, cfg, log)      # (c)
    table1 = table1_rows(camera, calibration)
    table_s1 = stage1_rows(camera, set_values, calibration)

    param_sets = {"set": {s.label: set_values.lens(s.theta_L_set_deg) for s in LENS_STATES},
                  TRUE_LENS: {s.label: camera.lens(s.theta_L_set_deg) for s in LENS_STATES}}
    param_sets.update(calibration["lenses"])
    results = stage_boxes(camera, param_sets, cfg, lines, out_dir, log)                   # (d)
    table2 = [row for res in results for row in res.rows]
    rec_b = calibration.get("records", {}).get("b", {})
    joint_s = (rec_b.get("joint") or {}).get("runtime_s", 0.0)
    calib_seconds = {"calibrated (joint)": joint_s,
                     "calibrated (photometric)": joint_s + (rec_b.get("photometric") or {}).get("runtime_s", 0.0)}
    speed = stage_speed(results, cfg, lines, log, calib_seconds, camera)         # (e)
    files = plot_all(results, speed, lines, out_dir)

    # (f) tables, figure data, run record, report
    files.update(write_tables(out_dir, table1, table_s1, table2, speed))
    with open(os.path.join(out_dir, "figures.json"), "w", encoding="utf-8") as f:
        json.dump(figures_json(results, speed, lines, files), f)
    files["figures"] = "figures.json"
    runtime = log.elapsed
    record = {
        "config": asdict(cfg), "quick": quick, "runtime_s": runtime, "skipped": skipped,
        "truth": {**asdict(camera), **camera.untilted.record(), "U0_mm": camera.untilted.U, "f_mm": camera.f_mm,
                  "lens_states": {s.label: camera.lens(s.theta_L_set_deg).record() for s in LENS_STATES}},
        "set_values": {s.label: set_values.lens(s.theta_L_set_deg).record() for s in LENS_STATES},
        "calibration": calibration["records"], "calibration_errors": calibration["errors"],
        "target_photographs": targets["files"] if targets else None,
        "image_size_px": [width, height], "target_image_size_px": [target_w, target_h],
    }
    record["truth"]["sensor"] = asdict(camera.sensor)
    with open(os.path.join(out_dir, "run.json"), "w", encoding="utf-8") as f:
        json.dump(record, f, indent=1)
    files["run"] = "run.json"
    files["report"] = write_report(out_dir, table1, table_s1, table2, speed, files, skipped, cfg, runtime)
    print("Stage 1: w, U, d (mm)\n")
    print(markdown_table(table_s1))
    print("Table 1: lens tilt, set -> estimated (degrees)\n")
    print(markdown_table(table1))
    print("Table 2: average brightness error along the lines (0-255 grey levels)\n")
    print(markdown_table(table2, TABLE2_COLUMNS, floatfmt=".3f"))
    if skipped:
        print("Skipped: " + "; ".join(skipped))
    log(f"done: outputs in {out_dir}")
    return ReproduceResult(table1, table2, speed, files, skipped, runtime)


def write_tables(out_dir: str, table1, table_s1, table2, speed) -> dict:
    """Markdown and CSV of Table 1, the stage-1 lens, Table 2 and the speed–accuracy sweep."""
    files = {}
    for stem, rows, cols, title in (
            ("table1", table1, None, "Table 1: lens tilt, set -> estimated (degrees)"),
            ("table_stage1", table_s1, None, "Stage 1: w, U, d (mm)"),
            ("table2", table2, None, "Table 2: average brightness error along the lines (0-255 grey levels)"),
            ("speed_accuracy", speed, None, "Speed and accuracy of the CG (lens state (b))")):
        write_markdown(rows, os.path.join(out_dir, f"{stem}.md"), cols, title)
        write_csv(rows, os.path.join(out_dir, f"{stem}.csv"), cols)
        files[stem] = f"{stem}.md"
    return files


def true_lens_sentence(table2: list[dict]) -> str:
    """What the true-lens rows show against the noise floor, measured (not assumed), as one sentence."""
    by = {(r["state"], r["parameters"]): r for r in table2}
    diffs = [by[(s, TRUE_LENS)][line] - by[(s, NOISE_FLOOR)][line]
             for (s, p) in by if p == TRUE_LENS and (s, NOISE_FLOOR) in by for line in ("red", "green")]
    if not diffs:
        return ""
    above = sum(d > 0 for d in diffs)
    return (f"In this run the true-lens CG lands above the noise floor in {above} of {len(diffs)} line profiles "
            f"(true lens − floor from {min(diffs):+.2f} to {max(diffs):+.2f} grey levels).")


def write_report(out_dir, table1, table_s1, table2, speed, files, skipped, cfg, runtime) -> str:
    """report.md: the tables and the figures in one page."""
    parts = ["# Tilt-lens paper, reproduced on a simulated camera\n",
             f"Run: boxes images 1/{cfg.downscale}, target photographs 1/{cfg.target_downscale}, "
             f"{cfg.spp_capture} spp photographs, {cfg.spp_cg} spp CG, "
             f"{runtime:.0f} s.\n"]
    if skipped:
        parts.append("**Skipped:** " + "; ".join(skipped) + ".\n")
    parts += ["## Stage 1: w, U, d (mm)\n", markdown_table(table_s1),
              "\n## Table 1: lens tilt, set -> estimated (degrees)\n", markdown_table(table1),
              "\n## Table 2: average brightness error (0-255 grey levels)\n",
              "Average error = mean |photo − CG| of the BT.601 luma of the 8-bit sRGB images along the line, "
              "sampled every step_px. The noise floor compares two photographs of the same scene (independent "
              "render samples and sensor noise); the true-lens row is the CG rendered with the simulation's own "
              "lens, what a perfect calibration would score. " + true_lens_sentence(table2) + "\n",
              markdown_table(table2, TABLE2_COLUMNS),
              "\n## Figures\n"]
    for key in ("images", "red", "green", "speed"):
        if key in files:
            parts.append(f"![{key}]({files[key]})\n")
    parts += ["\n## Speed and accuracy\n", markdown_table(speed)]
    with open(os.path.join(out_dir, "report.md"), "w", encoding="utf-8") as f:
        f.write("\n".join(parts))
    return "report.md"


def main(argv=None) -> int:
    """`tiltfit reproduce [--quick] [--scale N] [--target-scale N] [--device cpu|cuda] [-o DIR]` (also
    `python -m tiltfit.experiments.reproduce`)."""
    ap = argparse.ArgumentParser(prog="tiltfit reproduce", description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small images and few samples (about a minute)")
    ap.add_argument("-o", "--output", default="reproduce_out", help="output folder [reproduce_out]")
    ap.add_argument("--threads", type=int, default=1, help="torch threads [1]; 0 keeps torch's default")
    ap.add_argument("--scale", type=int, default=None,
                    help="pixel binning of the boxes images only (the target photographs: --target-scale): "
                         "1 is the paper's 5472x3648 [16; --quick 32]")
    ap.add_argument("--target-scale", type=int, default=None,
                    help="pixel binning of the calibration target photographs: 1 is the paper's 5472x3648 [8]")
    ap.add_argument("--device", default="cpu", help="torch device of the boxes renders: cpu, cuda or cuda:N [cpu]")
    args = ap.parse_args(argv)
    if args.scale is not None and not 1 <= args.scale <= 256:
        ap.error(f"--scale: expected an integer from 1 to 256, got {args.scale}")
    if args.target_scale is not None and not 1 <= args.target_scale <= 256:
        ap.error(f"--target-scale: expected an integer from 1 to 256, got {args.target_scale}")
    from camio.checks import parse_device
    from camio.errors import UsageError

    try:
        parse_device(args.device)
    except UsageError as e:
        ap.error(str(e))
    cfg = RunConfig.quick() if args.quick else RunConfig.full()
    cfg = replace(cfg, device=args.device, **({} if args.scale is None else {"downscale": args.scale}),
                  **({} if args.target_scale is None else {"target_downscale": args.target_scale}))
    t0 = time.perf_counter()
    run(args.output, quick=args.quick, threads=args.threads or None, config=cfg)
    print(f"reproduce: {time.perf_counter() - t0:.1f} s in all (boxes images 1/{cfg.downscale}, targets "
          f"1/{cfg.target_downscale}, {cfg.device})", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
