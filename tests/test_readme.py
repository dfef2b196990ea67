"""The README's Python quick starts run as written (a newcomer's first contact): each ```python block is executed
in a fresh folder that holds only links to the repository's `renderer/scenes` and `data`, and what it promises
(an image file, a calibration file, the printed numbers) is checked."""
from __future__ import annotations

import contextlib
import io
import json
import os
import re

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def readme_blocks() -> list[str]:
    with open(os.path.join(ROOT, "README.md"), encoding="utf-8") as f:
        return re.findall(r"```python\n(.*?)```", f.read(), flags=re.S)


def run_block(code: str, folder) -> str:
    os.makedirs(folder / "renderer", exist_ok=True)
    os.symlink(os.path.join(ROOT, "renderer", "scenes"), folder / "renderer" / "scenes")
    os.symlink(os.path.join(ROOT, "data"), folder / "data")
    out = io.StringIO()
    cwd = os.getcwd()
    os.chdir(folder)
    try:
        with contextlib.redirect_stdout(out):
            exec(compile(code, "README.md", "exec"), {"__name__": "readme"})
    finally:
        os.chdir(cwd)
    return out.getvalue()


def test_readme_has_the_two_quick_starts():
    blocks = readme_blocks()
    assert len(blocks) == 2, f"expected a render and a calibrate quick start, found {len(blocks)} python blocks"
    assert "renderer.render(" in blocks[0] and "tiltfit." in blocks[1], "the blocks should be render, then calibrate"
    for b in blocks:
        assert len(b.strip().splitlines()) <= 10, f"a quick start should be at most 10 lines:\n{b}"


def test_readme_render_quick_start(tmp_path):
    from camio.files import read_image

    printed = run_block(readme_blocks()[0], tmp_path)
    image = read_image(str(tmp_path / "tilt.png"))
    image = np.asarray(image.image if hasattr(image, "image") else image)
    assert image.shape[:2] == (160, 240), f"the quick start asked for 240x160, wrote {image.shape}"
    assert 0.02 < float(image.mean()) < 0.98, f"the image should be neither black nor white: mean {image.mean():.3f}"
    theta_L = float(printed.split()[0])
    assert theta_L != 0.0, f"tilt_fig9b has a tilted lens; printed {printed!r}"


@pytest.mark.slow
def test_readme_calibrate_quick_start(tmp_path):
    printed = run_block(readme_blocks()[1], tmp_path)
    with open(tmp_path / "calib.json") as f:
        calib = json.load(f)
    fx = calib["w_mm"] / calib["pixel_pitch_mm"]
    # OpenCV's calibrateCamera on all 36 photos gives fx 560 px (k1k2p1p2k3, free principal point); 12 views
    # of a GoPro's strong barrel distortion land within a few percent of it.
    assert 530 < fx < 590, f"focal length {fx:.1f} px is far from the GoPro's ~560 px"
    first = float(re.findall(r"[-+]?\d+\.?\d*(?:e[-+]?\d+)?", printed)[0])
    assert abs(first - fx) < 1e-3 * fx, f"the printed focal length {first} should be the file's {fx:.3f} px"
