"""Real against rendered: each photo beside the target rendered through its calibration, for `tiltfit report`.

    compare_view(calibration, view, photo_path, options) -> ViewComparison
    write_real_vs_rendered(calib, calib_path, out_dir, options) -> (files, summary)

For a view whose photo can be found, the target (CALIB.json's `target`) is rendered through the calibrated camera
of that view (`Calibration.camera`: pose, principal point, distortion about its centre, tilt, and the defocus of
U and d where the calibration determined them) under ambient light of intensity 1, with reflectance 0 for the dark
print and 1 for the paper: the rendered value r of a pixel is the share of paper in it, after the lens's blur.

Brightness model (what is fitted, per view, on the checkered area only): the photo's linear luminance
    I(x, y) ≈ a(x, y) + b(x, y) · r(x, y),
with a and b quadratic polynomials in the image position (12 numbers): the black level and dark toner (a), the
exposure times the paper's reflectance (b), both allowed to vary smoothly over the board (vignetting, uneven light,
the board's inclination to the light). Nothing about geometry or blur is fitted: a misplaced board, a wrong
distortion or a wrong blur width stays in the difference. The fit is robust: pixels off by more than
`CLIP_SIGMA` robust σ (glare, dust, a finger) are left out and the fit repeated.

Measures (the tilt-lens paper's Table 2, `tiltfit.photometric.profiles`): brightness profiles of photo and rendering along
lines across the board — the middle row of squares, the middle column and a diagonal, each drawn on the target
and projected through the calibration, so it follows the board's rows through the distortion — read on 0–255 sRGB
grey levels, and their average error (mean absolute difference); and the RMS of photo − rendered over the
checkered area.

Resolution: the comparison runs at the photo's resolution divided by an integer factor (the photo area-averaged,
the rendering made at that size: the same pixels, coarser) so that its width is at most `max_width_px`;
`--scale 1` compares at full resolution.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

import numpy as np

#: Samples per pixel of the renderings (Sobol over the pixel and the aperture). Render noise adds to |photo −
#: rendered|: against spp 32 on both shipped sets a line's average error moves by a median 0.10 (max 0.42) grey
#: level at 8, 0.31 (0.78) at 4, in half the time of 32 (benchmarks/results/real_vs_rendered.md).
DEFAULT_SPP = 8
#: The most samples per pixel `tiltfit report` renders with: far beyond where render noise stops mattering (spp 8
#: is within a median 0.1 grey level of spp 32) and still bounded in time and memory (1e9 tried to allocate 32 GB).
MAX_SPP = 1024
#: Default largest width (px) of the compared images: 1280-px photos are compared at half resolution.
DEFAULT_MAX_WIDTH_PX = 640
#: Views compared by default, spread evenly over the calibration's views.
DEFAULT_MAX_VIEWS = 6
#: Pixels whose brightness-fit residual exceeds this many robust σ are left out of the fit (glare, dust).
CLIP_SIGMA = 3.0
#: Samples drawn along each profile line on the target before projecting it (a polyline through the distortion).
LINE_VERTICES = 200
#: Profiles shorter than this (px, compared image) are not drawn: the line left the image.
MIN_LINE_PX = 20.0
#: The profile lines drawn on every view, and their colours.
LINE_NAMES = ("row", "column", "diagonal")
LINE_COLOURS = {"row": "tab:red", "column": "tab:green", "diagonal": "tab:blue"}


class RealVsRenderedError(ValueError):
    """A comparison that cannot run (no target, a photo of another size); the message names the file."""


@dataclass(frozen=True)
class RealVsRenderedOptions:
    """How `write_real_vs_rendered` picks views and renders them.

    Attributes:
        views: view indices to compare (None: `max_views` spread evenly over the views).
        max_views: views compared when `views` is None [DEFAULT_MAX_VIEWS]; 0 turns the page off.
        photos_dirs: folders where a view's photo is looked for by name when its stored path is not there.
        spp: samples per pixel of the renderings [DEFAULT_SPP].
        scale: integer factor the photo's resolution is divided by (None: the smallest that brings the width
            to at most `max_width_px` and divides both sides).
        max_width_px: see `scale` [DEFAULT_MAX_WIDTH_PX].
        encoding: the photos' encoding (`srgb`, `linear`; None: as the file says, 8-bit is sRGB).
        say: progress callback (a str each step), or None.
    """

    views: tuple | None = None
    max_views: int = DEFAULT_MAX_VIEWS
    photos_dirs: tuple = ()
    spp: int = DEFAULT_SPP
    scale: int | None = None
    max_width_px: int = DEFAULT_MAX_WIDTH_PX
    encoding: str | None = None
    say: object = field(default=None, repr=False, compare=False)


@dataclass
class ViewComparison:
    """One view compared (planes are (H, W) at the compared resolution).

    Attributes:
        view: index; image: the view's stored image name; photo_path: the file read.
        photo_grey, rendered_grey: 0–255 sRGB grey levels (unquantised) of the photo's luminance and of the fitted
            rendering a + b · r.
        board: (H, W) bool, the checkered area; fit_mask: the pixels the brightness fit kept.
        lines: {name: (K, 2) polyline px}; rows: `tiltfit.photometric.profiles.compare_profiles` rows; profiles: its profiles.
        rms_board: RMS of photo − rendered over the checkered area, grey levels.
        scale: the resolution factor; spp; render_s: rendering time (s); window: (x0, y0, w, h) rendered.
    """

    view: int
    image: str
    photo_path: str
    photo_grey: np.ndarray
    rendered_grey: np.ndarray
    board: np.ndarray
    fit_mask: np.ndarray
    lines: dict
    rows: list
    profiles: dict
    rms_board: float
    scale: int
    spp: int
    render_s: float
    window: tuple = (0, 0, 0, 0)
    notes: list = field(default_factory=list)

    @property
    def profile_error(self) -> float:
        """Mean over the lines of their average error (grey levels)."""
        return float(np.mean([r["average_error"] for r in self.rows])) if self.rows else math.nan

    def summary(self) -> dict:
        return {"view": self.view, "image": self.image, "photo": self.photo_path,
                "profile_error": self.profile_error,
                "profile_errors": {r["line"]: r["average_error"] for r in self.rows},
                "profile_bias": {r["line"]: r["bias"] for r in self.rows},
                "rms_board": self.rms_board, "board_pixels": int(self.board.sum()),
                "fit_pixels": int(self.fit_mask.sum()), "scale": self.scale, "spp": self.spp,
                "render_s": self.render_s, "notes": list(self.notes)}


# ------------------------------------------------------------------------------------------------ finding photos

def find_photo(image: str, calib_path: str | None, photos_dirs=()) -> str | None:
    """The file of a view's stored `image`: as stored (absolute, or relative to the working folder), relative to
    the calibration file's folder, then by its name (and its relative path) in each of `photos_dirs`."""
    if not image:
        return None
    image = os.path.expanduser(str(image))
    candidates = [image]
    if calib_path and not os.path.isabs(image):
        candidates.append(os.path.join(os.path.dirname(os.path.abspath(calib_path)), image))
    for folder in photos_dirs or ():
        if not os.path.isabs(image):
            candidates.append(os.path.join(folder, image))
        candidates.append(os.path.join(folder, os.path.basename(image)))
    return next((c for c in candidates if os.path.isfile(c)), None)


