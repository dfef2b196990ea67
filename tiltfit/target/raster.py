"""Images of the board: the exact dark fraction of every pixel of a rectangle of the target plane (`rasterise`),
the board at a print resolution (`render_target`) and as a texture (`target_texture`)."""
from __future__ import annotations

import math

import numpy as np

from .layout import Target


def _cumulative_sign(edges: np.ndarray, first_sign: float, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Along one axis: (length of [e0, x] inside the checkered span, ∫ of the ±1 column sign up to x)."""
    e = np.asarray(edges, dtype=np.float64)
    signs = first_sign * (-1.0) ** np.arange(len(e) - 1)
    knots_sign = np.concatenate([[0.0], np.cumsum(signs * np.diff(e))])
    inside = np.interp(x, e, e - e[0], left=0.0, right=e[-1] - e[0])
    signed = np.interp(x, e, knots_sign, left=0.0, right=knots_sign[-1])
    return inside, signed


def rasterise(target: Target, x_range_mm, y_range_mm, width_px: int, height_px: int,
              dark: float = 0.0, white: float = 1.0) -> np.ndarray:
    """Exact area-averaged (H, W) image of the board over a rectangle of the target plane.

    Pixel (c, r) covers X in x0 + [c, c + 1]·(x1 − x0)/W and Y likewise (column = X, row = Y). The checker is
    separable in ±1 signs, so each pixel's dark fraction is (A + ε · Sx · Sy) / 2 with A the overlap of the
    pixel with the checkered area and Sx, Sy the signed overlaps along each axis.
    """
    x0, x1 = x_range_mm
    y0, y1 = y_range_mm
    bx = np.linspace(x0, x1, width_px + 1)
    by = np.linspace(y0, y1, height_px + 1)
    ax, sx = (np.diff(v) for v in _cumulative_sign(target.x_edges, 1.0, bx))
    ay, sy = (np.diff(v) for v in _cumulative_sign(target.y_edges, 1.0, by))
    eps = 1.0 if (target.dark_cell[0] + target.dark_cell[1]) % 2 == 0 else -1.0
    dark_area = 0.5 * (np.outer(ay, ax) + eps * np.outer(sy, sx))
    add_rectangles(dark_area, bx, by, target.dark_rectangles())
    dark_frac = dark_area / (np.diff(by)[:, None] * np.diff(bx)[None, :])
    return (white + (dark - white) * dark_frac).astype(np.float32)


def add_rectangles(dark_area: np.ndarray, bx: np.ndarray, by: np.ndarray, rectangles) -> None:
    """Add to `dark_area` (H, W) each rectangle's (x0, y0, x1, y1) overlap with the pixels bounded by bx (W + 1)
    and by (H + 1), ascending, mm (separable: the outer product of the overlaps along each axis)."""
    for rx0, ry0, rx1, ry1 in rectangles:
        cx = np.diff(np.clip(bx, rx0, rx1))
        cy = np.diff(np.clip(by, ry0, ry1))
        c0, c1 = max(int(np.searchsorted(bx, rx0)) - 1, 0), int(np.searchsorted(bx, rx1)) + 1
        r0, r1 = max(int(np.searchsorted(by, ry0)) - 1, 0), int(np.searchsorted(by, ry1)) + 1
        dark_area[r0:r1, c0:c1] += np.outer(cy[r0:r1], cx[c0:c1])


def render_target(target: Target, dpi: float) -> np.ndarray:
    """(H, W) float32 reflectance image of the board incl. margin at `dpi` (dark 0, white 1, edges area-averaged).

    Row 0 is the top of the print (smallest Y), column 0 the left (smallest X); one pixel is 25.4 / dpi mm.
    The image is the whole number of pixels that covers the board; any fraction left over is white.
    """
    x0, y0, x1, y1 = target.extent_mm
    px = 25.4 / dpi
    W, H = int(math.ceil((x1 - x0) / px - 1e-9)), int(math.ceil((y1 - y0) / px - 1e-9))
    return rasterise(target, (x0, x0 + W * px), (y0, y0 + H * px), W, H)


def target_texture(target: Target, px_per_mm: float, dark: float = 0.0, white: float = 1.0) -> np.ndarray:
    """(H, W, 3) float32 linear texture of the board incl. margin, for a textured `rectangle`.

    Orientation: image column = target X, image row = target Y; column 0 / row 0 at (x_min, y_min) of
    `target.extent_mm`, the last column / row at (x_max, y_max). The image covers the extent exactly:
    W = round(width · px_per_mm), so the actual scale is W / width (likewise H). Edges are area-averaged.
    """
    x0, y0, x1, y1 = target.extent_mm
    W = max(1, int(round((x1 - x0) * px_per_mm)))
    H = max(1, int(round((y1 - y0) * px_per_mm)))
    img = rasterise(target, (x0, x1), (y0, y1), W, H, dark, white)
    return np.repeat(img[..., None], 3, axis=-1)
