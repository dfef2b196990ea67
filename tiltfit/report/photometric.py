"""The photometric refinement in `tiltfit report`: its CALIB.json record checked and summarised (`photometric_lines`,
`bound_sentence`), and each compared view's residual image, photo − the photometric model through the calibrated
camera with the record's exposure (`photometric_residual`, `write_photometric_residuals`, `plot_residual_image`)."""
from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np


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
