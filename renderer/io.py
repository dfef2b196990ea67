"""Image files through OpenImageIO: linear float in memory; sRGB for 8-bit files, linear otherwise."""
from __future__ import annotations

import os
import tempfile

import numpy as np


class ImageIOError(ValueError):
    """An image that cannot be read or written; one-line message naming the file."""


def srgb_to_linear(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(v: np.ndarray) -> np.ndarray:
    v = np.clip(np.asarray(v, dtype=np.float64), 0.0, None)
    return np.where(v <= 0.0031308, v * 12.92, 1.055 * np.power(v, 1 / 2.4) - 0.055)


def _default_encoding(path: str, is_8bit: bool) -> str:
    return "srgb" if is_8bit else "linear"


def read_image(path: str, encoding: str | None = None) -> np.ndarray:
    """Read an image as linear float32 (H, W, C).

    Args:
        encoding: `srgb` or `linear`; by default 8-bit files are sRGB and 16-bit/float files linear.
    """
    import OpenImageIO as oiio

    if not os.path.isfile(path):
        raise ImageIOError(f"{path}: no such file")
    inp = oiio.ImageInput.open(path)
    if inp is None:
        raise ImageIOError(f"{path}: cannot read image ({oiio.geterror().strip() or 'unknown format'})")
    try:
        spec = inp.spec()
        is_8bit = spec.format == oiio.UINT8
        pixels = inp.read_image(0, 0, 0, spec.nchannels, oiio.FLOAT)
        err = inp.geterror()
    finally:
        inp.close()
    if pixels is None or err:
        raise ImageIOError(f"{path}: cannot read image data ({(err or 'truncated or corrupt').strip()})")
    pixels = np.asarray(pixels, dtype=np.float32).reshape(spec.height, spec.width, spec.nchannels)
    enc = encoding or _default_encoding(path, is_8bit)
    if enc == "srgb":
        pixels = srgb_to_linear(pixels).astype(np.float32)
    elif enc != "linear":
        raise ImageIOError(f"{path}: encoding must be srgb or linear, got {enc!r}")
    return pixels


def write_image(path: str, image, encoding: str | None = None) -> None:
    """Write a linear (H, W, C) image; EXR keeps linear float, PNG/JPEG 8-bit sRGB, TIFF 16-bit sRGB.

    The file is written to a temporary name and renamed, so a failure leaves nothing half written.
    """
    import OpenImageIO as oiio

    arr = np.asarray(image.detach().cpu() if hasattr(image, "detach") else image, dtype=np.float32)
    if arr.ndim == 2:
        arr = arr[..., None]
    ext = os.path.splitext(path)[1].lower()
    if ext in (".exr", ".hdr"):
        fmt, enc = oiio.FLOAT, encoding or "linear"
    elif ext in (".png", ".jpg", ".jpeg"):
        fmt, enc = oiio.UINT8, encoding or "srgb"
    elif ext in (".tif", ".tiff"):
        fmt, enc = oiio.UINT16, encoding or "srgb"
    else:
        raise ImageIOError(f"{path}: unsupported output format {ext or '(none)'} (use .exr, .png or .tif)")
    data = linear_to_srgb(arr) if enc == "srgb" else arr
    if fmt != oiio.FLOAT:
        data = np.clip(data, 0.0, 1.0)
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=ext, dir=folder)
    os.close(fd)
    try:
        out = oiio.ImageOutput.create(tmp)
        spec = oiio.ImageSpec(arr.shape[1], arr.shape[0], arr.shape[2], fmt)
        if not out or not out.open(tmp, spec) or not out.write_image(np.ascontiguousarray(data, dtype=np.float32)):
            raise ImageIOError(f"{path}: cannot write image ({oiio.geterror().strip()})")
        out.close()
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
