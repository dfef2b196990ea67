"""`tiltfit report CALIB.json -o DIR`: the plots that tell whether a calibration can be trusted.

    write_report(calib: dict, out_dir) -> list of files written

Reads only CALIB.json (per-view `corners_px`, `residuals_px`, `blur_px`, `blur_residuals_px`, `depth_mm`,
written by `tiltfit calibrate`). Files:
    per_view_rms.png        reprojection RMS of every view, outlier views in red (a bad detection or a moved
                            board shows up here first)
    residual_vectors.png    each view's residual vectors on the image (exaggerated): a pattern that repeats
                            across views (radial, one corner) is model error; random directions are noise
    residual_histogram.png  x and y residuals with the Gaussian of the fitted σ: heavy tails mean outliers
    blur_vs_depth.png       blur residual against depth (a trend means the focus or blur model is off)
    coverage.png            where in the image the corners fell: empty regions (corners) leave the
                            distortion there extrapolated
    projection_uncertainty.png  σ of the projection across the image (CALIB.json's `projection_uncertainty`,
                            `tiltfit.uncertainty`), where the file has it
    report.md               the numbers: RMS, held-out error, per-view table, undetermined and skipped
"""
from __future__ import annotations

import math
import os

import numpy as np


def _views(calib: dict) -> list:
    views = calib.get("views") or []
    if not views or not any("residuals_px" in v for v in views):
        raise ValueError("views[].residuals_px: missing (calibrate with this version of tiltfit to get a report)")
    if not any(r is not None for v in views for r in v.get("residuals_px") or []):
        raise ValueError("views[].residuals_px: no view has a residual to draw")
    return views


def _arr(values, width: int) -> np.ndarray:
    return np.array([[np.nan] * width if v is None else ([v] if width == 1 else v) for v in values],
                    dtype=np.float64).reshape(len(values), width)


def write_report(calib: dict, out_dir: str) -> list:
    """Write the report's PNG plots and report.md into `out_dir`; returns the paths written.

    `calib` is a CALIB dict checked by `tiltfit.calibfile.validate_calib`. The files are written as a set
    (`renderer.io.atomic_folder`): on an error or interrupt none of them reaches `out_dir`.
    """
    from renderer.io import atomic_folder

    views = _views(calib)
    with atomic_folder(out_dir) as staging:
        names = _write_plots(calib, views, staging)
    return [os.path.join(out_dir, name) for name in names]


