"""report.md of `tiltfit report`: the calibration in numbers, each rounded to its σ (`with_sigma`)."""
from __future__ import annotations

import math

from .photometric import photometric_lines


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


def summary_lines(calib: dict, views: list, names: list, covered: float) -> list:
    """report.md's lines: RMS and held-out error, the lens, board, undetermined and skipped keys, coverage, the
    calibration's notes and warnings, the per-view table, the uncertainty and the photometric refinement."""
    from tiltfit.files.calibrated import Calibration

    lines = ["# Calibration report", ""]
    rms_all = calib.get("rms_reprojection_px")
    ho = calib.get("held_out") or {}
    lines.append(f"- reprojection RMS (per corner, as OpenCV): {rms_all if rms_all is None else f'{rms_all:.4f}'} px"
                 + (f"; held out ({ho.get('folds')}-fold): {ho['rms_px']:.4f} px" if ho.get("rms_px") else ""))
    lens_calib = Calibration.from_dict(calib)
    F, sF = lens_calib.focal_px, lens_calib.sigma_focal_px
    sig = calib.get("sigma") or {}
    pp, spp = calib.get("principal_point_px") or [math.nan, math.nan], sig.get("principal_point_px") or [None, None]
    lines.append(f"- focal length {with_sigma(F, sF)} px, principal point ({with_sigma(pp[0], spp[0])}, "
                 f"{with_sigma(pp[1], spp[1])}) px, distortion {calib.get('distortion_model', 'none')}: "
                 f"{_rounded_list((calib.get('distortion') or {}).get('coefficients'), sig.get('distortion'))}")
    board = calib.get("board") or {}
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
    return lines


def _rounded_list(values, sigmas) -> str:
    """Coefficients rounded to their σ where known (`with_sigma`), else to 4 significant digits."""
    if not values:
        return "none"
    sigmas = sigmas or [None] * len(values)
    pairs = list(zip(values, sigmas))
    while pairs and pairs[-1][0] == 0 and not pairs[-1][1]:  # trailing zeros only: the others keep their places
        pairs.pop()
    return "[" + ", ".join(with_sigma(v, s) if s else f"{v:.4g}" for v, s in pairs) + "]"


def sigma_px_text(value) -> str:
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


def _uncertainty_lines(calib: dict) -> list:
    """report.md lines on the error model, the projection uncertainty and the cross-validation."""
    out = []
    model = calib.get("sigma_model")
    if model:
        extra = f", design effect {model['design_effect']:.2g}" if model.get("design_effect") else ""
        out.append(f"- σ error model: {model.get('name')}{extra}")
    pu = calib.get("projection_uncertainty")
    if pu:
        out.append(f"- projection uncertainty: median {sigma_px_text(pu.get('median_px'))}, worst {sigma_px_text(pu.get('worst_px'))}")
    cv = calib.get("cross_validation")
    for pair in (cv or {}).get("pairs", []):
        a, b = pair["groups"]
        pred = pair.get("predicted_median_px")
        out.append(f"- cross-validation, groups {a} and {b}: difference median {sigma_px_text(pair.get('median_px'))} against "
                   + (f"{sigma_px_text(pred)} predicted" if pred is not None else "no prediction")
                   + f": {pair['verdict'].split(':')[0]}")
    return out
