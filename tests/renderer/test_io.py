"""Image files and output files: encodings round-trip through the file's metadata, self-description,
umask-respecting permissions, nothing left behind on failure or SIGKILL."""
from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from camio import files as rio
from camio.files import ImageIOError, atomic_output, image_metadata, read_image, write_image

# Largest slope of the sRGB decoding curve (at code 1.0): 2.4/1.055 · (1.055/1.055)^1.4 ≈ 2.275; a half-step of
# quantisation in sRGB codes is at most this much in linear values.
SRGB_SLOPE = 2.4 / 1.055
CASES = [  # (extension, encoding, bound on |read - written| in linear values)
    (".exr", None, 0.0), (".exr", "linear", 0.0), (".exr", "srgb", 1e-6),
    (".png", None, 0.5 / 255 * SRGB_SLOPE), (".png", "srgb", 0.5 / 255 * SRGB_SLOPE), (".png", "linear", 0.5 / 255),
    (".tif", None, 0.5 / 65535 * SRGB_SLOPE), (".tif", "srgb", 0.5 / 65535 * SRGB_SLOPE),
    (".tif", "linear", 0.5 / 65535), (".tiff", "linear", 0.5 / 65535),
    (".hdr", None, 1 / 128), (".hdr", "linear", 1 / 128),  # RGBE: 8-bit mantissas sharing one exponent
]


def _ramp(h=16, w=32) -> np.ndarray:
    """Linear values over [0, 1] in every channel, different per channel, (h, w, 3) float32."""
    x = np.linspace(0.0, 1.0, h * w, dtype=np.float32).reshape(h, w)
    return np.stack([x, x[::-1, ::-1], np.sqrt(x)], -1)


@pytest.mark.parametrize("ext,encoding,bound", CASES, ids=[f"{e}-{c}" for e, c, _ in CASES])
def test_every_format_and_encoding_round_trips_within_quantisation(tmp_path, ext, encoding, bound):
    image = _ramp()
    path = str(tmp_path / f"img{ext}")
    write_image(path, image, encoding)
    back = read_image(path)
    err = float(np.abs(back - image).max())
    assert back.shape == image.shape, f"shape {back.shape}"
    assert err <= bound + 1e-7, f"{ext} {encoding}: error {err:.3g} above the quantisation bound {bound:.3g}"


def test_16bit_tiff_of_0_2_reads_back_0_2(tmp_path):
    """The issue's case: a 16-bit TIFF written sRGB used to read back as linear (0.2 -> 0.4845)."""
    path = str(tmp_path / "grey.tif")
    write_image(path, np.full((4, 4, 3), 0.2, np.float32))
    value = float(read_image(path).mean())
    assert abs(value - 0.2) < 1e-4, f"0.2 written, {value} read"


def test_jpeg_is_srgb_only_and_round_trips_a_flat_image(tmp_path):
    path = str(tmp_path / "flat.jpg")
    write_image(path, np.full((16, 16, 3), 0.3, np.float32))
    value = float(read_image(path).mean())
    assert abs(value - 0.3) < 0.5 / 255 * SRGB_SLOPE + 1e-3, f"0.3 written, {value} read"
    with pytest.raises(ImageIOError, match="flat.jpg: JPG files cannot record a linear encoding"):
        write_image(path, np.zeros((2, 2, 3)), "linear")


def test_files_without_a_recorded_encoding_follow_the_contract(tmp_path):
    """8-bit files are sRGB, 16-bit and float linear, unless the file (or the caller) says otherwise."""
    import OpenImageIO as oiio

    value = np.full((2, 2, 3), 0.5, np.float32)
    for ext, fmt, expected in ((".png", oiio.UINT8, rio.srgb_to_linear(0.5)), (".tif", oiio.UINT16, 0.5)):
        path = str(tmp_path / f"bare{ext}")
        out = oiio.ImageOutput.create(path)
        out.open(path, oiio.ImageSpec(2, 2, 3, fmt))
        out.write_image(value)
        out.close()
        got = float(read_image(path).mean())
        assert abs(got - expected) < 2e-3, f"{ext}: {got}, expected {expected}"
        assert abs(float(read_image(path, "linear").mean()) - 0.5) < 2e-3, f"{ext}: explicit linear wins"


def test_images_describe_themselves(tmp_path):
    for ext in (".exr", ".png", ".tif"):
        path = str(tmp_path / f"m{ext}")
        write_image(path, _ramp(), metadata={"scene": "fig7.json", "camera": "ThinLensCamera", "spp": 16})
        meta = image_metadata(path)
        assert meta["Software"].startswith("renderer "), f"{ext}: {meta}"
        assert (meta["scene"], meta["camera"], meta["spp"]) == ("fig7.json", "ThinLensCamera", "16"), f"{ext}: {meta}"
        assert meta["encoding"] == ("linear" if ext == ".exr" else "srgb"), f"{ext}: {meta}"


def test_non_finite_pixels_are_refused_and_nothing_written(tmp_path):
    image = _ramp()
    image[3, 4, 1] = np.nan
    path = tmp_path / "nan.exr"
    with pytest.raises(ImageIOError, match="nan.exr: the image holds 1 NaN or infinite values"):
        write_image(str(path), image)
    assert os.listdir(tmp_path) == [], f"left behind: {os.listdir(tmp_path)}"


