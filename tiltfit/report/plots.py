"""`tiltfit report CALIB.json -o DIR`: the plots that tell whether a calibration can be trusted.

    write_report(calib: dict, out_dir) -> list of files written

Reads only CALIB.json (per-view `corners_px`, `residuals_px`, `blur_px`, `blur_residuals_px`, `depth_mm`,
written by `tiltfit calibrate`). Files:
    per_view_rms.png        reprojection RMS of every view, outlier views in red (a bad detection or a moved
                            board shows up here first)
    residual_vectors.png    each view's residual vectors on the image (exaggerated): a pattern that repeats
                            across views (radial, one corner) is model error; random directions are noise
    residual_vectors_flat_board.png  the same with the target file's flat board instead of the fitted one
                            (only when the calibration fitted the board's shape: what that shape explains)
    residual_histogram.png  x and y residuals with the Gaussian of the fitted σ: heavy tails mean outliers
    blur_vs_depth.png       blur residual against depth, with the median per depth bin (a trend means the focus
                            or blur model is off; the title names one the calibration found significant,
                            `model_selection.blur.trend_with_depth`)
    coverage.png            where in the image the corners fell, and the share of the image inside the union
                            of the views' boards (`coverage_fraction`): empty regions (corners, a bare
                            border) leave the distortion there extrapolated
    projection_uncertainty.png  σ of the projection across the image (CALIB.json's `projection_uncertainty`,
                            `tiltfit.uncertainty.covariance`), where the file has it
    report.md               the numbers: RMS, held-out error, per-view table, undetermined and skipped,
                            the calibration's notes and warnings
    photometric_residual_view_KK.png  where CALIB.json has a `photometric` record and `real_vs_rendered` options
                            are given: for the same views and photos as the real-against-rendered page, photo −
                            the photometric model through the camera the record refers to (the refined one where
                            kept, else the corner fit's), with the record's exposure (`photometric_residual`)
    real_vs_rendered/view_KK.png, real_vs_rendered.png, real_vs_rendered.json  with `real_vs_rendered` options
                            (the CLI's default): each found photo against the target rendered through the
                            calibration, difference and brightness profiles (`tiltfit.report.real_vs_rendered`)
"""
from __future__ import annotations

import math
import os

import numpy as np

from .photometric import check_photometric_record, write_photometric_residuals
from .summary import sigma_px_text, summary_lines

#: Cell size (px) of the raster that `coverage_fraction` measures the union of the views' boards on.
COVERAGE_CELL_PX = 4


def coverage_fraction(corners_per_view, image_size_px, cell_px: int = COVERAGE_CELL_PX) -> float:
    """Share of the image (0–1) inside at least one view's board: the union of the convex hulls of each
    view's detected corners, rasterised on cells of `cell_px` pixels. A board that never reaches the border
    leaves the border bare, and the share says so (an 80 px bare border of a 1280×1024 image: 74 %).

    Args:
        corners_per_view: list of (N, 2) corner positions (px; NaN rows ignored), one per view.
        image_size_px: (W, H).
    """
    return float(coverage_mask(corners_per_view, image_size_px, cell_px).mean())


def coverage_mask(corners_per_view, image_size_px, cell_px: int = COVERAGE_CELL_PX) -> np.ndarray:
    """(ceil(H / cell_px), ceil(W / cell_px)) uint8: 1 in cells inside some view's board (`coverage_fraction`)."""
    import cv2

    W, H = (int(v) for v in image_size_px)
    gw, gh = max(1, math.ceil(W / cell_px)), max(1, math.ceil(H / cell_px))
    mask = np.zeros((gh, gw), np.uint8)
    for c in corners_per_view:
        c = np.asarray(c, dtype=np.float64).reshape(-1, 2)
        c = c[np.isfinite(c).all(1)]
        if len(c) < 3:
            continue
        # pixel centres at integers: the image spans [-0.5, W - 0.5]; cell k covers [k, k + 1) · cell_px
        hull = cv2.convexHull(np.round((c + 0.5) / cell_px * 16).astype(np.int32))
        cv2.fillConvexPoly(mask, hull, 1, lineType=cv2.LINE_8, shift=4)
    return mask