def _write_plots(calib: dict, views: list, out_dir: str) -> list:
    """The report's files written into `out_dir`; returns their names."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    W, H = calib["image_size_px"]
    names = [os.path.basename(str(v.get("image", f"view{i}"))) for i, v in enumerate(views)]
    C = [_arr(v.get("corners_px", []), 2) for v in views]
    E = [_arr(v.get("residuals_px", []), 2) for v in views]
    files = []

    def save(fig, name):
        path = os.path.join(out_dir, name)
        try:
            fig.savefig(path, dpi=110, bbox_inches="tight")
        finally:
            plt.close(fig)
        files.append(name)

    # Per-view RMS.
    rms = np.array([v.get("rms_reprojection_px") or np.nan for v in views], dtype=np.float64)
    out = np.array([bool(v.get("outlier")) for v in views])
    fig, ax = plt.subplots(figsize=(max(6, 0.25 * len(views) + 2), 3.2))
    ax.bar(range(len(views)), rms, color=np.where(out, "tab:red", "tab:blue"))
    ax.axhline(np.nanmedian(rms), color="k", lw=0.8, ls="--", label="median")
    ax.set_xticks(range(len(views)), names, rotation=90, fontsize=6)
    ax.set_ylabel("RMS per corner (px)")
    ax.set_title("Reprojection RMS per view (red: outlier)")
    ax.legend()
    save(fig, "per_view_rms.png")

    # Residual vectors per view.
    n = len(views)
    cols = int(math.ceil(math.sqrt(n * 4 / 3)))
    rows = int(math.ceil(n / cols))
    allE = np.concatenate([e[np.isfinite(e).all(1)] for e in E]) if n else np.zeros((0, 2))
    typical = float(np.percentile(np.hypot(allE[:, 0], allE[:, 1]), 90)) if len(allE) else 1.0
    scale = 0.05 * max(W, H) / max(typical, 1e-9)
    fig, axes = plt.subplots(rows, cols, figsize=(2.0 * cols, 1.6 * rows), squeeze=False)
    for i, ax in enumerate(axes.ravel()):
        ax.set_xticks([])
        ax.set_yticks([])
        if i >= n:
            ax.axis("off")
            continue
        ok = np.isfinite(C[i]).all(1) & np.isfinite(E[i]).all(1)
        ax.quiver(C[i][ok, 0], C[i][ok, 1], E[i][ok, 0] * scale, E[i][ok, 1] * scale, angles="xy",
                  scale_units="xy", scale=1, width=0.006, color="tab:red" if out[i] else "tab:blue")
        ax.set_xlim(0, W)
        ax.set_ylim(H, 0)
        ax.set_aspect("equal")
        ax.set_title(f"{names[i]} {rms[i]:.2f}px", fontsize=6)
    fig.suptitle(f"Residual vectors (model − detected), ×{scale:.0f}", fontsize=9)
    save(fig, "residual_vectors.png")

    # Histogram.
    fig, ax = plt.subplots(figsize=(6, 3.5))
    if len(allE):
        lim = float(np.percentile(np.abs(allE), 99.5)) * 1.2 + 1e-9
        bins = np.linspace(-lim, lim, 61)
        ax.hist(allE[:, 0], bins, alpha=0.6, label="x", density=True)
        ax.hist(allE[:, 1], bins, alpha=0.6, label="y", density=True)
        s = math.sqrt(float((allE ** 2).mean()))
        g = np.exp(-0.5 * (bins / s) ** 2) / (s * math.sqrt(2 * math.pi))
        ax.plot(bins, g, "k", lw=1, label=f"Gaussian σ = {s:.3f} px")
    ax.set_xlabel("residual (px)")
    ax.set_title("Reprojection residuals")
    ax.legend()
    save(fig, "residual_histogram.png")

    # Blur residual against depth.
    fig, ax = plt.subplots(figsize=(6, 3.5))
    z = np.concatenate([_arr(v.get("depth_mm", []), 1).ravel() for v in views])
    br = np.concatenate([_arr(v.get("blur_residuals_px", [None] * len(v.get("depth_mm", []))), 1).ravel()
                         for v in views])
    ok = np.isfinite(z) & np.isfinite(br)
    if ok.any():
        ax.scatter(z[ok], br[ok], s=3, alpha=0.5)
        ax.axhline(0, color="k", lw=0.8)
        ax.set_ylabel("blur residual, model − measured (px)")
    else:
        ax.text(0.5, 0.5, "no blur widths in this calibration", ha="center", va="center", transform=ax.transAxes)
    ax.set_xlabel("depth z in the camera frame (mm)")
    ax.set_title("Blur residual against depth")
    save(fig, "blur_vs_depth.png")

    # Coverage.
    fig, ax = plt.subplots(figsize=(6, 6 * H / W + 0.6))
    cmap = plt.get_cmap("viridis")
    for i, c in enumerate(C):
        ok = np.isfinite(c).all(1)
        ax.scatter(c[ok, 0], c[ok, 1], s=3, color=cmap(i / max(n - 1, 1)))
    ax.set_xlim(0, W)
    ax.set_ylim(H, 0)
    ax.set_aspect("equal")
    allC = np.concatenate([c[np.isfinite(c).all(1)] for c in C]) if n else np.zeros((0, 2))
    gx = np.clip((allC[:, 0] / W * 8).astype(int), 0, 7)
    gy = np.clip((allC[:, 1] / H * 6).astype(int), 0, 5)
    covered = len(set(zip(gx.tolist(), gy.tolist()))) / 48.0
    ax.set_title(f"Corners of all views (colour = view); {100 * covered:.0f} % of an 8×6 grid of the image covered",
                 fontsize=9)
    save(fig, "coverage.png")

    _projection_uncertainty_plot(calib, save, plt)

    # Text summary.
    lines = ["# Calibration report", ""]
    rms_all = calib.get("rms_reprojection_px")
    ho = calib.get("held_out") or {}
    lines.append(f"- reprojection RMS (per corner, as OpenCV): {rms_all if rms_all is None else f'{rms_all:.4f}'} px"
                 + (f"; held out ({ho.get('folds')}-fold): {ho['rms_px']:.4f} px" if ho.get("rms_px") else ""))
    F = calib["w_mm"] / calib["pixel_pitch_mm"]
    lines.append(f"- focal length {F:.2f} px, principal point {calib.get('principal_point_px')}, distortion "
                 f"{calib.get('distortion_model', 'none')}: {(calib.get('distortion') or {}).get('coefficients')}")
    lines.append(f"- undetermined: {calib.get('undetermined') or 'none'}; skipped: "
                 f"{[s.get('image') for s in calib.get('skipped') or []] or 'none'}")
    lines.append(f"- image coverage (8×6 cells with a corner): {100 * covered:.0f} %")
    for note in calib.get("notes") or []:
        lines.append(f"- note: {note}")
    lines += ["", "| view | RMS (px) | corners | outlier |", "|---|---|---|---|"]
    for nm, v in zip(names, views):
        r = v.get("rms_reprojection_px")
        lines.append(f"| {nm} | {'' if r is None else f'{r:.3f}'} | {v.get('n_points')} | "
                     f"{'yes' if v.get('outlier') else ''} |")
    lines += _uncertainty_lines(calib)
    path = os.path.join(out_dir, "report.md")
    with open(path, "w", encoding="utf-8") as f:
        f.write("\n".join(lines) + "\n")
    files.append("report.md")
    return files


def _projection_uncertainty_plot(calib: dict, save, plt) -> None:
    """projection_uncertainty.png: the map of CALIB.json's `projection_uncertainty` (nothing without one)."""
    pu = calib.get("projection_uncertainty")
    if not isinstance(pu, dict) or not pu.get("sigma_px"):
        return
    W, H = calib["image_size_px"]
    sig = np.array([[np.nan if s is None else s for s in row] for row in pu["sigma_px"]], dtype=np.float64)
    fig, ax = plt.subplots(figsize=(6, 6 * H / W + 0.8))
    im = ax.pcolormesh(np.array(pu["grid_x_px"]), np.array(pu["grid_y_px"]), sig, shading="nearest", cmap="magma",
                       vmin=0)
    ax.set_xlim(0, W)
    ax.set_ylim(H, 0)
    ax.set_aspect("equal")
    fig.colorbar(im, ax=ax, shrink=0.8, label="σ of the projection (px)")
    model = (calib.get("sigma_model") or {}).get("name", "classical")
    ax.set_title(f"Projection uncertainty ({model} error model): median {pu['median_px']:.2g} px, "
                 f"worst {pu['worst_px']:.2g} px", fontsize=9)
    save(fig, "projection_uncertainty.png")


def _uncertainty_lines(calib: dict) -> list:
    """report.md lines on the error model, the projection uncertainty and the cross-validation."""
    out = []
    model = calib.get("sigma_model")
    if model:
        extra = f", design effect {model['design_effect']:.2g}" if model.get("design_effect") else ""
        out.append(f"- σ error model: {model.get('name')}{extra}")
    pu = calib.get("projection_uncertainty")
    if pu and pu.get("median_px") is not None:
        out.append(f"- projection uncertainty: median {pu['median_px']:.2g} px, worst {pu['worst_px']:.2g} px")
    cv = calib.get("cross_validation")
    for pair in (cv or {}).get("pairs", []):
        a, b = pair["groups"]
        pred = pair.get("predicted_median_px")
        out.append(f"- cross-validation, groups {a} and {b}: difference median {pair['median_px']:.2g} px against "
                   + (f"{pred:.2g} px predicted" if pred is not None else "no prediction")
                   + f": {pair['verdict'].split(':')[0]}")
    return out
