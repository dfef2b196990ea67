"""(e) The speed–accuracy sweep, the figures (photographs and CG with the lines, profiles) and their data."""
from __future__ import annotations

import os

import numpy as np

from tiltfit.photometric.profiles import compare_profiles, plot_images, plot_profiles, save_figure
from .config import RunConfig, SimulatedCamera, render_boxes, seed_for
from .boxes import StateResult, file_slug


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
            radiance, dt = render_boxes(res.lenses[name], cfg, spp, seed_for(cfg, "sweep", spp))
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
        panel.update({f"CG, {n}": f"images/cg_{file_slug(n)}_{res.state.label}.png" for n in res.cg})
        out["images"]["panels"][res.state.label] = panel
    for line in lines:
        key = {"red": "fig14_red", "green": "fig15_green"}.get(line, f"profiles_{line}")
        out[key] = {"file": files.get(line), "states": {
            res.state.label: {label: p.to_dict() for label, p in res.profiles[line].items()} for res in results}}
    out["speed_accuracy"] = {"file": files.get("speed"), "rows": speed_rows}
    return out
