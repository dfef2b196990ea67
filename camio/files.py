"""Image files through OpenImageIO, and the atomic, permission-respecting way every output file is written.

Encodings: in memory images are linear float. A file's encoding is written into its metadata
(`oiio:ColorSpace`: `srgb_rec709_scene` or `lin_rec709_scene`) and honoured on read, so every
`write_image` / `read_image` pair round-trips. A file that does not say (OpenImageIO reports no colour
space, e.g. a linear TIFF) follows the contract: 8-bit files sRGB, 16-bit and float files linear. An
explicit `encoding` argument overrides both. JPEG is always sRGB-tagged and Radiance HDR always linear, so
writing those in the other encoding is refused rather than silently mislabelled.

Metadata written with every image: `Software` ("renderer <version>"), `DateTime`, and an `ImageDescription`
of `key=value` pairs (scene, camera, spp, ...) passed by the caller; EXR files also carry each pair as a
`renderer:<key>` attribute. PNG, TIFF and JPEG keep the description as text.

Output files (`atomic_output`): written where no other process can see them and published by a rename, so
the final path holds either the old file or the complete new one. On Linux the data goes to an anonymous
`O_TMPFILE` inode in the output's folder, which the kernel frees if the process dies at any point before
publication, SIGKILL included; it is linked under a hidden name and renamed over the output in two system
calls. Elsewhere a hidden temporary file is used and removed on every exit path Python can catch. New files
get mode 0666 minus the umask, as `open()` would give them. Hidden names carry the writer's process id
(`.NAME.PID.N.tmp`, a set of files `.NAME.PID.tmp/`): what a SIGKILL leaves between link and rename is removed
by the next write to the same path once that process is gone (`remove_stale`).

A set of files (`atomic_folder`, e.g. a report's plots) is written into a hidden sibling folder and moved
into place only when every file is complete: an error or interrupt leaves the target folder as it was.
"""
from __future__ import annotations

import contextlib
import datetime
import functools
import os
import shutil
import sys
import tempfile

from camio.errors import ImageIOError, one_line  # noqa: F401 - ImageIOError raised here, importable from here as before


SRGB_SPACE = "srgb_rec709_scene"
LINEAR_SPACE = "lin_rec709_scene"
PNG_COMPRESSION_LEVEL = 3
WRITE_FORMATS = {".exr": "float", ".hdr": "float", ".png": "uint8", ".jpg": "uint8", ".jpeg": "uint8",
                 ".tif": "uint16", ".tiff": "uint16"}


@functools.lru_cache(maxsize=None)
def software_version(name: str = "renderer") -> str:
    """`<name> <version>` for the files' Software field (the package metadata is read once)."""
    try:
        from importlib.metadata import version

        return f"{name} {version('unusual-cameras')}"
    except Exception:  # not installed (run from a checkout)
        return f"{name} 0.1.0"


def srgb_to_linear(v: np.ndarray) -> np.ndarray:
    import numpy as np  # here, not at the top: the commands' argument checks use this module

    v = np.asarray(v, dtype=np.float64)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(v):
    """The sRGB transfer function (IEC 61966-2-1) of linear values, negatives as 0: the one place it is written.
    numpy in, float64 numpy out; a torch tensor in, a tensor of its dtype on its device out."""
    if type(v).__module__.startswith("torch"):
        import torch

        v = v.clamp(min=0.0)
        return torch.where(v <= 0.0031308, v * 12.92, 1.055 * v.pow(1 / 2.4) - 0.055)
    import numpy as np

    v = np.clip(np.asarray(v, dtype=np.float64), 0.0, None)
    return np.where(v <= 0.0031308, v * 12.92, 1.055 * np.power(v, 1 / 2.4) - 0.055)


def _encode_srgb8_formula(v):
    """round(255 · sRGB(v)) as uint8 for float64 v already clipped to [0, 1]: the definition `encode_srgb8` keeps."""
    import numpy as np

    return np.clip(np.round(linear_to_srgb(v) * 255.0), 0, 255).astype(np.uint8)


