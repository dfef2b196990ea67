"""(c) The accumulation-buffer camera (Barsky–Pasztor) against distributed ray tracing as the plane of focus tilts
past the last pixel: coverage against θF, rendered and in closed form (`closed_forms.first_row_lost_theta_F`,
`closed_forms.coverage_closed_form`)."""
from __future__ import annotations

import math
import time

import numpy as np
import torch
from renderer import load_scene
from renderer.cameras import image_centre_px, optics
from renderer import render

from .closed_forms import coverage_closed_form, first_row_lost_theta_F
from .common import D_MM, U0_MM, W_MM, StabilityConfig, Study, subplots_row


def coverage_scene(theta_F_deg: float, camera_type: str, cfg: StabilityConfig) -> dict:
    """The boxes scene (`tiltfit.experiments.scenes`) seen through the simulated lens with the plane of focus tilted by θF
    (U held at U0), by the `thin_lens` camera or the accumulation-buffer camera `thin_lens_accumulation`."""
    from ..scenes import Lens, boxes_scene_dict

    d = boxes_scene_dict(Lens(W_MM, U0_MM, D_MM, math.radians(theta_F_deg)), downscale=cfg.coverage_downscale,
                         spp=cfg.coverage_spp)
    d["camera"]["type"] = camera_type
    return d


def bottom_edge_valid(scene, theta_F: float) -> bool:
    """Whether the camera of `scene`, with its plane of focus tilted to θF (radians) instead, has a valid ray at
    the image's bottom edge (pixel y = H − 0.5, the lowest sample position), through the lens centre."""
    cam = scene.camera
    tilted = cam.with_lens(cam.lens.with_(theta_F=theta_F))
    uv = torch.tensor([[image_centre_px(cam.width, cam.height)[0], cam.height - 0.5]], dtype=torch.float64)
    return bool(tilted.generate_rays(uv, torch.full_like(uv, 0.5)).valid.all())


def study_coverage(cfg: StabilityConfig, log) -> Study:
    """(c) Coverage of the accumulation buffer and of distributed ray tracing against θF."""
    t0 = time.perf_counter()
    rows, images, h_mm = _coverage_rows(cfg, log)
    # The threshold: closed form, and where the camera's ray at the bottom edge disappears (bisection).
    theta_star = first_row_lost_theta_F(W_MM, h_mm)
    probe = load_scene(coverage_scene(0.0, "thin_lens_accumulation", cfg))
    theta_meas = _bottom_edge_threshold(probe)
    around = _around_threshold(cfg, theta_star)
    n_px = probe.camera.width * probe.camera.height
    err = max(abs(r["accumulation_coverage"] - r["closed_form_coverage"]) for r in rows)
    ours_min = min(r["ours_coverage"] for r in rows)
    log(f"(c) first row lost at θF = {math.degrees(theta_star):.4f}° (closed form), "
        f"{math.degrees(theta_meas):.4f}° (bisection on the camera's rays)")

    last = max(rows, key=lambda r: r["theta_F_deg"])
    findings = [
        f"The accumulation buffer loses its first pixel row at θF = {math.degrees(theta_star):.3f}° = "
        f"atan(w / (h/2)) "
        f"(w = {W_MM} mm, h = {h_mm:.3f} mm); bisection on the camera's bottom-edge ray gives "
        f"{math.degrees(theta_meas):.4f}°. Rendered 0.25° either side: last-row coverage "
        f"{around['-0.25']['last_row_coverage']:.3f} → {around['+0.25']['last_row_coverage']:.3f}.",
        f"Beyond it the rendered coverage follows the closed form 1/2 + w / (h tan θF) to within {err:.4f} "
        f"(≈ {err * n_px:.0f} of {n_px} pixels, sample noise at {cfg.coverage_spp} spp) and falls to "
        f"{last['accumulation_coverage']:.3f} at θF = {last['theta_F_deg']:g}°.",
        f"Distributed ray tracing (eqs. (5), (6)) renders every pixel at every θF of the sweep: minimum coverage "
        f"{ours_min:.3f}, all images finite: {all(r['ours_finite'] for r in rows)}.",
    ]
    fig = _coverage_figure(rows, images, h_mm, theta_star, last)
    data = {"theta_F_first_row_lost_deg": {"closed_form": math.degrees(theta_star),
                                           "bisection": math.degrees(theta_meas)},
            "around_threshold": around, "sensor_height_mm": h_mm, "w_mm": W_MM, "U_mm": U0_MM,
            "image_px": [probe.camera.width, probe.camera.height], "spp": cfg.coverage_spp,
            "max_coverage_error": err}
    return Study("coverage", "(c) Accumulation buffer against distributed ray tracing as θF grows", rows, findings,
                 data, fig, time.perf_counter() - t0)


