"""(c) Calibration from the detected target photographs: stage 1, stage 2, joint and photometric fits, and
Table 1 and the stage-1 table against the truth."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from ..scenes import Lens
from .config import LENS_STATES, NOT_RUN, RunConfig, SetValues, SimulatedCamera
from .targets import MIN_CORNER_FRACTION


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
    from tiltfit.photometric import PhotometricError, PhotometricOptions, refine_photometric

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
