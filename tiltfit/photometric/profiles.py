"""Compare a photograph with a rendering: brightness profiles along lines, error metrics, tables, plots.

Works on any pair of images of the same size, real or rendered. The comparison follows the tilt-lens
paper (Baba, Nakane, Hiura, IPSJ 2017, §4.2.3, Figs. 13–15, Table 2): the brightness of the photo and of
the CG image is read along a line drawn on the image (a red and a green line in the paper), the two
profiles are plotted against each other, and the mean brightness error per line is tabulated.

Brightness scale. Images in memory are linear float RGB (`renderer.read_image`, `renderer.render`); the
paper compares the 8-bit sRGB images a camera writes. `grey_levels` converts to that scale: sRGB-encode,
×255, round to integers like an 8-bit file (uint8 input is taken as already encoded). Profiles are then
read on the grey levels, so the metrics are in 0–255 grey levels as in the paper's Table 2.

Pixels: float (x = column, y = row); (0, 0) is the centre of the top-left pixel. A polyline must stay
between the outermost pixel centres, where bilinear interpolation is defined without padding.
"""
from __future__ import annotations

import csv
import io
import math
import numbers
import os
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from camio.files import linear_to_srgb, write_text
from renderer.cameras.sensor import decode_srgb8

# ITU-R BT.601 luma weights, as OpenCV's RGB->grey conversion (the usual "brightness" of an 8-bit photo).
LUMA_WEIGHTS = (0.299, 0.587, 0.114)


class EvaluationError(ValueError):
    """Bad input to a comparison (image shape, polyline, channel, step); the message names the argument."""


@dataclass(frozen=True)
class Profile:
    """Values sampled along a polyline.

    Attributes:
        s_px: (N,) arc length from the polyline's first vertex, pixels.
        xy_px: (N, 2) sample positions (x = column, y = row), pixels.
        values: (N,) sampled values, in the image's units (grey levels after `grey_levels`).
    """

    s_px: np.ndarray
    xy_px: np.ndarray
    values: np.ndarray

    def to_dict(self) -> dict:
        return {"s_px": self.s_px.tolist(), "xy_px": self.xy_px.tolist(), "values": self.values.tolist()}


def _as_array(image, name: str) -> np.ndarray:
    if isinstance(image, torch.Tensor):
        image = image.detach().cpu().numpy()
    arr = np.asarray(image)
    if arr.ndim not in (2, 3) or arr.shape[0] < 2 or arr.shape[1] < 2:
        raise EvaluationError(f"{name}: expected an (H, W) or (H, W, C) image with H, W >= 2, got shape "
                              f"{tuple(arr.shape)}")
    if not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating):
        raise EvaluationError(f"{name}: expected a real-valued image, got dtype {arr.dtype}")
    return arr


def grey_levels(image, quantize: bool = True) -> np.ndarray:
    """The 0–255 grey levels an 8-bit sRGB file of the image holds (the paper's brightness scale).

    Args:
        image: (H, W) or (H, W, C) linear float image (as `renderer.read_image` / `render` return), or a
            uint8 array, taken as already sRGB-encoded.
        quantize: round to integers like an 8-bit file [True].
    Returns:
        (H, W[, C]) float64 array in [0, 255].
    """
    if isinstance(image, torch.Tensor):
        image = image.detach().cpu().numpy()
    arr = np.asarray(image)
    if arr.dtype == np.uint8:
        return arr.astype(np.float64)
    if not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating):
        raise EvaluationError(f"image: expected real values, got dtype {arr.dtype}")
    out = linear_to_srgb(np.clip(arr.astype(np.float64), 0.0, 1.0)) * 255.0
    return np.round(out) if quantize else out


def linear_from_grey_levels(levels) -> np.ndarray:
    """Inverse of `grey_levels`: 0–255 sRGB grey levels (uint8 or float) to linear float64 in [0, 1]."""
    return decode_srgb8(levels)


def select_channel(image, channel: str | int = "luma") -> np.ndarray:
    """(H, W) plane of an image: `luma` (BT.601 weights of R, G, B; the image itself if it has one
    channel) or a channel index."""
    arr = _as_array(image, "image").astype(np.float64)
    if arr.ndim == 2:
        arr = arr[..., None]
    n = arr.shape[2]
    if channel == "luma":
        if n == 1:
            return arr[..., 0]
        if n < 3:
            raise EvaluationError(f"channel: 'luma' needs 1 or >= 3 channels, the image has {n}")
        return arr[..., :3] @ np.asarray(LUMA_WEIGHTS)
    if isinstance(channel, (int, np.integer)) and not isinstance(channel, bool):
        if not 0 <= channel < n:
            raise EvaluationError(f"channel: expected 'luma' or an index in [0, {n - 1}], got {channel}")
        return arr[..., int(channel)]
    raise EvaluationError(f"channel: expected 'luma' or an integer index, got {channel!r}")


