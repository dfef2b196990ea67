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
from dataclasses import dataclass

import numpy as np


def with_sigma(value: float, sigma: float | None) -> str:
    """"value ± σ" with σ to 2 significant digits and the value rounded to the same decimal place
    (3041.27 ± 1.314 -> "3041.3 ± 1.3"); the value to 4 significant digits when σ is unknown or 0."""
    if sigma is None or not math.isfinite(sigma) or sigma <= 0:
        return f"{value:.4g}"
    if not math.isfinite(value):
        return f"{value} ± {sigma:.2g}"
    place = math.floor(math.log10(sigma)) - 1          # the decimal place of σ's second significant digit
    decimals = max(-place, 0)
    q = 10.0 ** place
    v, sg = round(value / q) * q, round(sigma / q) * q
    return f"{v:.{decimals}f} ± {sg:.{decimals}f}"


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

    # Residual vectors per view: with the board as fitted, and (when its shape was fitted) with the flat board.
    n = len(views)
    allE = np.concatenate([e[np.isfinite(e).all(1)] for e in E]) if n else np.zeros((0, 2))
    board = calib.get("board") or {}
    E_flat = [_arr(v.get("residuals_flat_board_px", []), 2) for v in views]
    fitted_board = board.get("model", "flat") != "flat" and all(len(e) for e in E_flat)
    # One arrow scale for both figures, so that they compare: that of the larger (flat-board) residuals.
    ref = np.concatenate([e[np.isfinite(e).all(1)] for e in E_flat]) if fitted_board else allE
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
    mask = coverage_mask(C, (W, H))
    covered = float(mask.mean())
    cell = COVERAGE_CELL_PX
    ax.imshow(mask, cmap="Greys", vmin=0, vmax=4, interpolation="nearest",
              extent=(-0.5, mask.shape[1] * cell - 0.5, mask.shape[0] * cell - 0.5, -0.5))
    ax.set_xlim(-0.5, W - 0.5)
    ax.set_ylim(H - 0.5, -0.5)
    ax.set_title(f"Corners of all views (colour = view); {100 * covered:.0f} % of the image inside a view's board",
                 fontsize=9)
    save(fig, "coverage.png")

    _projection_uncertainty_plot(calib, save, plt)

    # Text summary.
    lines = ["# Calibration report", ""]
    rms_all = calib.get("rms_reprojection_px")
    ho = calib.get("held_out") or {}
    lines.append(f"- reprojection RMS (per corner, as OpenCV): {rms_all if rms_all is None else f'{rms_all:.4f}'} px"
                 + (f"; held out ({ho.get('folds')}-fold): {ho['rms_px']:.4f} px" if ho.get("rms_px") else ""))
    from tiltfit.files.calibrated import Calibration

    lens_calib = Calibration.from_dict(calib)
    F, sF = lens_calib.focal_px, lens_calib.sigma_focal_px
    sig = calib.get("sigma") or {}
    pp, spp = calib.get("principal_point_px") or [math.nan, math.nan], sig.get("principal_point_px") or [None, None]
    lines.append(f"- focal length {with_sigma(F, sF)} px, principal point ({with_sigma(pp[0], spp[0])}, "
                 f"{with_sigma(pp[1], spp[1])}) px, distortion {calib.get('distortion_model', 'none')}: "
                 f"{_rounded_list((calib.get('distortion') or {}).get('coefficients'), sig.get('distortion'))}")
    if board:
        lines.append(f"- board: {_board_text(board)}")
    lines.append(f"- undetermined: {calib.get('undetermined') or 'none'}; skipped: "
                 f"{[s.get('image') for s in calib.get('skipped') or []] or 'none'}")
    lines.append(f"- image coverage (share of the image inside a view's board): {100 * covered:.0f} %")
    for note in calib.get("notes") or []:
        lines.append(f"- note: {note}")
    for warning in calib.get("warnings") or []:
        lines.append(f"- warning: {warning}")
    lines += ["", "| view | RMS (px) | corners | outlier |", "|---|---|---|---|"]
    for nm, v in zip(names, views):
        r = v.get("rms_reprojection_px")
        lines.append(f"| {nm} | {'' if r is None else f'{r:.3f}'} | {v.get('n_points')} | "
                     f"{'yes' if v.get('outlier') else ''} |")
    lines += _uncertainty_lines(calib)
    lines += photometric_lines(calib)
    path = os.path.join(out_dir, "report.md")
    with open(path, "w", encoding="utf-8") as f:
        f.write("\n".join(lines) + "\n")
    files.append("report.md")
    return files


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