def _coverage_rows(cfg: StabilityConfig, log):
    """(one row per θF of the sweep: both cameras' rendered coverage and the closed form; the renders by (camera,
    θF); the sensor height, mm)."""
    rows, images = [], {}
    h_mm = None
    for tf in cfg.coverage_theta_F_deg:
        row = {"theta_F_deg": tf,
               "theta_L_deg": math.degrees(float(optics.theta_L_from_theta_F(math.radians(tf), W_MM, U0_MM)))}
        for cam_type, key in (("thin_lens_accumulation", "accumulation"), ("thin_lens", "ours")):
            scene = load_scene(coverage_scene(tf, cam_type, cfg))
            res = render(scene, spp=cfg.coverage_spp, seed=cfg.seed)
            row[f"{key}_coverage"] = float(res.coverage.mean())
            row[f"{key}_finite"] = bool(torch.isfinite(res.image).all())
            images[(key, tf)] = res
            h_mm = scene.camera.screen.size[1]
        row["closed_form_coverage"] = coverage_closed_form(math.radians(tf), W_MM, h_mm)
        rows.append(row)
        log(f"(c) θF {tf:5.1f}° (θL {row['theta_L_deg']:5.2f}°): accumulation coverage "
            f"{row['accumulation_coverage']:.4f} "
            f"(closed form {row['closed_form_coverage']:.4f}), ours {row['ours_coverage']:.4f}")
    return rows, images, h_mm


def _bottom_edge_threshold(probe) -> float:
    """θF (radians) where the accumulation camera's bottom-edge ray disappears, by 60 bisection steps on
    [60°, 89.9°]."""
    lo, hi = math.radians(60.0), math.radians(89.9)
    if not (bottom_edge_valid(probe, lo) and not bottom_edge_valid(probe, hi)):
        raise RuntimeError("the accumulation camera's bottom-edge ray does not change state between 60° and 89.9°")
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if bottom_edge_valid(probe, mid) else (lo, mid)
    return 0.5 * (lo + hi)


def _around_threshold(cfg: StabilityConfig, theta_star: float) -> dict:
    """The accumulation camera's coverage and last-row coverage rendered 0.25° either side of θF* (radians)."""
    around = {}
    for delta in (-0.25, 0.25):
        tf = math.degrees(theta_star) + delta
        res = render(load_scene(coverage_scene(tf, "thin_lens_accumulation", cfg)), spp=cfg.coverage_spp,
                     seed=cfg.seed)
        around[f"{delta:+.2f}"] = {"theta_F_deg": tf, "coverage": float(res.coverage.mean()),
                                   "last_row_coverage": float(res.coverage[-1].mean())}
    return around


def _coverage_figure(rows: list, images: dict, h_mm: float, theta_star: float, last: dict):
    """Coverage against θF (closed form, both cameras rendered), and both renders at the largest θF."""
    fig, axes = subplots_row(3, width=3.9)
    ax = axes[0]
    x = [r["theta_F_deg"] for r in rows]
    fine = np.linspace(0.0, max(x), 400)
    ax.plot(fine, [coverage_closed_form(math.radians(t), W_MM, h_mm) for t in fine], "-", color="tab:red", lw=1,
            label="closed form 1/2 + w/(h tan θF)")
    ax.plot(x, [r["accumulation_coverage"] for r in rows], "o", color="tab:red", mfc="none",
            label="accumulation buffer, rendered")
    ax.plot(x, [r["ours_coverage"] for r in rows], "s-", color="tab:blue", ms=4, label="distributed ray tracing")
    ax.axvline(math.degrees(theta_star), color="k", ls=":", lw=0.8)
    ax.set_xlabel("θF [deg]")
    ax.set_ylabel("coverage (renderable fraction)")
    ax.set_ylim(-0.02, 1.05)
    ax.legend(fontsize="x-small", loc="lower left")
    ax.grid(alpha=0.3)
    for ax, key in zip(axes[1:], ("accumulation", "ours")):
        res = images[(key, last["theta_F_deg"])]
        img = np.clip(res.image.numpy(), 0, 1) ** (1 / 2.2)
        img = np.where(res.coverage.numpy()[..., None] > 0, img, np.array([1.0, 0.0, 1.0]))
        ax.imshow(img, interpolation="nearest")
        ax.set_title(f"{'accumulation buffer' if key == 'accumulation' else 'ours'}, θF = {last['theta_F_deg']:g}°"
                     + (" (magenta: no ray)" if key == "accumulation" else ""), fontsize="small")
        ax.set_axis_off()
    fig.suptitle("(c) plane of focus tilted past the last finite pixel", fontsize="medium")
    return fig