@pytest.mark.parametrize("umask", [0o022, 0o027, 0o002, 0o077])
@pytest.mark.parametrize("tmpfile", [True, False], ids=["O_TMPFILE", "mkstemp"])
def test_new_files_get_0666_minus_the_umask(tmp_path, monkeypatch, umask, tmpfile):
    if not tmpfile:
        monkeypatch.setattr(rio, "_tmpfile_supported", lambda folder: False)
    old = os.umask(umask)
    try:
        write_image(str(tmp_path / "a.png"), _ramp())
        rio.write_text(str(tmp_path / "b.json"), "{}\n")
    finally:
        os.umask(old)
    for name in ("a.png", "b.json"):
        mode = os.stat(tmp_path / name).st_mode & 0o777
        assert mode == 0o666 & ~umask, f"{name}: mode {oct(mode)} under umask {oct(umask)}"
    assert sorted(os.listdir(tmp_path)) == ["a.png", "b.json"], f"left behind: {os.listdir(tmp_path)}"


@pytest.mark.parametrize("tmpfile", [True, False], ids=["O_TMPFILE", "mkstemp"])
def test_a_failed_write_keeps_the_old_file_and_leaves_nothing(tmp_path, monkeypatch, tmpfile):
    if not tmpfile:
        monkeypatch.setattr(rio, "_tmpfile_supported", lambda folder: False)
    path = tmp_path / "out.json"
    path.write_text("old")
    for exc in (RuntimeError("boom"), KeyboardInterrupt()):
        with pytest.raises(type(exc)):
            with atomic_output(str(path)) as tmp:
                with open(tmp, "w") as f:
                    f.write("half")
                raise exc
    assert path.read_text() == "old", "the old file survives"
    assert os.listdir(tmp_path) == ["out.json"], f"left behind: {os.listdir(tmp_path)}"


@pytest.mark.skipif(not rio._tmpfile_supported("."), reason="needs O_TMPFILE (Linux)")
def test_when_linking_the_anonymous_file_is_refused_it_is_copied(tmp_path, monkeypatch):
    real_link = os.link

    def refuse(src, *args, **kwargs):
        if str(src).startswith("/proc/self/fd/"):
            raise PermissionError(1, "Operation not permitted")
        return real_link(src, *args, **kwargs)

    monkeypatch.setattr(os, "link", refuse)
    write_image(str(tmp_path / "a.png"), _ramp())
    assert float(np.abs(read_image(str(tmp_path / "a.png")) - _ramp()).max()) < 0.005, "the copy holds the image"
    assert os.listdir(tmp_path) == ["a.png"], f"left behind: {os.listdir(tmp_path)}"


def test_an_output_path_that_is_a_folder_is_refused_before_writing(tmp_path):
    with pytest.raises(IsADirectoryError):
        with atomic_output(str(tmp_path)):
            raise AssertionError("must not be reached")


@pytest.mark.skipif(not rio._tmpfile_supported("."), reason="needs O_TMPFILE (Linux)")
def test_sigkill_during_a_write_leaves_nothing_behind(tmp_path):
    """SIGKILL cannot be caught: the half-written data lives in an anonymous inode the kernel frees."""
    out = tmp_path / "out.png"
    out.write_bytes(b"previous")
    code = ("import os, signal\n"
            "from camio.files import atomic_output\n"
            f"with atomic_output({str(out)!r}) as tmp:\n"
            "    with open(tmp, 'wb') as f:\n"
            "        f.write(b'x' * 100000)\n"
            "        f.flush()\n"
            "    os.kill(os.getpid(), signal.SIGKILL)\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, timeout=120)
    assert proc.returncode == -9, f"killed by SIGKILL: {proc.returncode} {proc.stderr[-300:]!r}"
    assert os.listdir(tmp_path) == ["out.png"], f"left behind: {os.listdir(tmp_path)}"
    assert out.read_bytes() == b"previous", "the old file survives"


def test_atomic_folder_writes_a_subfolder_again(tmp_path):
    """A folder output written twice (`tiltfit report -o DIR` run again): its subfolders are replaced by the new
    ones, not refused because the old ones are not empty, and no staging or old copy is left."""
    from camio.files import atomic_folder

    out = tmp_path / "report"
    for run in ("first", "second"):
        with atomic_folder(str(out)) as staging:
            os.makedirs(os.path.join(staging, "sub"))
            with open(os.path.join(staging, "sub", f"{run}.txt"), "w") as f:
                f.write(run)
            with open(os.path.join(staging, "top.txt"), "w") as f:
                f.write(run)
    assert sorted(os.listdir(out / "sub")) == ["second.txt"], f"the subfolder is the new one: {os.listdir(out / 'sub')}"
    assert (out / "top.txt").read_text() == "second"
    assert sorted(os.listdir(tmp_path)) == ["report"] and sorted(os.listdir(out)) == ["sub", "top.txt"], \
        f"nothing left over: {os.listdir(tmp_path)}, {os.listdir(out)}"