# `encode_srgb8`'s table: float64 values in [0, 1] binned by their bit pattern's top bits (sign, exponent and the
# first _SRGB8_MANTISSA_BITS of the mantissa: bins 2^-7 of their value wide), narrower than the gap between two
# codes' thresholds (0.94 % of the value at code 255, more below), so each bin holds at most one threshold
_SRGB8_MANTISSA_BITS = 7
_SRGB8_SHIFT = 52 - _SRGB8_MANTISSA_BITS


# ... and for float32 values, binned the same way by their own bit pattern (23 mantissa bits)
_SRGB8_SHIFT32 = 23 - _SRGB8_MANTISSA_BITS


@functools.lru_cache(maxsize=None)
def _srgb8_thresholds():
    """(255,) float64: threshold k − 1 is the least float64 whose code is k, found by bisection over the ordered bit
    patterns with the formula itself (the formula is monotone)."""
    import numpy as np

    lo = np.zeros(255, np.int64)  # bit patterns: code(lo) < k <= code(hi)
    hi = np.full(255, np.float64(1.0).view(np.int64))
    k = np.arange(1, 256)
    while (hi - lo > 1).any():
        mid = lo + (hi - lo) // 2
        up = _encode_srgb8_formula(mid.view(np.float64)) >= k
        hi, lo = np.where(up, mid, hi), np.where(up, lo, mid)
    return hi.view(np.float64)


def _binned_table(thresholds, starts):
    """(code at each bin's start (uint8), the next code's threshold (inf past 255)) of bins starting at `starts`."""
    import numpy as np

    code = np.searchsorted(thresholds, starts, side="right")
    assert (np.searchsorted(thresholds, np.nextafter(starts[1:], 0), side="right") - code[:-1] <= 1).all(), \
        "two sRGB codes in one bin of the table"
    return code.astype(np.uint8), np.append(thresholds, np.inf).astype(thresholds.dtype)[code]


@functools.lru_cache(maxsize=None)
def _srgb8_table():
    """(code at each bin's start (uint8), the next code's threshold (float64, inf past 255)) for `encode_srgb8`,
    from the thresholds of `_srgb8_thresholds`, so the table reproduces the formula exactly."""
    import numpy as np

    starts = (np.arange((np.float64(1.0).view(np.int64) >> _SRGB8_SHIFT) + 2, dtype=np.int64)
              << _SRGB8_SHIFT).view(np.float64)
    return _binned_table(_srgb8_thresholds(), starts)


@functools.lru_cache(maxsize=None)
def _srgb8_table32():
    """`_srgb8_table` for float32 values: each threshold rounded up to the least float32 at or above it (a float32
    value reaches a threshold exactly when it reaches that float32), the bins by the float32 bit pattern, all
    2^16 of them (sign and exponent included, so no value needs clipping first): the bins past 1 (+inf too) give
    255, the negative ones (−0.0 too) 0, with a threshold of NaN that no value reaches. NaN's bins are never read
    (NaN takes the formula)."""
    import numpy as np

    t = _srgb8_thresholds()
    t32 = t.astype(np.float32)
    t32 = np.where(t32.astype(np.float64) < t, np.nextafter(t32, np.float32(np.inf)), t32)
    starts = (np.arange((np.float32(1.0).view(np.int32) >> _SRGB8_SHIFT32) + 2, dtype=np.int32)
              << _SRGB8_SHIFT32).view(np.float32)
    code, nxt = _binned_table(t32, starts)
    every_code = np.zeros(1 << (32 - _SRGB8_SHIFT32), np.uint8)
    every_nxt = np.full(every_code.shape, np.nan, np.float32)
    every_code[:code.size], every_nxt[:code.size] = code, nxt
    every_code[code.size:1 << (31 - _SRGB8_SHIFT32)] = 255  # past 1 up to +inf (and +NaN's bins)
    return every_code, every_nxt