def check_polyline(polyline_px, width: int, height: int, name: str = "polyline_px") -> np.ndarray:
    """Validate a polyline: (K, 2) finite vertices, K >= 2, positive length, inside the pixel centres.

    Returns:
        (K, 2) float64 vertices (x, y), pixels.
    """
    p = np.asarray(polyline_px, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2 or p.shape[0] < 2:
        raise EvaluationError(f"{name}: expected (K, 2) vertices with K >= 2, got shape {tuple(p.shape)}")
    if not np.all(np.isfinite(p)):
        raise EvaluationError(f"{name}: vertices must be finite, got {p.tolist()}")
    tol = 1e-9
    bad = (p[:, 0] < -tol) | (p[:, 0] > width - 1 + tol) | (p[:, 1] < -tol) | (p[:, 1] > height - 1 + tol)
    if bad.any():
        v = p[np.argmax(bad)].tolist()
        raise EvaluationError(f"{name}: vertex {v} lies outside the pixel centres of a {width}x{height} image "
                              f"(x in [0, {width - 1}], y in [0, {height - 1}])")
    if np.linalg.norm(np.diff(p, axis=0), axis=1).sum() <= 0:
        raise EvaluationError(f"{name}: the polyline has zero length")
    return p


def polyline_samples(polyline_px, step_px: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Points every `step_px` of arc length along a polyline, starting at its first vertex.

    Samples sit at s = 0, step, 2·step, … ≤ L (L the total length); the last vertex is included when L is
    a multiple of the step. Zero-length segments are skipped.
    Returns:
        s_px (N,), xy_px (N, 2).
    """
    if isinstance(step_px, bool) or not (isinstance(step_px, numbers.Real) and math.isfinite(step_px) and step_px > 0):
        raise EvaluationError(f"step_px: expected a positive number of pixels, got {step_px!r}")
    p = np.asarray(polyline_px, dtype=np.float64)
    p = p[np.r_[True, np.linalg.norm(np.diff(p, axis=0), axis=1) > 0]]  # drop repeated vertices
    if p.shape[0] < 2:
        raise EvaluationError("polyline_px: the polyline has zero length")
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    n = int(math.floor(cum[-1] / step_px + 1e-9)) + 1
    s = np.arange(n) * step_px
    k = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
    t = np.clip((s - cum[k]) / seg[k], 0.0, 1.0)
    xy = p[k] + t[:, None] * (p[k + 1] - p[k])
    return s, xy


def sample_bilinear(plane: np.ndarray, xy_px: np.ndarray) -> np.ndarray:
    """Bilinear interpolation of an (H, W) plane at (N, 2) pixel positions (float64, grid_sample).

    (0, 0) is the centre of the top-left pixel, so `align_corners=True` maps −1 and +1 to the centres of the
    outer pixels: x_norm = 2x/(W − 1) − 1.
    """
    h, w = plane.shape
    img = torch.as_tensor(np.ascontiguousarray(plane), dtype=torch.float64)[None, None]
    xy = torch.as_tensor(xy_px, dtype=torch.float64)
    grid = torch.stack([2 * xy[:, 0] / (w - 1) - 1, 2 * xy[:, 1] / (h - 1) - 1], -1)[None, None]
    out = F.grid_sample(img, grid, mode="bilinear", padding_mode="border", align_corners=True)
    return out[0, 0, 0].numpy()


def profile(image, polyline_px, step_px: float = 0.5, channel: str | int = "luma") -> Profile:
    """Values of an image along a polyline, with sub-pixel bilinear interpolation.

    Args:
        image: (H, W) or (H, W, C) array or tensor; sampled as given (convert with `grey_levels` first for
            the paper's 0–255 brightness).
        polyline_px: (K, 2) vertices (x = column, y = row), pixels, (0, 0) the centre of the top-left
            pixel; K >= 2 and every vertex within [0, W − 1] × [0, H − 1].
        step_px: arc-length spacing of the samples, pixels [0.5].
        channel: `luma` (BT.601 weighted R, G, B) or a channel index.
    Returns:
        Profile with arc length, positions and values.
    """
    plane = select_channel(image, channel)
    h, w = plane.shape
    p = check_polyline(polyline_px, w, h)
    s, xy = polyline_samples(p, step_px)
    return Profile(s, xy, sample_bilinear(plane, xy))


def _pair(a, b) -> tuple[np.ndarray, np.ndarray]:
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape != b.shape:
        raise EvaluationError(f"metrics: the two arrays differ in shape, {a.shape} vs {b.shape}")
    if a.size == 0:
        raise EvaluationError("metrics: empty arrays")
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        raise EvaluationError("metrics: arrays contain NaN or infinity")
    return a, b


def mean_absolute_error(a, b) -> float:
    """mean |a − b| over all elements."""
    a, b = _pair(a, b)
    return float(np.mean(np.abs(a - b)))


def rmse(a, b) -> float:
    """sqrt(mean (a − b)²) over all elements."""
    a, b = _pair(a, b)
    return float(np.sqrt(np.mean((a - b) ** 2)))


def bias(a, b) -> float:
    """mean (a − b): a brightness offset (lighting, exposure) rather than a blur mismatch."""
    a, b = _pair(a, b)
    return float(np.mean(a - b))


def average_error(real_levels, rendered_levels) -> float:
    """The paper's "average error" (平均誤差, Table 2) between two brightness profiles.

    The paper reads the brightness (明度) of the photo and of the CG image along a line and reports "the
    mean error of the brightness" per line, on the 0–255 grey levels of the 8-bit images; it gives no
    formula. We take the only reading under which errors of both signs cannot cancel: the mean absolute
    difference of the two profiles, sample by sample,
        E = (1/N) Σ_i |I_real(s_i) − I_CG(s_i)|,
    with I the BT.601 luma of the sRGB grey levels (`grey_levels`, `profile`). It equals
    `mean_absolute_error` on grey-level profiles; the separate name marks the scale it assumes.
    """
    return mean_absolute_error(real_levels, rendered_levels)


def compare_profiles(real, rendered, lines: dict, step_px: float = 0.5, channel: str | int = "luma",
                     to_grey_levels: bool = True) -> tuple[list[dict], dict]:
    """Profiles of two images along named lines and their errors (one table row per line).

    Args:
        real, rendered: images of equal size, (H, W[, C]): linear float (as read or rendered) or uint8.
        lines: {name: (K, 2) polyline in pixels}.
        step_px: sample spacing along each line, pixels.
        channel: `luma` or a channel index.
        to_grey_levels: compare 0–255 sRGB grey levels (the paper's scale) [True]; False compares the
            values as given.
    Returns:
        rows: [{line, n_samples, length_px, average_error, mae, rmse, bias, max_abs_error}] (errors in grey
            levels, bias = mean(real − rendered)), and profiles: {name: (real Profile, rendered Profile)}.
    """
    a, b = _as_array(real, "real"), _as_array(rendered, "rendered")
    if a.shape[:2] != b.shape[:2]:
        raise EvaluationError(f"rendered: image size {b.shape[1]}x{b.shape[0]} differs from the real image's "
                              f"{a.shape[1]}x{a.shape[0]}")
    if not isinstance(lines, dict) or not lines:
        raise EvaluationError(f"lines: expected a non-empty {{name: polyline}} dict, got {lines!r}")
    if to_grey_levels:
        a, b = grey_levels(a), grey_levels(b)
    rows, profiles = [], {}
    for name, line in lines.items():
        pa = profile(a, line, step_px, channel)
        pb = profile(b, line, step_px, channel)
        err = pa.values - pb.values
        rows.append({
            "line": str(name),
            "n_samples": int(len(pa.s_px)),
            "length_px": float(pa.s_px[-1]),
            "average_error": average_error(pa.values, pb.values),
            "mae": mean_absolute_error(pa.values, pb.values),
            "rmse": rmse(pa.values, pb.values),
            "bias": bias(pa.values, pb.values),
            "max_abs_error": float(np.max(np.abs(err))),
        })
        profiles[name] = (pa, pb)
    return rows, profiles


# ---------------------------------------------------------------------------------------------- tables

def _cell(v, floatfmt: str) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return "nan" if math.isnan(v) else format(v, floatfmt)
    return str(v)


def _columns(rows: list[dict], columns) -> list[str]:
    if columns is not None:
        return list(columns)
    cols: list[str] = []
    for r in rows:
        cols += [k for k in r if k not in cols]
    return cols


def markdown_table(rows: list[dict], columns=None, floatfmt: str = ".3f") -> str:
    """A Markdown table of dict rows; `columns` picks and orders keys (default: all, first-seen order)."""
    cols = _columns(rows, columns)
    if not cols:
        raise EvaluationError("rows: nothing to tabulate")
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        lines.append("| " + " | ".join(_cell(r.get(c), floatfmt).replace("|", "\\|") for c in cols) + " |")
    return "\n".join(lines) + "\n"


def csv_table(rows: list[dict], columns=None) -> str:
    """CSV text of dict rows (full float precision)."""
    cols = _columns(rows, columns)
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=cols, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    for r in rows:
        writer.writerow({c: ("" if r.get(c) is None else r.get(c)) for c in cols})
    return buf.getvalue()


def write_markdown(rows: list[dict], path: str, columns=None, title: str | None = None,
                   floatfmt: str = ".3f") -> str:
    """Write a Markdown table (with an optional `# title` line); returns the text."""
    text = (f"# {title}\n\n" if title else "") + markdown_table(rows, columns, floatfmt)
    write_text(path, text)
    return text


def write_csv(rows: list[dict], path: str, columns=None) -> str:
    """Write a CSV table; returns the text."""
    text = csv_table(rows, columns)
    write_text(path, text)
    return text


# ---------------------------------------------------------------------------------------------- plots

LINE_COLORS = {"red": "tab:red", "green": "tab:green"}


def plot_profiles(profiles: dict, title: str = "", ax=None, ylabel: str = "brightness [grey level]"):
    """Profiles against arc length, as the paper's Figs. 14/15 (photo and CG along one line).

    Args:
        profiles: {label: Profile}, e.g. {"real": p_real, "CG (calibrated)": p_cg}.
        ax: a matplotlib Axes to draw into; a new Figure is made when None.
    Returns:
        the matplotlib Figure.
    """
    from matplotlib.figure import Figure

    if ax is None:
        fig = Figure(figsize=(6.4, 3.2), layout="constrained")
        ax = fig.add_subplot()
    else:
        fig = ax.figure
    styles = ["-", "--", ":", "-."]
    for i, (label, prof) in enumerate(profiles.items()):
        ax.plot(prof.s_px, prof.values, styles[i % len(styles)], lw=1.2 if i == 0 else 1.0, label=label)
    ax.set_xlabel("position along the line [px]")
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title)
    ax.legend(fontsize="small")
    ax.grid(alpha=0.3)
    return fig


def _display(image) -> np.ndarray:
    arr = _as_array(image, "image")
    if arr.dtype == np.uint8:
        return arr
    return grey_levels(arr, quantize=True).astype(np.uint8)


def plot_images(images: dict, lines: dict | None = None, title: str = "", ncols: int | None = None):
    """Images side by side (e.g. photo and CG, as Figs. 11/12) with the profile lines drawn over them.

    Args:
        images: {label: (H, W[, 3]) linear float or uint8 image}.
        lines: optional {name: (K, 2) polyline in pixels}; `red`/`green` are drawn in those colours.
    Returns:
        the matplotlib Figure.
    """
    from matplotlib.figure import Figure

    n = len(images)
    if n == 0:
        raise EvaluationError("images: nothing to show")
    ncols = ncols or n
    nrows = -(-n // ncols)
    first = _as_array(next(iter(images.values())), "image")
    aspect = first.shape[0] / first.shape[1]
    fig = Figure(figsize=(3.6 * ncols, 3.6 * aspect * nrows + 0.5), layout="constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False).ravel()
    for ax, (label, img) in zip(axes, images.items()):
        arr = _display(img)
        ax.imshow(arr, cmap="gray" if arr.ndim == 2 else None, vmin=0, vmax=255, interpolation="nearest")
        for name, line in (lines or {}).items():
            p = np.asarray(line, dtype=np.float64)
            ax.plot(p[:, 0], p[:, 1], color=LINE_COLORS.get(name, "tab:blue"), lw=1.0)
        ax.set_title(label, fontsize="small")
        ax.set_axis_off()
    for ax in axes[n:]:
        ax.set_axis_off()
    if title:
        fig.suptitle(title)
    return fig


def save_figure(fig, path: str, dpi: int = 120) -> None:
    """Save a matplotlib Figure (PNG by extension), creating the folder."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=dpi)
