"""(d) The boxes scene photographed with the true lens at each lens state and re-rendered as CG with each
parameter set; Table 2 and the noise floor."""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field

from tiltfit.photometric.profiles import compare_profiles
from ..scenes import Lens, boxes_scene_dict
from .config import (LENS_STATES, LensState, RunConfig, SimulatedCamera, noise_source, render_boxes, save_png,
                     seed_for)


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
            radiance, dt = render_boxes(true_lens, cfg, cfg.spp_capture, seed_for(cfg, "photo", state.label, k))
            res.captures.append(camera.expose(radiance, noise_source(radiance, seed_for(cfg, "noise", state.label, k))))
            save_png(os.path.join(out_dir, "images", f"photo_{state.label}{'' if k == 0 else '_2'}.png"),
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
                radiance, dt = render_boxes(lens, cfg, cfg.spp_cg, seed_for(cfg, "cg", state.label))
                rendered[lens] = camera.expose_cg(radiance), dt
            cg, dt = rendered[lens]
            res.cg[name], res.lenses[name], res.render_s[name] = cg, lens, dt
            slug = file_slug(name)
            _write_scene(out_dir, f"cg_{slug}_{state.label}", lens, cfg, cfg.spp_cg)
            save_png(os.path.join(out_dir, "images", f"cg_{slug}_{state.label}.png"), cg)
            rows, prof = compare_profiles(res.captures[0], cg, lines, cfg.step_px)
            res.rows.append(_table2_row(state, name, lens, rows, dt))
            for line in lines:
                res.profiles[line][f"CG, {name}"] = prof[line][1]
            errs = ", ".join(f"{r['line']} {r['average_error']:.2f}" for r in rows)
            log(f"(d) {tag}: CG with the {name} values, {cfg.spp_cg} spp, {dt:.1f} s; average error {errs}")
        results.append(res)
    return results

def file_slug(name: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in name).strip("_").replace("__", "_")

def _write_scene(out_dir: str, stem: str, lens: Lens, cfg: RunConfig, spp: int) -> None:
    """The scene file of a render, so `renderer render` can redo it."""
    path = os.path.join(out_dir, "scenes", f"{stem}.json")
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w", encoding="utf-8") as f:
        json.dump(boxes_scene_dict(lens, downscale=cfg.downscale, spp=spp, sampler=cfg.sampler), f, indent=1)