def encode_srgb8(linear):
    """Linear values to the uint8 an 8-bit sRGB file holds: round(255 · sRGB(clip(v, 0, 1))) (numpy).

    Read from a table binned by the values' bit patterns (`_srgb8_table`, or `_srgb8_table32` for float32 values
    without a float64 copy: the same codes as the formula to the last bit, without the power law's per-value
    cost); NaN (code of the formula) takes the formula."""
    import numpy as np

    a = np.asarray(linear)
    if a.dtype == np.float32 and a.size >= 4096 and not np.isnan(a).any():
        code, nxt = _srgb8_table32()
        b = np.ascontiguousarray(a).view(np.uint32) >> _SRGB8_SHIFT32  # every bit pattern has its bin: no clipping
        return np.take(code, b) + (a >= np.take(nxt, b))  # np.take: cheaper than indexing here
    v = np.clip(np.asarray(a, dtype=np.float64), 0.0, 1.0)
    if v.size < 4096 or np.isnan(v).any():
        return _encode_srgb8_formula(v)
    code, nxt = _srgb8_table()
    b = (v.view(np.int64) >> _SRGB8_SHIFT) & ((1 << (63 - _SRGB8_SHIFT)) - 1)  # the mask: -0.0 as 0.0
    return np.take(code, b) + (v >= np.take(nxt, b))


def _default_encoding(path: str, is_8bit: bool) -> str:
    return "srgb" if is_8bit else "linear"


def file_encoding(colour_space: str) -> str | None:
    """`srgb`, `linear` or None (the file does not say) from an OpenImageIO colour-space name."""
    cs = colour_space.lower()
    if "srgb" in cs:
        return "srgb"
    if cs.startswith("lin") or "linear" in cs or cs in ("acescg", "aces2065-1", "scene_linear"):
        return "linear"
    return None


