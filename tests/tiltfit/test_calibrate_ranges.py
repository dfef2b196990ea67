"""Every number `tiltfit calibrate` writes lies in its physical range (w > 0, U > 0 or null and undetermined,
d ≥ 0), and `tiltfit export` accepts every CALIB.json it writes: a sharp set (U, d undetermined), blur that
grows towards the camera as if focused beyond infinity (a fit with U < 0 on main), and a file doctored with
U < 0."""
import json
import math
import os
import sys

import pytest
import torch

from tiltfit.cli import main as cli
from tiltfit.files.calib import calib_dict
from tiltfit.calibrate.fit import FitOptions
from tiltfit.calibrate.flow import calibrate
from tiltfit.calibrate.model import PAPER_LENS, PAPER_SENSOR, Observations, LensCamera, random_poses
from tiltfit.target.layout import Target

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import fuzz_harness  # noqa: E402  (tests/fuzz_harness.py: run a command's main in-process)

TARGET = Target(tuple(25.0 * i for i in range(10)), tuple(25.0 * j for j in range(7)))  # 9 × 6 cells
PITCH = PAPER_SENSOR["pixel_pitch_mm"]


def observations(blur_of_depth, seed=3, n_views=6, corner_noise_px=0.05):
    """Synthetic corners of the paper's camera and blur widths `blur_of_depth(z_mm)` (pixels) with 3 % noise."""
    rvec, T = random_poses(n_views, seed, board_centre_mm=(112.5, 75.0))
    cam = LensCamera(n_views, **PAPER_SENSOR, **PAPER_LENS, rvec=rvec, T_mm=T)
    points = torch.as_tensor(TARGET.feature_points())
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        uv, _ = cam(points)
        z = cam.to_camera(points)[..., 2]
    b = blur_of_depth(z)
    corners = uv + corner_noise_px * torch.randn(uv.shape, generator=g, dtype=uv.dtype)
    blur = b * (1 + 0.03 * torch.randn(b.shape, generator=g, dtype=b.dtype))
    return Observations(points, corners, blur, PAPER_SENSOR["image_size_px"], PITCH)


def write_dets(obs, folder):
    paths = []
    for v in range(obs.n_views):
        p = folder / f"v{v}.json"
        p.write_text(json.dumps({"image_size_px": list(obs.image_size_px), "corners_px": obs.corners_px[v].tolist(),
                                 "blur_px": obs.blur_px[v].tolist(), "grid_found": True}))
        paths.append(str(p))
    return paths


def run(args):
    return fuzz_harness.run_command(cli.main, args)  # `tiltfit ARGS` in this process: (exit status, stderr)


def calibrate_and_export(obs, tmp_path):
    target = tmp_path / "T.json"
    TARGET.save(str(target))
    out = tmp_path / "calib.json"
    rc, err = run(["calibrate", *write_dets(obs, tmp_path), "--target", target, "--pixel-pitch-mm", PITCH,
                   "--distortion", "none", "--held-out", "0", "-o", out])
    assert rc == 0, err
    data = json.loads(out.read_text())
    rc, err_x = run(["export", out, "--to", "opencv", "-o", tmp_path / "cam.yml", "-q"])
    assert rc == 0, f"export refused what calibrate wrote: {err_x}"
    return data, err


def assert_physical(data):
    assert data["w_mm"] > 0, f"w {data['w_mm']}"
    for k in ("U_mm", "f_mm"):
        assert data[k] is None or data[k] > 0, f"{k} {data[k]}"
    assert data["d_mm"] is None or data["d_mm"] >= 0, f"d {data['d_mm']}"
    for k in ("U_mm", "d_mm"):
        assert (data[k] is None) == (k in data["undetermined"]), f"{k} null exactly when undetermined"


@pytest.mark.slow
def test_sharp_set_has_undetermined_focus(tmp_path):
    data, err = calibrate_and_export(observations(lambda z: torch.full_like(z, 0.4)), tmp_path)
    assert_physical(data)
    assert data["U_mm"] is None and data["d_mm"] is None, f"sharp: U {data['U_mm']}, d {data['d_mm']}"
    assert abs(data["w_mm"] / PAPER_LENS["w_mm"] - 1) < 0.003, f"the geometry is still calibrated: w {data['w_mm']}"


@pytest.mark.slow
def test_focus_beyond_infinity_is_not_written_as_negative_U(tmp_path):
    """Blur widths b = w d (1/z + 1/(58 mm)) / p: the thin lens's |1/U − 1/z| with U = −58 mm."""
    w, d = PAPER_LENS["w_mm"], 2.0
    data, err = calibrate_and_export(observations(lambda z: w * d * (1 / z + 1 / 58.0) / PITCH), tmp_path)
    assert_physical(data)
    assert data["U_mm"] is None and "U_mm" in data["undetermined"], f"U {data['U_mm']} ({err})"


def test_calib_dict_never_writes_a_value_outside_its_range():
    obs = observations(lambda z: torch.full_like(z, 0.4), n_views=4)
    res = calibrate(obs, "unified", options=FitOptions(model_selection=False, free_principal_point=False))
    res.values.update(U_mm=-58.14, d_mm=-1.0, f_mm=-3.0)
    res.undetermined = []
    data = calib_dict(res)
    assert data["U_mm"] is None and data["d_mm"] is None and data["f_mm"] is None, \
        f"U {data['U_mm']}, d {data['d_mm']}, f {data['f_mm']}"
    assert {"U_mm", "d_mm"} <= set(data["undetermined"]), f"listed: {data['undetermined']}"
    assert math.isfinite(data["w_mm"]) and data["w_mm"] > 0, "w kept"