def pick_views(n_views: int, options: RealVsRenderedOptions) -> list[int]:
    """The view indices to compare: `options.views` (checked), else `max_views` spread evenly."""
    if options.views is not None:
        bad = [v for v in options.views if not -n_views <= int(v) < n_views]
        if bad:
            raise RealVsRenderedError(f"views: view {bad[0]} does not exist (the calibration has {n_views} "
                                      f"views: 0 to {n_views - 1})")
        return sorted({int(v) % n_views for v in options.views})
    m = min(int(options.max_views), n_views)
    if m <= 0:
        return []
    return sorted({int(round(i)) for i in np.linspace(0, n_views - 1, m)})


def comparison_scale(size_px, options: RealVsRenderedOptions) -> int:
    """The integer factor the photo's resolution is divided by (`RealVsRenderedOptions.scale`)."""
    W, H = (int(v) for v in size_px)
    if options.scale is not None:
        k = int(options.scale)
        if k < 1 or W % k or H % k:
            raise RealVsRenderedError(f"scale: {k} does not divide the {W}x{H} image into whole pixels")
        return k
    divisors = [k for k in range(1, 17) if W % k == 0 and H % k == 0]
    fitting = [k for k in divisors if W / k <= options.max_width_px]
    return fitting[0] if fitting else divisors[-1]