@contextlib.contextmanager
def quiet_c_stderr():
    """Keep what C libraries print on file descriptor 2 (libpng's and libtiff's complaints) off the terminal
    while reading: the failure is reported once, as the one-line error."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):
        yield
        return
    try:
        with tempfile.TemporaryFile() as sink:
            os.dup2(sink.fileno(), 2)
            try:
                yield
            finally:
                os.dup2(saved, 2)
    finally:
        os.close(saved)


def read_image(path: str, encoding: str | None = None, max_pixels: int | None = None) -> np.ndarray:
    """Read an image as linear float32 (H, W, C).

    Args:
        encoding: `srgb` or `linear`; by default the file's recorded colour space, else 8-bit files are
            sRGB and 16-bit/float files linear.
        max_pixels: refuse (ImageIOError naming the file) an image of more pixels, from its header, before
            any pixel is decoded (a small file can declare a huge image: a decompression bomb).
    """
    import numpy as np
    import OpenImageIO as oiio

    if encoding not in (None, "srgb", "linear"):
        raise ImageIOError(f"{path}: encoding must be srgb or linear, got {encoding!r}")
    if not os.path.isfile(path):
        raise ImageIOError(f"{path}: {'is a folder' if os.path.isdir(path) else 'no such file'}")
    with quiet_c_stderr():
        inp = oiio.ImageInput.open(path)
        if inp is None:
            raise ImageIOError(f"{path}: cannot read image ({one_line(oiio.geterror()) or 'unknown format'})")
        try:
            spec = inp.spec()
            is_8bit = spec.format == oiio.UINT8
            pixels = None
            if max_pixels is not None and spec.width * spec.height > max_pixels:
                raise ImageIOError(f"{path}: a {spec.width}x{spec.height} image ({spec.width * spec.height / 1e6:.0f} "
                                   f"megapixels); at most {max_pixels / 1e6:.0f} megapixels are read here")
            if spec.width * spec.height * spec.nchannels * 4 <= _available_bytes():
                pixels = inp.read_image(0, 0, 0, spec.nchannels, oiio.FLOAT)
            else:
                raise ImageIOError(f"{path}: a {spec.width}x{spec.height} image does not fit in memory")
            err = inp.geterror()
            recorded = file_encoding(spec.get_string_attribute("oiio:ColorSpace"))
        finally:
            inp.close()
    if pixels is None or err:
        raise ImageIOError(f"{path}: cannot read image data ({one_line(err) or 'truncated or corrupt'})")
    pixels = np.asarray(pixels, dtype=np.float32).reshape(spec.height, spec.width, spec.nchannels)
    enc = encoding or recorded or _default_encoding(path, is_8bit)
    if enc == "srgb":
        pixels = srgb_to_linear(pixels).astype(np.float32)
    if not np.isfinite(pixels).all():
        raise ImageIOError(f"{path}: the image holds NaN or infinite pixel values")
    return pixels


def _available_bytes() -> int:
    from camio.checks import available_memory_bytes

    return available_memory_bytes()


def write_image(path: str, image, encoding: str | None = None, metadata: dict | None = None) -> None:
    """Write a linear (H, W, C) image; EXR/HDR keep linear float, PNG/JPEG 8-bit sRGB, TIFF 16-bit sRGB.

    Args:
        encoding: `srgb` or `linear` for the stored values [per format as above]; recorded in the file.
        metadata: `key: value` pairs describing the image (scene, camera, spp, ...), written into the
            file's ImageDescription (and as `renderer:<key>` attributes in EXR).
    A numpy uint8 image is taken as the file's 8-bit levels themselves (already encoded as `encoding`
    says, e.g. what a simulated camera records) and written unchanged to a .png or .jpg: no decode and
    re-encode of every pixel.
    Raises:
        ImageIOError: unsupported format or encoding, non-finite pixels, an unwritable path (one line).
    The file is written atomically (see the module docstring): a failure leaves the old file or nothing.
    """
    import numpy as np
    import OpenImageIO as oiio

    levels = isinstance(image, np.ndarray) and image.dtype == np.uint8
    arr = image if levels else np.asarray(image.detach().cpu() if hasattr(image, "detach") else image,
                                          dtype=np.float32)
    if arr.ndim == 2:
        arr = arr[..., None]
    ext = os.path.splitext(path)[1].lower()
    if ext not in WRITE_FORMATS:
        raise ImageIOError(f"{path}: unsupported output format {ext or '(none)'} (use .exr, .png or .tif)")
    if arr.ndim != 3 or arr.shape[0] < 1 or arr.shape[1] < 1 or not 1 <= arr.shape[2] <= 4:
        raise ImageIOError(f"{path}: expected an (H, W, C) image with 1 to 4 channels, got shape {arr.shape}")
    if levels and WRITE_FORMATS[ext] != "uint8":
        raise ImageIOError(f"{path}: uint8 levels go to an 8-bit format (.png or .jpg), not {ext}")
    if not levels and not np.isfinite(arr).all():
        raise ImageIOError(f"{path}: the image holds {int((~np.isfinite(arr)).sum())} NaN or infinite values; "
                           "not written")
    kind = WRITE_FORMATS[ext]
    fmt = {"float": oiio.FLOAT, "uint8": oiio.UINT8, "uint16": oiio.UINT16}[kind]
    enc = encoding or ("linear" if kind == "float" else "srgb")
    if enc not in ("srgb", "linear"):
        raise ImageIOError(f"{path}: encoding must be srgb or linear, got {enc!r}")
    if (ext in (".jpg", ".jpeg") and enc != "srgb") or (ext == ".hdr" and enc != "linear"):
        raise ImageIOError(f"{path}: {ext[1:].upper()} files cannot record a {enc} encoding "
                           f"(use .png or .tif for 8/16-bit {enc}, .exr for float)")
    if levels:
        data = arr
    else:
        data = linear_to_srgb(arr) if enc == "srgb" else arr
        if fmt != oiio.FLOAT:
            data = np.clip(data, 0.0, 1.0)
    spec = oiio.ImageSpec(arr.shape[1], arr.shape[0], arr.shape[2], fmt)
    spec.attribute("oiio:ColorSpace", SRGB_SPACE if enc == "srgb" else LINEAR_SPACE)
    if ext == ".png":
        # zlib level 3 instead of OpenImageIO's 6: less than half the time for a few per cent larger files
        # (docs/speed.md).
        spec.attribute("png:compressionLevel", PNG_COMPRESSION_LEVEL)
    spec.attribute("Software", software_version())
    spec.attribute("DateTime", datetime.datetime.now().strftime("%Y:%m:%d %H:%M:%S"))
    meta = {"encoding": enc, **(metadata or {})}
    spec.attribute("ImageDescription", "; ".join(f"{k}={one_line(str(v))}" for k, v in meta.items()))
    if kind == "float" and ext == ".exr":
        for k, v in meta.items():
            spec.attribute(f"renderer:{k}", one_line(str(v)))
    with atomic_output(path) as tmp:
        out = oiio.ImageOutput.create(path)
        if not out or not out.open(tmp, spec) or not out.write_image(np.ascontiguousarray(data, dtype=np.uint8 if levels else np.float32)):
            err = (out.geterror() if out else "") or oiio.geterror()
            raise ImageIOError(f"{path}: cannot write image ({one_line(err) or 'unknown error'})")
        if not out.close():
            raise ImageIOError(f"{path}: cannot write image ({one_line(out.geterror()) or 'close failed'})")


def image_metadata(path: str) -> dict:
    """The `key=value` pairs of an image's ImageDescription (as written by `write_image`), plus `Software`."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(path)
    if inp is None:
        raise ImageIOError(f"{path}: cannot read image ({one_line(oiio.geterror())})")
    try:
        spec = inp.spec()
        desc = spec.get_string_attribute("ImageDescription")
        out = {"Software": spec.get_string_attribute("Software")}
    finally:
        inp.close()
    for part in desc.split("; "):
        key, sep, value = part.partition("=")
        if sep:
            out[key] = value
    return out


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _tmpfile_supported(folder: str) -> bool:
    return hasattr(os, "O_TMPFILE") and os.path.isdir("/proc/self/fd")