def _rounded_list(values, sigmas) -> str:
    """Coefficients rounded to their σ where known (`with_sigma`), else to 4 significant digits."""
    if not values:
        return "none"
    sigmas = sigmas or [None] * len(values)
    pairs = list(zip(values, sigmas))
    while pairs and pairs[-1][0] == 0 and not pairs[-1][1]:  # trailing zeros only: the others keep their places
        pairs.pop()
    return "[" + ", ".join(with_sigma(v, s) if s else f"{v:.4g}" for v, s in pairs) + "]"


def _px(value) -> str:
    """A σ in pixels to 2 significant digits, "unknown" where CALIB.json has null."""
    return "unknown" if value is None else f"{value:.2g} px"


def _board_text(board: dict) -> str:
    """The fitted board in one line, numbers rounded to their σ."""
    model = board.get("model", "flat")
    if model == "warp":
        par, sig = board.get("parameters") or {}, board.get("sigma") or {}
        return "warp: " + ", ".join(f"{k} {with_sigma(v, sig.get(k))}" for k, v in par.items())
    if model == "free":
        return (f"free (every point): moved up to {board.get('max_offset_in_plane_mm', 0):.2g} mm in the board's "
                f"plane and {board.get('max_offset_out_of_plane_mm', 0):.2g} mm out of it")
    return "flat (the target file's points)"


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
    ax.set_title(f"Projection uncertainty ({model} error model)\nmedian {_px(pu.get('median_px'))}, "
                 f"worst {_px(pu.get('worst_px'))}", fontsize=9, loc="left")
    save(fig, "projection_uncertainty.png")


def _uncertainty_lines(calib: dict) -> list:
    """report.md lines on the error model, the projection uncertainty and the cross-validation."""
    out = []
    model = calib.get("sigma_model")
    if model:
        extra = f", design effect {model['design_effect']:.2g}" if model.get("design_effect") else ""
        out.append(f"- σ error model: {model.get('name')}{extra}")
    pu = calib.get("projection_uncertainty")
    if pu:
        out.append(f"- projection uncertainty: median {_px(pu.get('median_px'))}, worst {_px(pu.get('worst_px'))}")
    cv = calib.get("cross_validation")
    for pair in (cv or {}).get("pairs", []):
        a, b = pair["groups"]
        pred = pair.get("predicted_median_px")
        out.append(f"- cross-validation, groups {a} and {b}: difference median {_px(pair.get('median_px'))} against "
                   + (f"{_px(pred)} predicted" if pred is not None else "no prediction")
                   + f": {pair['verdict'].split(':')[0]}")
    return out