def _short(name: str, n: int = 16) -> str:
    """A file name cut to n characters in the middle (titles of small panels)."""
    return name if len(name) <= n else name[: n // 2 - 1] + "…" + name[-(n - n // 2):]


def _views(calib: dict) -> list:
    views = calib.get("views") or []
    if not views:
        raise ValueError("views: the calibration has no views, so there are no residuals to plot")
    if not any("residuals_px" in v for v in views):
        raise ValueError("views[].residuals_px: missing (calibrate with this version of tiltfit to get a report)")
    if not any(r is not None for v in views for r in v.get("residuals_px") or []):
        raise ValueError("views[].residuals_px: no view has a residual to draw")
    return views


def _arr(values, width: int) -> np.ndarray:
    return np.array([[np.nan] * width if v is None else ([v] if width == 1 else v) for v in values],
                    dtype=np.float64).reshape(len(values), width)


def write_report(calib: dict, out_dir: str, calib_path: str | None = None, real_vs_rendered=None) -> list:
    """Write the report's PNG plots and report.md into `out_dir`; returns the paths written.

    `calib` is a CALIB dict checked by `tiltfit.files.calib.validate_calib`. The files are written as a set
    (`camio.files.atomic_folder`): on an error or interrupt none of them reaches `out_dir`.
    real_vs_rendered: `tiltfit.report.real_vs_rendered.RealVsRenderedOptions` to add the real-against-rendered page
    (photos found through the views' `image`, relative to `calib_path`'s folder or in its `photos_dirs`), or None.
    """
    from camio.files import atomic_folder

    views = _views(calib)
    if "photometric" in calib:
        check_photometric_record(calib["photometric"], len(views))
    with atomic_folder(out_dir) as staging:
        names = _write_plots(calib, views, staging)
        wanted = real_vs_rendered is not None and (real_vs_rendered.max_views > 0 or real_vs_rendered.views)
        if wanted and isinstance(calib.get("photometric"), dict):
            more, lines = write_photometric_residuals(calib, calib_path, staging, real_vs_rendered)
            names += more
            with open(os.path.join(staging, "report.md"), "a", encoding="utf-8") as f:
                f.write("\n".join(lines) + "\n")
        if wanted:
            from tiltfit.report.real_vs_rendered import markdown_lines, write_real_vs_rendered

            more, summary = write_real_vs_rendered(calib, calib_path, staging, real_vs_rendered)
            names += more
            with open(os.path.join(staging, "report.md"), "a", encoding="utf-8") as f:
                f.write("\n".join(markdown_lines(summary)) + "\n")
    return [os.path.join(out_dir, name) for name in names]


def _write_plots(calib: dict, views: list, out_dir: str) -> list:
    """The report's files written into `out_dir`; returns their names."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    names = [os.path.basename(str(v.get("image", f"view{i}"))) for i, v in enumerate(views)]
    C = [_arr(v.get("corners_px", []), 2) for v in views]
    E = [_arr(v.get("residuals_px", []), 2) for v in views]
    out = np.array([bool(v.get("outlier")) for v in views])
    files = []

    def save(fig, name):
        path = os.path.join(out_dir, name)
        try:
            fig.savefig(path, dpi=110, bbox_inches="tight")
        finally:
            plt.close(fig)
        files.append(name)

    save(_rms_figure(plt, views, names, out), "per_view_rms.png")
    _residual_vector_figures(plt, calib, views, C, E, names, out, save)
    save(_histogram_figure(plt, _finite_rows(E)), "residual_histogram.png")
    save(_blur_depth_figure(plt, calib, views), "blur_vs_depth.png")
    fig, covered = _coverage_figure(plt, C, calib["image_size_px"])
    save(fig, "coverage.png")
    _projection_uncertainty_plot(calib, save, plt)
    with open(os.path.join(out_dir, "report.md"), "w", encoding="utf-8") as f:
        f.write("\n".join(summary_lines(calib, views, names, covered)) + "\n")
    files.append("report.md")
    return files


def _finite_rows(E: list) -> np.ndarray:
    """(M, 2) the residuals of every view without their NaN rows."""
    return np.concatenate([e[np.isfinite(e).all(1)] for e in E]) if len(E) else np.zeros((0, 2))


def _rms_figure(plt, views: list, names: list, out: np.ndarray):
    """per_view_rms.png: each view's reprojection RMS, outlier views in red."""
    rms = np.array([v.get("rms_reprojection_px") or np.nan for v in views], dtype=np.float64)
    fig, ax = plt.subplots(figsize=(max(6, 0.25 * len(views) + 2), 3.2))
    ax.bar(range(len(views)), rms, color=np.where(out, "tab:red", "tab:blue"))
    ax.axhline(np.nanmedian(rms), color="k", lw=0.8, ls="--", label="median")
    ax.set_xticks(range(len(views)), names, rotation=90, fontsize=6)
    ax.set_ylabel("RMS per corner (px)")
    ax.set_title("Reprojection RMS per view (red: outlier)")
    ax.legend()
    return fig


def _residual_vector_figures(plt, calib: dict, views: list, C: list, E: list, names: list, out, save) -> None:
    """residual_vectors.png with the board as fitted, and (when its shape was fitted) residual_vectors_flat_board.png
    with the flat board, at one arrow scale so that they compare: that of the larger (flat-board) residuals."""
    W, H = calib["image_size_px"]
    board = calib.get("board") or {}
    E_flat = [_arr(v.get("residuals_flat_board_px", []), 2) for v in views]
    fitted_board = board.get("model", "flat") != "flat" and all(len(e) for e in E_flat)
    ref = _finite_rows(E_flat) if fitted_board else _finite_rows(E)
    typical = float(np.percentile(np.hypot(ref[:, 0], ref[:, 1]), 90)) if len(ref) else 1.0
    scale = 0.05 * max(W, H) / max(typical, 1e-9)
    what = f"the board as fitted ({board.get('model')})" if fitted_board else "the target file's board"
    save(_vector_figure(plt, C, E, names, out, (W, H), scale, f"Residual vectors (model − detected), ×{scale:.0f}, "
                        f"with {what}"), "residual_vectors.png")
    if fitted_board:
        save(_vector_figure(plt, C, E_flat, names, out, (W, H), scale,
                            f"Residual vectors, ×{scale:.0f}, with the target file's flat board (same lens, poses "
                            f"refitted)"),
             "residual_vectors_flat_board.png")


def _histogram_figure(plt, allE: np.ndarray):
    """residual_histogram.png: the x and y residuals with the Gaussian of their RMS."""
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
    return fig


def _blur_depth_figure(plt, calib: dict, views: list):
    """blur_vs_depth.png: the blur residuals against depth with the median per depth bin, the title naming a trend
    the calibration found significant."""
    fig, ax = plt.subplots(figsize=(6, 3.5))
    z = np.concatenate([_arr(v.get("depth_mm", []), 1).ravel() for v in views])
    br = np.concatenate([_arr(v.get("blur_residuals_px", [None] * len(v.get("depth_mm", []))), 1).ravel()
                         for v in views])
    ok = np.isfinite(z) & np.isfinite(br)
    trend = ((calib.get("model_selection") or {}).get("blur") or {}).get("trend_with_depth") or {}
    if ok.any():
        ax.scatter(z[ok], br[ok], s=3, alpha=0.5)
        ax.axhline(0, color="k", lw=0.8)
        edges = np.quantile(z[ok], np.linspace(0, 1, 9))
        mid = 0.5 * (edges[1:] + edges[:-1])
        med = [np.median(br[ok][(z[ok] >= a) & (z[ok] <= b)]) for a, b in zip(edges[:-1], edges[1:])]
        ax.plot(mid, med, "o-", color="tab:red", ms=3, lw=1.2, label="median per depth bin")
        ax.legend(fontsize=8)
        ax.set_ylabel("blur residual, model − measured (px)")
    else:
        ax.text(0.5, 0.5, "no blur widths in this calibration", ha="center", va="center", transform=ax.transAxes)
    ax.set_xlabel("depth z in the camera frame (mm)")
    ax.set_title("Blur residual against depth" + (
        f": a trend the blur model does not explain\n({trend['amplitude_px']:.2g} px over the depths, "
        f"p = {trend['p_value']:.1g}; see the warning in report.md)" if trend.get("significant") else ""),
        fontsize=10)
    return fig


def _coverage_figure(plt, C: list, image_size_px):
    """(coverage.png: the corners of all views over the union of their boards, the share of the image inside it)."""
    W, H = image_size_px
    n = len(C)
    fig, ax = plt.subplots(figsize=(6, 6 * H / W + 0.6))
    cmap = plt.get_cmap("viridis")
    for i, c in enumerate(C):
        ok = np.isfinite(c).all(1)
        ax.scatter(c[ok, 0], c[ok, 1], s=3, color=cmap(i / max(n - 1, 1)))
    ax.set_xlim(0, W)
    ax.set_ylim(H, 0)
    ax.set_aspect("equal")
    mask = coverage_mask(C, (W, H))
    covered = float(mask.mean())
    cell = COVERAGE_CELL_PX
    ax.imshow(mask, cmap="Greys", vmin=0, vmax=4, interpolation="nearest",
              extent=(-0.5, mask.shape[1] * cell - 0.5, mask.shape[0] * cell - 0.5, -0.5))
    ax.set_xlim(-0.5, W - 0.5)
    ax.set_ylim(H - 0.5, -0.5)
    ax.set_title(f"Corners of all views (colour = view); {100 * covered:.0f} % of the image inside a view's board",
                 fontsize=9)
    return fig, covered


def _vector_figure(plt, C, E, names, out, size, scale, title):
    """One panel per view of residual vectors ×`scale`; titles in two short lines so that neighbours do not
    overlap."""
    W, H = size
    n = len(C)
    cols = max(1, int(math.ceil(math.sqrt(n * 4 / 3))))
    rows = max(1, int(math.ceil(n / cols)))
    fig, axes = plt.subplots(rows, cols, figsize=(2.4 * cols, 2.4 * rows * H / W + 0.45 * rows + 0.5),
                             squeeze=False)
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
        e = E[i][ok]
        r = math.sqrt(float((e ** 2).sum(1).mean())) if len(e) else math.nan
        ax.set_title(f"{i}: {_short(names[i])}\n{r:.2f} px", fontsize=6)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    return fig


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
    ax.set_title(f"Projection uncertainty ({model} error model)\nmedian {sigma_px_text(pu.get('median_px'))}, "
                 f"worst {sigma_px_text(pu.get('worst_px'))}", fontsize=9, loc="left")
    save(fig, "projection_uncertainty.png")