@contextlib.contextmanager
def atomic_output(path: str):
    """Context manager yielding a path to write `path`'s new content to; on a clean exit it replaces `path`
    atomically, on any exception the old file (or nothing) stays.

    Raises OSError (naming `path`) when the folder cannot be created or written; a `path` that is a folder
    is refused before anything is written.
    """
    path = os.fspath(path)
    if os.path.isdir(path):
        raise IsADirectoryError(21, "is a folder, not a file", path)
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    hidden = f".{os.path.basename(path)}."
    remove_stale(folder, hidden)
    fd = -1
    if _tmpfile_supported(folder):
        try:
            fd = os.open(folder, os.O_TMPFILE | os.O_WRONLY, 0o666)  # the kernel applies the umask
        except OSError:
            fd = -1  # a file system without O_TMPFILE
    if fd >= 0:
        try:
            yield f"/proc/self/fd/{fd}"
            _publish_tmpfile(fd, folder, hidden, path)
        finally:
            os.close(fd)
        return
    with _hidden_file(folder, hidden, path) as (tmp_fd, tmp):
        os.close(tmp_fd)
        yield tmp


@contextlib.contextmanager
def _hidden_file(folder: str, hidden: str, path: str):
    """Yield (fd, name) of a new hidden temporary file in `folder` (mode 0666 minus the umask), renamed over
    `path` on a clean exit and removed on any exception: the writer where `O_TMPFILE` is missing or its
    inode cannot be linked. The caller closes fd."""
    fd, tmp = tempfile.mkstemp(prefix=f"{hidden}{os.getpid()}.", suffix=".tmp", dir=folder)
    try:
        os.chmod(tmp, 0o666 & ~_umask())
        yield fd, tmp
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def _publish_tmpfile(fd: int, folder: str, hidden: str, path: str) -> None:
    """Give the anonymous inode `fd` a hidden name in `folder`, then rename it over `path`."""
    dir_fd = os.open(folder, os.O_RDONLY)
    try:
        for attempt in range(100):
            name = f"{hidden}{os.getpid()}.{attempt}.tmp"
            try:
                os.link(f"/proc/self/fd/{fd}", name, dst_dir_fd=dir_fd, follow_symlinks=True)
                break
            except FileExistsError:
                continue
            except OSError:  # linking an anonymous inode refused (a restricted /proc): copy it instead
                _publish_copy(fd, folder, hidden, path)
                return
        else:
            raise FileExistsError(17, "cannot create a temporary name", os.path.join(folder, hidden))
        try:
            os.replace(name, os.path.basename(path), src_dir_fd=dir_fd, dst_dir_fd=dir_fd)
        except BaseException:
            with contextlib.suppress(OSError):
                os.unlink(name, dir_fd=dir_fd)
            raise
    finally:
        os.close(dir_fd)


