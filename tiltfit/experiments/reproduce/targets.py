"""(b) The target photographs: the designed board at each view, rendered through the true lens at each lens
state, exposed by the simulated camera and detected as any photograph."""
from __future__ import annotations

import os
import time

import numpy as np
from renderer.core.transforms import euler_xyz_deg

from tiltfit.photometric.profiles import linear_from_grey_levels
from .config import LENS_STATES, RunConfig, SetValues, SimulatedCamera, save_png, seed_for


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
    from tiltfit.target.design import design_target

    nominal = set_values.nominal
    return design_target(9, 6, 25.0, w_mm=nominal.w, distance_mm=nominal.U, inclination_deg=30.0)

def target_pose(target, rot_x_deg: float, rot_y_deg: float, distance_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """(R, T), X_cam = R X_target + T: the board's design centre on the optical axis at `distance_mm`, the
    board turned by rot_x then rot_y about the camera axes."""
    from tiltfit.target.design import design_centre_mm

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
                                     seed=seed_for(cfg, "target", state.label, v))
            clean = np.repeat(np.asarray(view.clean, dtype=np.float64)[..., None], 3, axis=-1)
            photo = camera.expose(clean, np.random.default_rng(seed_for(cfg, "target noise", state.label, v)))
            name = f"target_{state.label}_{v}.png"
            save_png(os.path.join(out_dir, "images", name), photo)
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