def _finite(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def check_photometric_record(ph, n_views: int) -> None:
    """Refuse (ValueError naming the field) a CALIB.json `photometric` record the report cannot read: `kept` a text,
    `bounds` entries with `start`, `low`, `high`, `refined` finite or null (∞), `vignetting` finite, `levels` one entry (or
    null) a view with finite levels and gains, `refined` and `corner_fit` lens values finite or null."""
    if not isinstance(ph, dict):
        raise ValueError(f"photometric: expected an object, got {type(ph).__name__}")
    if not isinstance(ph.get("kept", ""), str):
        raise ValueError(f"photometric.kept: expected a text, got {ph['kept']!r}")
    for i, b in enumerate(ph.get("bounds") or []):
        if not isinstance(b, dict) or not isinstance(b.get("parameter"), str):
            raise ValueError(f"photometric.bounds[{i}]: expected an object with a parameter name, got {b!r}")
        for key in ("start", "low", "high", "refined"):   # null: U at infinity (1/U = 0)
            if b.get(key) is not None and not _finite(b.get(key)):
                raise ValueError(f"photometric.bounds[{i}].{key}: expected a number or null, got {b.get(key)!r}")
    if ph.get("vignetting") is not None and not _finite(ph["vignetting"]):
        raise ValueError(f"photometric.vignetting: expected a finite number, got {ph['vignetting']!r}")
    levels = ph.get("levels")
    if levels is not None:
        if not isinstance(levels, list) or len(levels) != n_views:
            raise ValueError(f"photometric.levels: expected a list of {n_views} entries (one a view), got {levels!r}"[:200])
        for i, lv in enumerate(levels):
            if lv is None:
                continue
            if not isinstance(lv, dict):
                raise ValueError(f"photometric.levels[{i}]: expected an object or null, got {lv!r}")
            for key in ("white", "black", "gain_x", "gain_y"):
                if key in lv and not _finite(lv[key]):
                    raise ValueError(f"photometric.levels[{i}].{key}: expected a finite number, got {lv[key]!r}")
    for name in ("refined", "corner_fit"):
        lens = ph.get(name)
        if lens is None:
            continue
        if not isinstance(lens, dict):
            raise ValueError(f"photometric.{name}: expected an object, got {lens!r}")
        for key, value in lens.items():
            if value is not None and not _finite(value):
                raise ValueError(f"photometric.{name}.{key}: expected a finite number or null, got {value!r}")


def photometric_lines(calib: dict) -> list:
    """report.md lines on the photometric refinement (`--refine photometric`): kept or not and why, and for each
    bounded lens parameter its start, bound and refined value (which parameter hit which bound)."""
    ph = calib.get("photometric")
    if not isinstance(ph, dict):
        return []
    out = ["", "## Photometric refinement", "",
           f"- kept: {ph.get('kept', 'photometric')}" + (f" (not kept: {ph['rejected_because']})"
                                                          if ph.get("rejected_because") else "")]
    if ph.get("rms_linear") is not None:
        out.append(f"- pixel residual RMS {ph['rms_linear']:.4g} (linear units)")
    bounds = ph.get("bounds") or []
    if bounds:
        out += ["", "| parameter | start | trust bound | refined | at the bound |", "|---|---|---|---|---|"]
        for b in bounds:
            out.append(f"| {b['parameter']} | {_bound_value(b['start'])} | [{_bound_value(b['low'])}, "
                       f"{_bound_value(b['high'])}] | {_bound_value(b['refined'])} | "
                       f"{'**yes**' if b.get('at_bound') else 'no'} |")
    return out + ["", bound_sentence(ph)]


def _bound_value(value) -> str:
    """A bound record's number; null is U at infinity (1/U = 0)."""
    return "∞" if value is None else f"{value:.6g}"


def bound_sentence(ph: dict) -> str:
    """One sentence on which lens parameter hit which end of its trust bound (CALIB.json's photometric `bounds`,
    `at_bound`), and why the refinement was not kept where it was not (`rejected_because`)."""
    bounds = [b for b in ph.get("bounds") or [] if isinstance(b, dict)]
    hits = [b for b in bounds if b.get("at_bound")]
    kept = ph.get("kept", "photometric") == "photometric"
    why = ph.get("rejected_because") or ""
    if hits:
        parts = []
        for b in hits:
            r, lo, hi = (math.inf if b.get(k) is None else float(b[k]) for k in ("refined", "low", "high"))
            end = "upper" if r == hi or (math.isfinite(r) and abs(r - hi) <= abs(r - lo)) else "lower"
            parts.append(f"{b['parameter']} hit the {end} end of its trust bound ({_bound_value(b.get('start'))} → "
                         f"{_bound_value(b.get('refined'))}, bound [{_bound_value(b.get('low'))}, "
                         f"{_bound_value(b.get('high'))}])")
        text = "; ".join(parts) + ": pixels and corners disagree on " + (
            "it" if len(hits) == 1 else "them") + " beyond both fits' σ"
        return f"**Trust bound:** {text}" + ("" if kept else ", so the corner fit is kept") + "."
    if not bounds and ph.get("at_bound"):   # a record without the table
        return f"**Trust bound:** {', '.join(ph['at_bound'])} ended at the trust bound" + (
            "" if kept else ", so the corner fit is kept") + "."
    text = "No lens parameter reached its trust bound" if bounds else "No trust bounds are recorded"
    return f"**Trust bound:** {text}" + (f"; the refinement was not kept: {why}." if not kept and why else ".")


#: Most pixels a view's photometric residual image evaluates (`photometric_residual`): beyond it every k-th column
#: and row of the board's box (each still a full-resolution pixel of the model). The model's cost is mostly the
#: undistortion of each pixel: 22,000-30,000 usable pixels a view took a median 9-10 s on the shipped sets
#: (benchmarks/results/report_photometric_real.md).
RESIDUAL_MAX_PIXELS = 40_000
#: Residuals beyond this many robust σ are left out of the levels' fit (glare, dust), as in the real-vs-rendered fit.
LEVELS_CLIP_SIGMA = 3.0


@dataclass
class PhotometricResidual:
    """One view's photometric residual (`photometric_residual`).

    Attributes:
        residual: (H, W) photo − model (linear units), NaN off the pixels the fit may use and off the stride's grid.
        stride: every `stride`-th column and row was evaluated (`residual[::stride, ::stride]` is the picture).
        white, black, vignetting, gain: the exposure the model was shaded with.
        levels: "record" (CALIB.json's photometric `levels` of this view) or "refitted" (white and black fitted
            to this photo with the rest held: the record's levels belong to another camera, or are missing).
        camera: "photometric" (the refined lens and poses) or "corner fit".
        rms_levels_refitted: the RMS with white and black fitted to these pixels (`fit_levels`): far below `rms`
            where the levels, not the geometry, miss (a tone curve, sharpening halos the fit's edge pixels saw).
        n_saturated: pixels left out as saturated (glare; the fit leaves them out too).
    """

    residual: np.ndarray
    stride: int
    white: float
    black: float
    vignetting: float
    gain: tuple
    levels: str
    camera: str
    rms_levels_refitted: float = math.nan
    n_saturated: int = 0

    @property
    def rms(self) -> float:
        """RMS of the residual over the evaluated pixels (linear units)."""
        r = self.residual[np.isfinite(self.residual)]
        return float(np.sqrt(np.mean(r * r))) if r.size else math.nan

    @property
    def n_pixels(self) -> int:
        return int(np.isfinite(self.residual).sum())


def photometric_calibration(calib: dict, calib_path: str | None = None):
    """The `tiltfit.files.calibrated.Calibration` of the camera CALIB.json's photometric record refers to: the file's lens
    and poses (the refined ones where `kept` is "photometric", else the corner fit's) with w, U, d and θF as the
    refinement saw them (`refined` or `corner_fit`: where the corners could not tell U and d the file has them
    null, and the refinement ran with a placeholder U and a fitted or starting d)."""
    from tiltfit.files.calibrated import Calibration

    ph = calib.get("photometric") or {}
    lens = ph.get("refined" if ph.get("kept", "photometric") == "photometric" else "corner_fit") or {}
    keys = ("w_mm", "d_mm", "theta_F_deg")
    data = dict(calib)
    if all(_finite(lens.get(k)) for k in keys):
        data.update({k: float(lens[k]) for k in keys})
        # U at infinity (1/U = 0) is null in the JSON
        data["U_mm"] = float(lens["U_mm"]) if _finite(lens.get("U_mm")) else math.inf
        data.pop("theta_L_deg", None)   # θL follows from θF, w and U (`lens_from_calib`)
    return Calibration.from_dict(data, calib_path or "<calibration>")


def fit_levels(photo: np.ndarray, dark: np.ndarray, vignetting: float = 0.0, gain=(0.0, 0.0)) -> tuple[float, float]:
    """(white, black): the view's levels fitted to `photo` (H, W, linear) where `dark` (H, W, NaN elsewhere; a
    `tiltfit.photometric.render.dark_fraction_image`) is evaluated, vignetting and illumination gradient held.
    The model is linear in the levels (white · shade(D; 1, 0) + black · shade(D; 0, 1)); least squares, pixels
    beyond LEVELS_CLIP_SIGMA robust σ left out and the fit repeated."""
    from tiltfit.photometric.render import shade_image

    ok = np.isfinite(dark) & np.isfinite(photo)
    A = np.stack([shade_image(dark, 1.0, 0.0, vignetting, gain)[ok],
                  shade_image(dark, 0.0, 1.0, vignetting, gain)[ok]], 1)
    from tiltfit.solve.robust_linear import clipped_lstsq

    y = np.asarray(photo, dtype=np.float64)[ok]
    coef, _ = clipped_lstsq(A, y, LEVELS_CLIP_SIGMA, iterations=5, min_rows=2)
    if coef is None:
        coef = np.array([1.0, 0.0])
    return float(coef[0]), float(coef[1])


def photometric_residual(calib: dict, view: int, photo: np.ndarray, calib_path: str | None = None,
                         max_pixels: int = RESIDUAL_MAX_PIXELS) -> PhotometricResidual:
    """Photo − the photometric forward model of one view (`tiltfit.photometric.render.residual_image`'s model:
    the target's dark fraction with the aperture in closed form, shaded by the view's exposure), through the camera
    CALIB.json's `photometric` record refers to (`photometric_calibration`).

    The exposure is the record's: its `vignetting` and the view's illumination gradient (`levels[view]` `gain_x`,
    `gain_y`), and its white and black levels where the refinement was kept; where it was not, the record's levels
    belong to the rejected camera, so white and black are refitted to the photo through the corner fit's
    (`fit_levels`, as the refinement's held-out check does), as they are for a record without levels. Saturated
    pixels (the fit's `PhotometricOptions.saturation` of the photo's brightest: glare) are left out as the fit
    leaves them out.

    Args:
        photo: (H, W) linear photo of the view at the calibration's size (the channels' mean, as the fit reads it).
        max_pixels: evaluate every k-th column and row where the board's box holds more (RESIDUAL_MAX_PIXELS).
    """
    from tiltfit.photometric import PhotometricOptions
    from tiltfit.photometric.render import board_box, dark_fraction_image, shade_image

    ph = calib.get("photometric") or {}
    kept = ph.get("kept", "photometric") == "photometric"
    cal = photometric_calibration(calib, calib_path)
    target = cal.target
    if target is None:
        raise ValueError("target: the calibration holds no target, so there is nothing to render")
    photo = np.asarray(photo, dtype=np.float64)
    W, H = cal.image_size_px
    if photo.shape != (H, W):
        raise ValueError(f"a {photo.shape[1]}x{photo.shape[0]} photo; the calibration's images are {W}x{H}")
    cam = cal.camera(view)
    box = board_box(target, cam)
    area = 0 if box is None else (box[2] - box[0] + 1) * (box[3] - box[1] + 1)
    stride = max(1, math.ceil(math.sqrt(area / max(int(max_pixels), 1))))
    dark = dark_fraction_image(target, cam, stride=stride)
    saturation = PhotometricOptions().saturation
    saturated = np.isfinite(dark) & (photo >= (saturation or math.inf) * float(photo.max()))
    dark[saturated] = np.nan
    levels = (ph.get("levels") or [])
    rec = levels[view] if view < len(levels) and isinstance(levels[view], dict) else {}
    vignetting = float(ph.get("vignetting") or 0.0)
    gain = (float(rec.get("gain_x", 0.0)), float(rec.get("gain_y", 0.0)))
    refitted = fit_levels(photo, dark, vignetting, gain)
    if kept and "white" in rec and "black" in rec:
        (white, black), source = (float(rec["white"]), float(rec["black"])), "record"
    else:
        (white, black), source = refitted, "refitted"
    residual = photo - shade_image(dark, white, black, vignetting, gain)
    again = (photo - shade_image(dark, *refitted, vignetting, gain))[np.isfinite(dark)]
    return PhotometricResidual(residual, stride, white, black, vignetting, gain, source,
                               "photometric" if kept else "corner fit",
                               float(np.sqrt(np.mean(again * again))) if again.size else math.nan,
                               int(saturated.sum()))


def write_photometric_residuals(calib: dict, calib_path: str | None, out_dir: str, options) -> tuple[list, list]:
    """`photometric_residual_view_KK.png` for the views the real-against-rendered page compares (`options`: its
    `RealVsRenderedOptions`: the same view choice and photo lookup), and the report.md lines that show them.
    Returns (names written, relative to out_dir; lines)."""
    from camio.files import read_image

    from tiltfit.report.real_vs_rendered import board_outlines, find_photo, pick_views

    ph = calib["photometric"]
    say = getattr(options, "say", None) or (lambda text: None)
    kept = ph.get("kept", "photometric") == "photometric"
    views = calib.get("views") or []
    files, rows, skipped, shown = [], [], [], []
    cal = None
    for v in pick_views(len(views), options):
        image = str(views[v].get("image", ""))
        path = find_photo(image, calib_path, options.photos_dirs)
        if path is None:
            skipped.append(f"- view {v} ({os.path.basename(image)}): photo not found")
            continue
        say(f"photometric residual: view {v} ({os.path.basename(image)})")
        try:
            photo = read_image(path, options.encoding)
            photo = photo.mean(-1) if photo.ndim == 3 else photo
            res = photometric_residual(calib, v, photo, calib_path)
        except (ValueError, OSError) as e:   # an unreadable photo, one of another size
            skipped.append(f"- view {v} ({os.path.basename(image)}): {e}")
            continue
        if res.n_pixels == 0:
            skipped.append(f"- view {v} ({os.path.basename(image)}): no pixel of the board the fit may use")
            continue
        cal = cal or photometric_calibration(calib, calib_path)
        name = f"photometric_residual_view_{v:02d}.png"
        span = res.white - res.black if res.white > res.black else math.nan   # % of contrast: NaN without one
        title = (f"view {v}: {os.path.basename(image)}\nphoto − model through the "
                 + ("refined camera" if kept else "corner fit's camera (refinement not kept)")
                 + ("" if res.levels == "record" else ", levels refitted")
                 + f"\nRMS {res.rms:.3g} linear, {100 * res.rms / span:.2g} % of the print's contrast "
                 + f"({100 * res.rms_levels_refitted / span:.2g} % levels refitted)\n{res.n_pixels} "
                 + "pixels" + (f", one row and column in {res.stride}" if res.stride > 1 else "")
                 + (f"; {res.n_saturated} saturated left blank" if res.n_saturated else ""))
        plot_residual_image(res.residual, os.path.join(out_dir, name), title,
                            outlines=board_outlines(cal, cal.target, v), photo=photo, stride=res.stride,
                            contrast=span if math.isfinite(span) else None)
        files.append(name)
        shown.append(name)
        rows.append(f"| {v} | {os.path.basename(image)} | {res.rms:.4g} | {100 * res.rms / span:.2g} | "
                    f"{100 * res.rms_levels_refitted / span:.2g} | {res.n_pixels} | {res.stride} | {res.levels} |")
    lines = ["", "### Residual images", "",
             "Photo − the photometric model (the target's dark fraction through the lens, aperture in closed form, "
             "shaded by the view's exposure) on the pixels the fit may use (the board inside its margin), through "
             + ("the refined camera with the fit's levels, vignetting and illumination gradient."
                if kept else "the corner fit's camera (the refinement was not kept) with the refinement's vignetting "
                             "and illumination gradient, white and black refitted to each photo.")
             + " Red: the photo is brighter than the model."]
    if rows:
        lines += ["", "| view | image | RMS (linear) | RMS (% of contrast) | the same, levels refitted here | pixels "
                  "| stride | levels |", "|---|---|---|---|---|---|---|---|", *rows, "",
                  "Where refitting the levels to these pixels brings the RMS down a lot, the levels (a tone curve, "
                  "sharpening halos the fit's edge pixels saw), not the geometry, are what the model misses; "
                  "saturated pixels (glare) are left blank, as the fit leaves them out.", ""]
        lines += [f"![{n}]({n})" for n in shown]
    lines += skipped
    return files, lines


def plot_residual_image(residual: np.ndarray, path: str, title: str = "photo − rendered", *, outlines=None,
                        photo: np.ndarray | None = None, stride: int = 1, contrast: float | None = None) -> str:
    """Save an (H, W) residual image (photo − rendered, linear units; NaN where nothing was rendered) as a PNG with
    a diverging colour scale symmetric about 0 (±95th percentile of |residual|), cut to the rendered pixels.
    Returns `path`.

    Args:
        outlines: {name: (K, 2) polyline px} drawn over it (the board's edges, `real_vs_rendered.board_outlines`).
        photo: (H, W) linear photo shown faintly under it (context where nothing was rendered).
        stride: the residual was evaluated on every `stride`-th row and column (`residual[::stride, ::stride]`).
        contrast: white − black: the colour bar reads in % of it (else linear units).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    k = max(int(stride), 1)
    r = np.asarray(residual, dtype=np.float64)
    H, W = r.shape
    grid = r[::k, ::k]
    scale = 100.0 / contrast if contrast else 1.0
    finite = np.isfinite(grid)
    # ±95th percentile of |residual|: glare or a shadow over a few per cent of the board saturates the scale
    # (the bar's arrows) instead of washing out the rest
    lim = float(np.percentile(np.abs(grid[finite]), 95)) * scale if finite.any() else 1.0
    lim = lim if lim > 0 else 1.0
    if finite.any():   # cut to the rendered pixels, with a margin
        rows, cols = np.nonzero(finite)
        pad = max(4, int(0.04 * max(np.ptp(rows), np.ptp(cols)) * k))
        x0, x1 = max(cols.min() * k - pad, 0), min(cols.max() * k + pad, W - 1)
        y0, y1 = max(rows.min() * k - pad, 0), min(rows.max() * k + pad, H - 1)
    else:
        x0, y0, x1, y1 = 0, 0, W - 1, H - 1
    aspect = (y1 - y0 + 1) / (x1 - x0 + 1)
    fig, ax = plt.subplots(figsize=(7.5, 7.5 * aspect + 1.1))
    try:
        if photo is not None:
            p = np.asarray(photo, dtype=np.float64)
            hi = float(np.percentile(p, 99.5)) or 1.0
            ax.imshow(p, cmap="gray", vmin=-1.5 * hi, vmax=2.0 * hi, interpolation="nearest",
                      extent=(-0.5, W - 0.5, H - 0.5, -0.5))   # faint: context, not content
        gh, gw = grid.shape
        im = ax.imshow(np.where(finite, grid * scale, np.nan), cmap="RdBu_r", vmin=-lim, vmax=lim,
                       interpolation="nearest", extent=(-0.5 * k, (gw - 0.5) * k, (gh - 0.5) * k, -0.5 * k))
        for line in (outlines or {}).values():
            line = np.asarray(line, dtype=np.float64)
            ax.plot(line[:, 0], line[:, 1], color="k", lw=0.8, alpha=0.7)
        ax.set_xlim(x0 - 0.5, x1 + 0.5)
        ax.set_ylim(y1 + 0.5, y0 - 0.5)
        fig.colorbar(im, ax=ax, shrink=0.8, pad=0.02, extend="both",
                     label="photo − model, % of the print's contrast" if contrast else "photo − model (linear)")
        if "RMS" not in title:
            rms = float(np.sqrt(np.mean(grid[finite] ** 2))) if finite.any() else math.nan
            title = f"{title}: RMS {rms:.4g} over {int(finite.sum())} pixels"
        ax.set_title(title, fontsize=9)
        ax.text(0.0, -0.02, "red: photo brighter than the model, blue: darker\nlines: the checkered area and the "
                "board's edge", transform=ax.transAxes, ha="left", va="top", fontsize=7, color="0.3")
        ax.set_xticks([])
        ax.set_yticks([])
        fig.savefig(path, dpi=110, bbox_inches="tight")
    finally:
        plt.close(fig)
    return path