def _publish_copy(fd: int, folder: str, hidden: str, path: str) -> None:
    """Copy the anonymous inode `fd` to a hidden temporary file, then rename it over `path`."""
    with _hidden_file(folder, hidden, path) as (tmp_fd, _):
        with os.fdopen(tmp_fd, "wb") as dst, open(f"/proc/self/fd/{fd}", "rb") as src:
            shutil.copyfileobj(src, dst, 1 << 20)


def output_problem(path: str, extensions: tuple[str, ...] | None = None) -> str | None:
    """Why `path` cannot be an output file, checked before any work, or None: it is a folder, its extension is
    not one of `extensions` (when given), or its folder cannot be created or written. The commands of both
    packages raise it as their one-line error."""
    if os.path.isdir(path):
        return "is a folder; give an output file name"
    ext = os.path.splitext(path)[1].lower()
    if extensions is not None and ext not in extensions:
        return f"unsupported output format {ext or '(none)'} (use {', '.join(extensions)})"
    existing = os.path.dirname(os.path.abspath(path))
    while not os.path.exists(existing) and os.path.dirname(existing) != existing:
        existing = os.path.dirname(existing)
    if not os.path.isdir(existing):
        return f"{existing} is not a folder"
    if not os.access(existing, os.W_OK | os.X_OK):
        return f"cannot write in {existing} (permission denied)"
    return None


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # PermissionError: another user's live process
        return True
    return True


def remove_stale(folder: str, hidden: str) -> list:
    """Remove `hidden` + `PID.…tmp` entries in `folder` (this module's temporary names for one output) whose
    writing process no longer exists, e.g. after a SIGKILL; returns the names removed."""
    removed = []
    try:
        names = os.listdir(folder)
    except OSError:
        return removed
    for name in names:
        if not (name.startswith(hidden) and name.endswith(".tmp")):
            continue
        pid = name[len(hidden):].split(".", 1)[0]
        if not pid.isdigit() or int(pid) == os.getpid() or _pid_alive(int(pid)):
            continue
        full = os.path.join(folder, name)
        with contextlib.suppress(OSError):
            if os.path.isdir(full) and not os.path.islink(full):
                shutil.rmtree(full)
            else:
                os.remove(full)
            removed.append(name)
    return removed


@contextlib.contextmanager
def atomic_folder(path: str):
    """Context manager yielding a hidden staging folder beside `path` (a folder); on a clean exit every file
    written there is moved into `path` (created if missing: then in one rename), on any exception or interrupt
    the staging folder is removed and `path` is left as it was.

    Raises OSError when `path` is a file or the parent folder cannot be written.
    """
    path = os.path.abspath(os.fspath(path))
    if os.path.exists(path) and not os.path.isdir(path):
        raise NotADirectoryError(20, "not a folder", path)
    parent = os.path.dirname(path)
    os.makedirs(parent, exist_ok=True)
    hidden = f".{os.path.basename(path)}."
    remove_stale(parent, hidden)
    staging = os.path.join(parent, f"{hidden}{os.getpid()}.tmp")
    shutil.rmtree(staging, ignore_errors=True)
    os.mkdir(staging)
    try:
        os.chmod(staging, 0o777 & ~_umask())
        yield staging
        if not os.path.exists(path):
            os.rename(staging, path)
            return
        for name in sorted(os.listdir(staging)):
            src, dst = os.path.join(staging, name), os.path.join(path, name)
            if os.path.isdir(src) and os.path.isdir(dst) and not os.path.islink(dst):
                # A folder written again (a report's subfolder): the old one aside, the new in, the old removed
                # (os.replace cannot replace a folder that is not empty).
                old = os.path.join(path, f".{name}.{os.getpid()}.old")
                shutil.rmtree(old, ignore_errors=True)
                os.rename(dst, old)
                os.rename(src, dst)
                shutil.rmtree(old, ignore_errors=True)
            else:
                os.replace(src, dst)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def write_text(path: str, text: str) -> None:
    """Write a text file (UTF-8) atomically with umask-respecting permissions (see `atomic_output`)."""
    with atomic_output(path) as tmp:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)
