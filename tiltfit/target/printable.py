"""The printable board: an 8-bit PNG that records its dpi and a vector PDF, at true size with a scale bar
and a caption (`write_printable`), written in strips of rows so memory does not grow with the page."""
from __future__ import annotations

import math

import numpy as np

from .layout import Target, TargetError
from .raster import rasterise


def write_printable(target: Target, png_path: str | None, pdf_path: str | None, dpi: float = 300.0,
                    scale_bar_mm: float | None = None) -> None:
    """Write the board at true size with a scale bar below it: a PNG at `dpi` and/or a vector PDF.

    The page is the board incl. margin plus a 15 mm strip at the bottom holding a scale bar of
    `scale_bar_mm` (default: the largest of 10/20/50/100/200 mm that fits) with 10 mm ticks and a caption;
    print at 100 % and check the bar with a ruler.
    """
    x0, y0, x1, y1 = target.extent_mm
    width, strip = x1 - x0, 15.0
    if not (math.isfinite(dpi) and MIN_PRINT_DPI <= dpi <= MAX_PRINT_DPI):
        raise TargetError(f"dpi: expected {MIN_PRINT_DPI:g} to {MAX_PRINT_DPI:g} dots per inch, got {dpi:g}")
    if max(width, y1 + strip - y0) > MAX_PRINT_MM:
        raise TargetError(f"margin: the page would be {width / 1000:.3g} × {(y1 + strip - y0) / 1000:.3g} m "
                          f"(at most {MAX_PRINT_MM / 1000:g} m a side); use a smaller margin or board")
    if scale_bar_mm is None:
        fits = [v for v in (10.0, 20.0, 50.0, 100.0, 200.0) if v <= 0.8 * width]
        scale_bar_mm = fits[-1] if fits else 0.5 * width
    bar_room = x1 - _bar_geometry(target, strip, 0.0)[0]
    if not (math.isfinite(scale_bar_mm) and 0 < scale_bar_mm <= bar_room):
        raise TargetError(f"scale_bar_mm: expected a length in (0, {bar_room:.4g}] mm (the bar fits on the page), "
                          f"got {scale_bar_mm:g}")
    caption = f"{target.caption()}; bar = {scale_bar_mm:g} mm"
    if png_path:
        pixels = (width / 25.4 * dpi) * ((y1 + strip - y0) / 25.4 * dpi)
        if not (dpi > 0 and pixels <= MAX_PRINT_PIXELS):
            raise TargetError(f"dpi: {dpi:g} dpi gives a {pixels / 1e6:.0f}-megapixel PNG of this "
                              f"{width:.0f} × {y1 - y0:.0f} mm board (at most {MAX_PRINT_PIXELS / 1e6:.0f}); "
                              f"lower the dpi or print the PDF")
        _write_png(target, png_path, dpi, strip, scale_bar_mm, caption)
    if pdf_path:
        _write_pdf(target, pdf_path, strip, scale_bar_mm, caption)


# the largest PNG `write_printable` writes (a poster of 1.2 × 0.85 m at 600 dpi)
MAX_PRINT_PIXELS = 400e6
# Print resolutions: below 10 dpi a square is a few pixels; above 10,000 no printer resolves it.
MIN_PRINT_DPI, MAX_PRINT_DPI = 10.0, 10000.0
# The largest page side, mm (a 10 m banner); larger is a unit mistake in the margin or edges.
MAX_PRINT_MM = 10000.0


def _bar_geometry(target, strip, bar_mm):
    x0, _, _, y1 = target.extent_mm
    bx0 = x0 + max(5.0, 0.1 * target.margin)
    by0 = y1 + 4.0
    return bx0, by0, bar_mm, 2.0  # left, top, length, thickness (mm)


# Rows of the board rasterised at a time by `_write_png`: about 2^20 pixels a strip, so a poster needs tens of
# MB (rasterise holds a few float64 arrays of the strip), however large the page.
PNG_STRIP_PIXELS = 1 << 20