# ------------------------------------------------------------------------------------------------ geometry

def _project(calibration, points_mm: np.ndarray, view: int, k: int) -> np.ndarray:
    """(N, 2) px positions in the image divided by k (pixel centres at integers)."""
    xy = calibration.project(points_mm, view)
    return (xy + 0.5) / k - 0.5


def _rectangle(x0: float, y0: float, x1: float, y1: float, n: int = 64) -> np.ndarray:
    """(4 n + 1, 3) points along a closed rectangle on the target plane Z = 0 (mm), n a side."""
    t = np.linspace(0.0, 1.0, n, endpoint=False)
    xy = np.concatenate([np.stack([x0 + (x1 - x0) * t, np.full_like(t, y0)], 1),
                         np.stack([np.full_like(t, x1), y0 + (y1 - y0) * t], 1),
                         np.stack([x1 - (x1 - x0) * t, np.full_like(t, y1)], 1),
                         np.stack([np.full_like(t, x0), y1 - (y1 - y0) * t], 1), [[x0, y0]]])
    return np.c_[xy, np.zeros(len(xy))]


def board_outlines(calibration, target, view: int, k: int = 1) -> dict:
    """{"checkered": (K, 2), "board": (K, 2)} closed polylines (px, image divided by k) of the checkered area's
    outline and of the board's outer edge (its margin's), projected through the lens (distortion bends them)."""
    xe, ye = target.x_edges, target.y_edges
    out = {}
    for name, rect in (("checkered", (xe[0], ye[0], xe[-1], ye[-1])), ("board", target.extent_mm)):
        xy = _project(calibration, _rectangle(*(float(v) for v in rect)), view, k)
        out[name] = xy[np.isfinite(xy).all(1)]
    return out


def board_mask(calibration, target, view: int, k: int, size_px) -> np.ndarray:
    """(H, W) bool: pixels whose centre lies inside the checkered area's outline, projected through the lens."""
    import cv2

    x0, x1 = float(target.x_edges[0]), float(target.x_edges[-1])
    y0, y1 = float(target.y_edges[0]), float(target.y_edges[-1])
    t = np.linspace(0.0, 1.0, 64, endpoint=False)
    outline = np.concatenate([
        np.stack([x0 + (x1 - x0) * t, np.full_like(t, y0)], 1), np.stack([np.full_like(t, x1), y0 + (y1 - y0) * t], 1),
        np.stack([x1 - (x1 - x0) * t, np.full_like(t, y1)], 1), np.stack([np.full_like(t, x0), y1 - (y1 - y0) * t], 1)])
    xy = _project(calibration, np.c_[outline, np.zeros(len(outline))], view, k)
    W, H = size_px
    mask = np.zeros((H, W), np.uint8)
    if np.isfinite(xy).all():
        cv2.fillPoly(mask, [np.round(xy * 16).astype(np.int32)], 1, lineType=cv2.LINE_8, shift=4)
    return mask.astype(bool)


def profile_lines(calibration, target, view: int, k: int, size_px) -> dict:
    """{name: (K, 2) polyline px}: the middle row of squares, the middle column and a diagonal of the checkered
    area, drawn on the target and projected; each cut to its longest stretch inside the image's pixel centres
    (lines shorter than MIN_LINE_PX are left out)."""
    xe, ye = np.asarray(target.x_edges, float), np.asarray(target.y_edges, float)
    xm = 0.5 * (xe[len(xe) // 2 - 1] + xe[len(xe) // 2]) if len(xe) > 2 else 0.5 * (xe[0] + xe[-1])
    ym = 0.5 * (ye[len(ye) // 2 - 1] + ye[len(ye) // 2]) if len(ye) > 2 else 0.5 * (ye[0] + ye[-1])
    t = np.linspace(0.0, 1.0, LINE_VERTICES)
    # The diagonal is kept a quarter of a square off the corners' diagonal so that it does not run through corners.
    dy = 0.25 * float(np.min(np.diff(ye)))
    on_target = {
        "row": np.stack([xe[0] + (xe[-1] - xe[0]) * t, np.full_like(t, ym)], 1),
        "column": np.stack([np.full_like(t, xm), ye[0] + (ye[-1] - ye[0]) * t], 1),
        "diagonal": np.stack([xe[0] + (xe[-1] - xe[0]) * t, ye[0] + dy + (ye[-1] - ye[0] - 2 * dy) * t], 1),
    }
    W, H = size_px
    lines = {}
    for name, pts in on_target.items():
        xy = _project(calibration, np.c_[pts, np.zeros(len(pts))], view, k)
        inside = np.isfinite(xy).all(1) & (xy[:, 0] >= 0) & (xy[:, 0] <= W - 1) & (xy[:, 1] >= 0) & (xy[:, 1] <= H - 1)
        best, start = (0, 0), None
        for i, ok in enumerate(np.r_[inside, False]):
            if ok and start is None:
                start = i
            elif not ok and start is not None:
                best = max(best, (start, i), key=lambda r: r[1] - r[0])
                start = None
        seg = xy[best[0]:best[1]]
        if len(seg) >= 2 and np.linalg.norm(np.diff(seg, axis=0), axis=1).sum() >= MIN_LINE_PX:
            lines[name] = seg
    return lines


# ------------------------------------------------------------------------------------------------ rendering

def board_window(calibration, target, view: int, k: int, size_px, pad_px: int = 4) -> tuple[int, int, int, int]:
    """(x0, y0, width, height): the pixels of the compared image that the board with its margin covers (its
    outline projected through the lens, `pad_px` more on each side, cut to the image)."""
    x0, y0, x1, y1 = target.extent_mm
    t = np.linspace(0.0, 1.0, 64)
    outline = np.concatenate([np.stack([x0 + (x1 - x0) * t, np.full_like(t, y)], 1) for y in (y0, y1)]
                             + [np.stack([np.full_like(t, x), y0 + (y1 - y0) * t], 1) for x in (x0, x1)])
    xy = _project(calibration, np.c_[outline, np.zeros(len(outline))], view, k)
    W, H = size_px
    xy = xy[np.isfinite(xy).all(1)]
    if not len(xy):
        return 0, 0, W, H
    lo = np.clip(np.floor(xy.min(0)) - pad_px, 0, [W, H]).astype(int)
    hi = np.clip(np.ceil(xy.max(0)) + pad_px + 1, 0, [W, H]).astype(int)
    return int(lo[0]), int(lo[1]), int(max(hi[0] - lo[0], 0)), int(max(hi[1] - lo[1], 0))


def render_print(calibration, target, view: int, size_px, spp: int, window=None) -> np.ndarray:
    """(H, W) share of paper seen by each pixel of a view (dark print 0, paper 1, background 0), rendered by the
    renderer through the calibrated camera under ambient light 1, at `size_px` (the calibration's aspect).

    window: (x0, y0, width, height) — only these pixels are rendered (`renderer.Lens.cropped`), the rest is 0.
    """
    import torch

    import renderer
    from renderer.cameras import ThinLensCamera

    from tiltfit.report.composite import board_scene

    W, H = (int(v) for v in size_px)
    x0, y0, w, h = window or (0, 0, W, H)
    out = np.zeros((H, W))
    if w < 1 or h < 1:
        return out
    R, T = calibration.pose(view)
    lens = calibration.lens_for_image((W, H)).cropped(x0, y0, w, h)
    camera = ThinLensCamera.from_calibration(lens, torch.as_tensor(R), torch.as_tensor(T))
    result = renderer.render(board_scene(target, camera, reflectance=(0.0, 1.0)), spp=spp, progress=False)
    out[y0:y0 + h, x0:x0 + w] = result.image.detach().cpu().numpy().astype(np.float64)[..., 0]
    return out


# ------------------------------------------------------------------------------------------------ brightness fit

def _design(mask: np.ndarray, r: np.ndarray) -> np.ndarray:
    """(N, 12) design matrix of I = a(x, y) + b(x, y) · r, a and b quadratic, over the pixels of `mask`."""
    H, W = mask.shape
    y, x = np.nonzero(mask)
    u, v = (x - 0.5 * (W - 1)) / W, (y - 0.5 * (H - 1)) / W
    q = np.stack([np.ones_like(u), u, v, u * u, u * v, v * v], 1)
    return np.concatenate([q, q * r[mask][:, None]], 1)


def fit_brightness(photo: np.ndarray, r: np.ndarray, board: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rendering as the photo would show it: a(x, y) + b(x, y) · r fitted to the photo's linear luminance over
    `board` (module docstring), robustly. Returns the (H, W) model over the whole image and the fit's mask."""
    from tiltfit.solve.robust_linear import clipped_lstsq

    ok = board & np.isfinite(photo)
    full = _design(np.ones_like(board), r)
    A = _design(ok, r)
    coef, kept = clipped_lstsq(A, photo[ok], CLIP_SIGMA, iterations=3, min_rows=3 * A.shape[1], sigma_floor=1e-6)
    if coef is None:
        raise RealVsRenderedError(f"the board covers {int(ok.sum())} pixels: too few for the brightness fit")
    keep = np.zeros_like(board)
    keep[ok] = kept
    return (full @ coef).reshape(board.shape), keep


def _luminance(photo: np.ndarray) -> np.ndarray:
    from tiltfit.photometric.profiles import select_channel

    return select_channel(photo, "luma")


def _downscale(plane: np.ndarray, k: int) -> np.ndarray:
    if k == 1:
        return plane
    H, W = plane.shape
    return plane.reshape(H // k, k, W // k, k).mean(axis=(1, 3))


def compare_view(calibration, target, view: int, photo_path: str, options: RealVsRenderedOptions,
                 photo: np.ndarray | None = None) -> ViewComparison:
    """Render one view, fit its brightness and compare it with the photo (module docstring).

    Args:
        calibration: `tiltfit.files.calibrated.Calibration`; target: its `tiltfit.target.layout.Target`.
        photo: the photo as linear float (H, W[, C]); read from `photo_path` when None.
    """
    import time

    from camio.files import read_image

    from tiltfit.photometric.profiles import compare_profiles, grey_levels

    if photo is None:
        photo = read_image(photo_path, options.encoding)
    lum = _luminance(photo)
    W0, H0 = calibration.image_size_px
    if lum.shape != (H0, W0):
        raise RealVsRenderedError(f"{photo_path}: a {lum.shape[1]}x{lum.shape[0]} photo; the calibration's images "
                                  f"are {W0}x{H0}")
    k = comparison_scale((W0, H0), options)
    size = (W0 // k, H0 // k)
    lum = _downscale(lum, k)
    t = time.perf_counter()
    window = board_window(calibration, target, view, k, size)
    r = render_print(calibration, target, view, size, options.spp, window)
    render_s = time.perf_counter() - t
    board = board_mask(calibration, target, view, k, size)
    notes = []
    if not board.any():
        raise RealVsRenderedError(f"{photo_path}: the board, placed by the calibration, is outside the image")
    model, keep = fit_brightness(lum, r, board)
    photo_grey = grey_levels(lum, quantize=False)
    rendered_grey = grey_levels(np.clip(model, 0.0, 1.0), quantize=False)
    lines = profile_lines(calibration, target, view, k, size)
    rows, profiles = (compare_profiles(photo_grey, rendered_grey, lines, to_grey_levels=False) if lines else ([], {}))
    diff = (photo_grey - rendered_grey)[board]
    if not calibration.blur_known:
        notes.append("U, d undetermined: rendered sharp")
    board_model = (calibration.data.get("board") or {}).get("model", "flat")
    if board_model != "flat":
        notes.append(f"board rendered flat (the calibration fitted a {board_model} one)")
    if k > 1:
        notes.append(f"compared at 1/{k} resolution ({size[0]}x{size[1]})")
    return ViewComparison(view, str(calibration.views[view].get("image", "")), photo_path, photo_grey, rendered_grey,
                          board, keep, lines, rows, profiles, float(np.sqrt(np.mean(diff ** 2))), k, options.spp,
                          render_s, window, notes)


# ------------------------------------------------------------------------------------------------ figures

def view_figure(cmp: ViewComparison, title: str):
    """photo | rendered | difference (cut to the board), and under them each line's profiles, real and rendered."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    H, W = cmp.photo_grey.shape
    x0, y0, w, h = cmp.window if cmp.window[2] and cmp.window[3] else (0, 0, W, H)
    m = int(round(0.03 * max(w, h)))
    x0, y0, x1, y1 = max(x0 - m, 0), max(y0 - m, 0), min(x0 + w + m, W), min(y0 + h + m, H)
    panel_h = 14.0 / 3 * (y1 - y0) / (x1 - x0)
    fig = plt.figure(figsize=(14.0, panel_h + 3.6))
    grid = fig.add_gridspec(2, 3, height_ratios=[panel_h, 2.9], hspace=0.22, wspace=0.12, left=0.05, right=0.97,
                            top=1 - 0.75 / (panel_h + 3.6), bottom=0.45 / (panel_h + 3.6))
    extent = (x0 - 0.5, x1 - 0.5, y1 - 0.5, y0 - 0.5)
    shown = {"photo": cmp.photo_grey, "rendered through the calibration, brightness fitted": cmp.rendered_grey}
    for j, (label, img) in enumerate(shown.items()):
        ax = fig.add_subplot(grid[0, j])
        ax.imshow(np.clip(img[y0:y1, x0:x1], 0, 255), cmap="gray", vmin=0, vmax=255, interpolation="nearest",
                  extent=extent)
        for name, line in cmp.lines.items():
            ax.plot(line[:, 0], line[:, 1], color=LINE_COLOURS[name], lw=1.3)
        ax.set_title(label, fontsize=9)
        ax.set_axis_off()
    diff = np.where(cmp.board, cmp.photo_grey - cmp.rendered_grey, np.nan)[y0:y1, x0:x1]
    lim = max(float(np.nanpercentile(np.abs(diff), 99)) if np.isfinite(diff).any() else 1.0, 1.0)
    ax = fig.add_subplot(grid[0, 2])
    ax.imshow(cmp.photo_grey[y0:y1, x0:x1], cmap="gray", vmin=-255, vmax=255 * 2, interpolation="nearest",
              extent=extent)  # faint context around the checkered area
    im = ax.imshow(diff, cmap="RdBu_r", vmin=-lim, vmax=lim, interpolation="nearest", extent=extent)
    ax.set_title(f"photo − rendered (red: photo brighter); RMS {cmp.rms_board:.1f}", fontsize=9)
    ax.set_axis_off()
    fig.colorbar(im, ax=ax, shrink=0.85, pad=0.02, label="grey levels")
    fig.suptitle(title, fontsize=10, y=1 - 0.08 / (panel_h + 3.6))
    for j, name in enumerate(LINE_NAMES):
        ax = fig.add_subplot(grid[1, j])
        row = next((r for r in cmp.rows if r["line"] == name), None)
        if row is None:
            ax.text(0.5, 0.5, f"the {name} line leaves the image", ha="center", va="center", transform=ax.transAxes)
            ax.set_axis_off()
            continue
        real, rend = cmp.profiles[name]
        colour = LINE_COLOURS[name]
        ax.plot(real.s_px, real.values, color="k", lw=1.0, label="photo")
        ax.plot(rend.s_px, rend.values, color=colour, lw=1.1, ls="--", label="rendered")
        ax.fill_between(real.s_px, real.values, rend.values, color=colour, alpha=0.25, lw=0)
        ax.set_title(f"{name} ({colour.split(':')[1]} line): average error {row['average_error']:.1f}, "
                     f"bias {row['bias']:+.1f}", fontsize=9)
        ax.set_xlabel("position along the line (px)", fontsize=8)
        ax.set_ylim(0, 262)
        ax.tick_params(labelsize=8)
        ax.grid(alpha=0.3)
        if j == 0:
            ax.set_ylabel("brightness (grey level)", fontsize=8)
            ax.legend(fontsize=8, loc="lower left", framealpha=0.9)
    return fig


def summary_figure(comparisons: list, names: list):
    """Per view: each line's average error and the RMS over the checkered area."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(comparisons)
    fig, ax = plt.subplots(figsize=(max(6.0, 0.9 * n + 2.5), 3.4), layout="constrained")
    width = 0.8 / (len(LINE_NAMES) + 1)
    x = np.arange(n)
    for j, name in enumerate(LINE_NAMES):
        vals = [next((r["average_error"] for r in c.rows if r["line"] == name), np.nan) for c in comparisons]
        ax.bar(x + (j - 1.5) * width, vals, width, color=LINE_COLOURS[name], label=f"{name} profile, average error")
    ax.bar(x + 1.5 * width, [c.rms_board for c in comparisons], width, color="0.5", label="RMS over the board")
    ax.set_xticks(x, names, rotation=30, ha="right", fontsize=8)
    ax.set_ylabel("grey levels (0–255)")
    ax.set_title("Photo against the target rendered through the calibration, per view", fontsize=10)
    ax.legend(fontsize=7, ncols=2)
    ax.grid(axis="y", alpha=0.3)
    return fig


# ------------------------------------------------------------------------------------------------ the page

def write_real_vs_rendered(calib: dict, calib_path: str | None, out_dir: str,
                           options: RealVsRenderedOptions | None = None) -> tuple[list, dict]:
    """Compare the chosen views' photos with renderings (module docstring) and write into `out_dir`:
    `real_vs_rendered/view_KK.png` per view, `real_vs_rendered.png` (summary) and `real_vs_rendered.json`.

    Returns:
        (the names written, relative to out_dir; the summary dict, also in the JSON), ([], summary with the
        reason) where nothing could be compared.
    """
    import json

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from tiltfit.files.calibrated import Calibration

    options = options or RealVsRenderedOptions()
    say = options.say or (lambda text: None)
    cal = Calibration.from_dict(calib, calib_path or "<calibration>")
    summary = {"spp": options.spp, "fit": "photo luminance = a(x, y) + b(x, y) * rendered share of paper; a, b "
                                          "quadratic in the image position; robust, on the checkered area",
               "measure": "grey levels 0-255 of the sRGB luminance; profile error = mean |photo - rendered| along "
                          "the line (the tilt-lens paper's Table 2)", "views": [], "skipped": []}
    target = cal.target
    if target is None:
        summary["reason"] = "the calibration holds no target (CALIB.json `target`), so there is nothing to render"
        return [], summary
    if getattr(target, "type", "checkerboard") != "checkerboard":
        summary["note"] = "ChArUco markers are drawn; the profiles run through them as well"
    chosen = pick_views(len(cal.views), options)
    files, comparisons, names = [], [], []
    for n, v in enumerate(chosen):
        image = str(cal.views[v].get("image", ""))
        path = find_photo(image, calib_path, options.photos_dirs)
        if path is None:
            summary["skipped"].append({"view": v, "image": image, "reason": "photo not found"
                                       + ("" if options.photos_dirs else " (give the folder of the photos)")})
            say(f"real vs rendered: view {v} ({os.path.basename(image)}): photo not found, skipped")
            continue
        say(f"real vs rendered: view {v} ({os.path.basename(image)}), {n + 1} of {len(chosen)}: rendering")
        try:
            cmp = compare_view(cal, target, v, path, options)
        except (RealVsRenderedError, OSError) as e:
            summary["skipped"].append({"view": v, "image": image, "reason": str(e)})
            say(f"real vs rendered: view {v}: skipped ({e})")
            continue
        except ValueError as e:  # an unreadable photo (camio.files.ImageIOError)
            summary["skipped"].append({"view": v, "image": image, "reason": str(e)})
            say(f"real vs rendered: view {v}: skipped ({e})")
            continue
        os.makedirs(os.path.join(out_dir, "real_vs_rendered"), exist_ok=True)
        name = os.path.join("real_vs_rendered", f"view_{v:02d}.png")
        fig = view_figure(cmp, f"view {v}: {os.path.basename(image)} — profile error {cmp.profile_error:.1f} grey "
                               f"levels" + ("\n" + "; ".join(cmp.notes) if cmp.notes else ""))
        try:
            fig.savefig(os.path.join(out_dir, name), dpi=90)
        finally:
            plt.close(fig)
        files.append(name)
        comparisons.append(cmp)
        names.append(f"{v}: {_short(os.path.basename(image))}")
        summary["views"].append(cmp.summary())
        say(f"real vs rendered: view {v}: profile error {cmp.profile_error:.2f} grey levels, RMS over the board "
            f"{cmp.rms_board:.2f} ({cmp.render_s:.1f} s to render)")
    if comparisons:
        errs = [c.profile_error for c in comparisons]
        summary["median_profile_error"] = float(np.median(errs))
        summary["median_rms_board"] = float(np.median([c.rms_board for c in comparisons]))
        fig = summary_figure(comparisons, names)
        try:
            fig.savefig(os.path.join(out_dir, "real_vs_rendered.png"), dpi=110)
        finally:
            plt.close(fig)
        files.append("real_vs_rendered.png")
    with open(os.path.join(out_dir, "real_vs_rendered.json"), "w", encoding="utf-8") as f:
        json.dump(summary, f, indent=1)
    files.append("real_vs_rendered.json")
    return files, summary


def markdown_lines(summary: dict) -> list:
    """report.md lines: the real-against-rendered table."""
    out = ["", "## Real against rendered", ""]
    if summary.get("reason"):
        return out + [f"- not drawn: {summary['reason']}"]
    out.append(f"- each photo beside the target rendered through the calibration (spp {summary['spp']}); "
               f"brightness fitted per view: {summary['fit']}; measure: {summary['measure']}")
    if summary.get("views"):
        out.append(f"- median over the views: profile error {summary['median_profile_error']:.2f}, RMS over the "
                   f"board {summary['median_rms_board']:.2f} grey levels (figures: real_vs_rendered/)")
        out += ["", "| view | image | row | column | diagonal | profile error | RMS over the board | notes |",
                "|---|---|---|---|---|---|---|---|"]
        for v in summary["views"]:
            e = v["profile_errors"]
            cells = [f"{e[n]:.2f}" if n in e else "" for n in LINE_NAMES]
            out.append(f"| {v['view']} | {os.path.basename(v['image'])} | " + " | ".join(cells)
                       + f" | {v['profile_error']:.2f} | {v['rms_board']:.2f} | {'; '.join(v['notes'])} |")
    for s in summary.get("skipped") or []:
        out.append(f"- view {s['view']} ({os.path.basename(s['image'])}) not compared: {s['reason']}")
    return out


def _short(name: str, n: int = 18) -> str:
    return name if len(name) <= n else name[: n // 2 - 1] + "…" + name[-(n - n // 2):]