def _write_png(target, path, dpi, strip, bar_mm, caption):
    """The board rasterised exactly at `dpi`, the bar and its ticks drawn in pixels, the caption (the bar's
    length) drawn as text over the strip; an 8-bit grey PNG that records its dpi so viewers and printers keep
    true size. Written through OpenImageIO in strips of rows (`PNG_STRIP_PIXELS`): memory does not grow with the
    page (a 0.71 m board at 300 dpi, 72 megapixels, once took 10 GB as one float image)."""
    import OpenImageIO as oiio

    from camio.files import atomic_output, quiet_c_stderr

    x0, y0, x1, y1 = target.extent_mm
    px = 25.4 / dpi
    W, H = int(math.ceil((x1 - x0) / px - 1e-9)), int(math.ceil((y1 + strip - y0) / px - 1e-9))
    Hb = int(math.ceil((y1 - y0) / px - 1e-9))
    spec = oiio.ImageSpec(W, H, 1, oiio.UINT8)
    spec.attribute("XResolution", float(dpi))
    spec.attribute("YResolution", float(dpi))
    spec.attribute("ResolutionUnit", "in")
    spec.attribute("oiio:ColorSpace", "sRGB")
    rects = np.asarray(target.dark_rectangles(), dtype=np.float64).reshape(-1, 4)
    rows = max(1, PNG_STRIP_PIXELS // W)
    with atomic_output(path) as tmp:
        out = oiio.ImageOutput.create("png")
        if not out or not out.open(tmp, spec):
            raise OSError(f"cannot write PNG ({(out.geterror() if out else '') or oiio.geterror()})")
        try:
            for r0 in range(0, Hb, rows):
                r1 = min(Hb, r0 + rows)
                ya, yb = y0 + r0 * px, y0 + r1 * px
                near = rects[(rects[:, 3] > ya) & (rects[:, 1] < yb)]  # the markers this strip crosses
                img = rasterise(_WithRectangles(target, near), (x0, x0 + W * px), (ya, yb), W, r1 - r0)
                _write_rows(out, r0, _srgb8(img))
            _write_rows(out, Hb, _scale_bar_rows(target, dpi, strip, bar_mm, caption, W, H, Hb))
        except BaseException:
            with quiet_c_stderr():  # libpng complains of the unfinished file, which atomic_output removes
                out.close()
            raise
        if not out.close():
            raise OSError(f"cannot write PNG ({out.geterror() or 'close failed'})")


class _WithRectangles:
    """A target seen through `rasterise` with only some of its dark rectangles (those a strip crosses)."""

    def __init__(self, target, rectangles):
        self._target, self._rectangles = target, rectangles

    def __getattr__(self, name):
        return getattr(self._target, name)

    def dark_rectangles(self):
        return self._rectangles


def _srgb8(linear: np.ndarray) -> np.ndarray:
    from camio.files import encode_srgb8

    return encode_srgb8(linear)


def _write_rows(out, r0: int, rows_u8: np.ndarray) -> None:
    if not out.write_scanlines(r0, r0 + rows_u8.shape[0], 0, np.ascontiguousarray(rows_u8[..., None])):
        raise OSError(f"cannot write PNG ({out.geterror() or 'write failed'})")


def _scale_bar_rows(target, dpi, strip, bar_mm, caption, W, H, Hb) -> np.ndarray:
    """(H − Hb, W) uint8 rows below the board: white, the bar and its 10 mm ticks in pixels, the caption drawn
    by matplotlib 2 mm below the bar at 6 pt, as in the PDF (only the caption's box is drawn, so a wide page
    costs no more than a narrow one)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    x0, y0, _, _ = target.extent_mm
    px = 25.4 / dpi
    rows = np.full((H - Hb, W), 255, dtype=np.uint8)  # white; black is 0 in any encoding
    bx0, by0, L, t = _bar_geometry(target, strip, bar_mm)
    c = lambda x: int(round((x - x0) / px))  # noqa: E731
    r = lambda y: int(round((y - y0) / px)) - Hb  # noqa: E731
    rows[max(r(by0), 0):max(r(by0 + t), 0), c(bx0):c(bx0 + L)] = 0
    for k in range(int(L // 10) + 1):
        xk = bx0 + 10.0 * k
        rows[max(r(by0 - 1.5), 0):max(r(by0 + t), 0), c(xk) - 1:c(xk) + 1] = 0
    top, left = max(r(by0 + t + 2.0), 0), c(bx0)
    # The caption's box: 6 pt a character is wider than any glyph of the font at 6 pt; to the strip's bottom.
    box_w, box_h = min(W - left, int(math.ceil(len(caption) * 6 / 72 * dpi)) + 2), H - Hb - top
    if box_w > 0 and box_h > 0:
        fig = Figure(figsize=(box_w / dpi, box_h / dpi), dpi=dpi, facecolor="white")
        canvas = FigureCanvasAgg(fig)
        fig.text(0.0, 1.0, caption, fontsize=6, va="top", ha="left", color="black")
        canvas.draw()
        text = np.asarray(canvas.buffer_rgba())[:box_h, :box_w, 0]
        region = rows[top:top + text.shape[0], left:left + text.shape[1]]
        np.minimum(region, text[:region.shape[0], :region.shape[1]], out=region)
    return rows


def _save_atomic(fig, path: str, fmt: str, **kwargs) -> None:
    """`fig.savefig` through `camio.files.atomic_output`: nothing partial at `path` on an error or signal."""
    from camio.files import atomic_output

    with atomic_output(path) as tmp:
        with open(tmp, "wb") as f:
            fig.savefig(f, format=fmt, **kwargs)


def _write_pdf(target, path, strip, bar_mm, caption):
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle

    x0, y0, x1, y1 = target.extent_mm
    Wmm, Hmm = x1 - x0, y1 + strip - y0
    fig = Figure(figsize=(Wmm / 25.4, Hmm / 25.4))
    ax = fig.add_axes((0, 0, 1, 1))
    ax.set_xlim(x0, x1)
    ax.set_ylim(y1 + strip, y0)  # Y down, as on the print
    ax.set_axis_off()
    xe, ye = target.x_edges, target.y_edges
    dark = target.cell_colours()
    for j in range(target.n_rows):
        for i in range(target.n_cols):
            if dark[j, i]:
                ax.add_patch(Rectangle((xe[i], ye[j]), xe[i + 1] - xe[i], ye[j + 1] - ye[j], facecolor="black",
                                       edgecolor="none", linewidth=0, antialiased=False))
    for rx0, ry0, rx1, ry1 in target.dark_rectangles():
        ax.add_patch(Rectangle((rx0, ry0), rx1 - rx0, ry1 - ry0, facecolor="black", edgecolor="none", linewidth=0,
                               antialiased=False))
    bx0, by0, L, t = _bar_geometry(target, strip, bar_mm)
    ax.add_patch(Rectangle((bx0, by0), L, t, facecolor="black", edgecolor="none"))
    for k in range(int(L // 10) + 1):
        ax.plot([bx0 + 10.0 * k] * 2, [by0 - 1.5, by0 + t], color="black", linewidth=0.5)
    ax.text(bx0, by0 + t + 2.0, caption, fontsize=6, va="top", ha="left")
    _save_atomic(fig, path, "pdf")
