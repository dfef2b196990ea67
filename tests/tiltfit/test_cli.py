"""tiltfit.cli.main: `tiltfit calibrate` / `detect` end to end on files, and the error contract.

Detections are written as DET.json files (the format of `tiltfit detect`) from synthetic observations, so
these tests do not depend on the detector.
"""
import json
import math
import os
import re
import subprocess
import sys

import numpy as np
import pytest
import torch

from renderer import write_image
from tiltfit.files.calib import REQUIRED_KEYS, SIGMA_KEYS, VIEW_KEYS, camera_from_calib, read_calib
from tiltfit.cli.main import main
from tiltfit.calibrate.model import PAPER_LENS, PAPER_SENSOR, LensCamera, random_poses, synthesize_observations
from tiltfit.target.layout import Target

W_MM, U_MM, D_MM = PAPER_LENS["w_mm"], PAPER_LENS["U_mm"], PAPER_LENS["d_mm"]
F_MM = W_MM * U_MM / (W_MM + U_MM)
PITCH = PAPER_SENSOR["pixel_pitch_mm"]
TARGET = Target(tuple(25.0 * i for i in range(10)), tuple(25.0 * j for j in range(7)))  # 9 × 6 cells


def write_detections(folder, camera, prefix, seed):
    points = torch.as_tensor(TARGET.feature_points())
    clean = synthesize_observations(camera, points, 0.0, 0.0)
    obs = synthesize_observations(camera, points, 0.05, 0.03 * float(clean.blur_px.nanmedian()), seed=seed)
    paths = []
    for v in range(obs.n_views):
        det = {"image_size_px": list(obs.image_size_px),
               "corners_px": [None if math.isnan(c[0]) else c for c in obs.corners_px[v].tolist()],
               "blur_px": [None if math.isnan(b) else b for b in obs.blur_px[v].tolist()],
               "grid_found": True}
        path = os.path.join(folder, f"{prefix}{v}.json")
        with open(path, "w") as f:
            json.dump(det, f)
        paths.append(path)
    return paths


def views(n, seed, theta_L_deg=0.0):
    rvec, T = random_poses(n, seed, board_centre_mm=(112.5, 75.0))
    if theta_L_deg:
        return LensCamera.from_tilted_lens(n, **PAPER_SENSOR, w_mm=W_MM, f_mm=F_MM, d_mm=D_MM,
                                               theta_L=math.radians(theta_L_deg), rvec=rvec, T_mm=T)
    return LensCamera(n, **PAPER_SENSOR, **PAPER_LENS, rvec=rvec, T_mm=T)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("cli")
    target = str(folder / "T.json")
    TARGET.save(target)
    untilted = write_detections(str(folder), views(6, seed=21), "flat", seed=1)
    tilted = write_detections(str(folder), views(6, seed=22, theta_L_deg=5.0), "tilt", seed=2)
    return folder, target, untilted, tilted


def run_cli(args, capfd):
    rc = main([str(a) for a in args])
    out, err = capfd.readouterr()
    return rc, out, err


def assert_one_line_error(rc, err, file, output):
    lines = err.strip().splitlines()
    assert rc == 2, f"exit status 2 expected, got {rc} ({err!r})"
    assert len(lines) == 1 and re.match(rf"tiltfit: {re.escape(str(file))}(:\d+:\d+)?: ", lines[0]), \
        f"one line naming {file} (and where in it): {err!r}"
    assert "Traceback" not in err, "no traceback"
    assert not os.path.exists(output), "no output file is left behind"
    leftovers = [n for n in os.listdir(os.path.dirname(output)) if n.startswith(".calib-") or n.startswith(".tiltfit-")]
    assert not leftovers, f"no temporary files left: {leftovers}"


# --- calibrate -----------------------------------------------------------------------------------------------

def test_calibrate_unified_then_tilt_writes_the_contract(files, capfd):
    folder, target, untilted, tilted = files
    out1 = folder / "stage1.json"
    rc, out, err = run_cli(["calibrate", *untilted, "--target", target, "--pixel-pitch-mm", PITCH, "-o", out1], capfd)
    assert rc == 0, f"stage 1 failed: {err}"
    assert out == "", "results go to the file, progress to stderr"
    assert "model selection" in err and "wrote" in err, f"progress on stderr: {err}"
    calib = read_calib(str(out1))
    missing = [k for k in REQUIRED_KEYS if k not in calib]
    assert not missing, f"contract keys missing: {missing}"
    assert all(k in calib["sigma"] for k in SIGMA_KEYS), f"sigma keys: {calib['sigma']}"
    assert all(all(k in v for k in VIEW_KEYS) for v in calib["views"]), "view keys"
    assert calib["image_size_px"] == list(PAPER_SENSOR["image_size_px"]) and calib["pixel_pitch_mm"] == PITCH
    assert abs(calib["w_mm"] / W_MM - 1) < 0.003 and abs(calib["U_mm"] / U_MM - 1) < 0.005, \
        f"stage 1 recovers w, U: {calib['w_mm']}, {calib['U_mm']}"
    assert calib["fit"] == "unified" and calib["model_selection"]["theta_F"]["justified"] is False, \
        "model-selection verdict stored"
    assert [v["image"] for v in calib["views"]] == [str(p) for p in untilted], "views named by input"
    assert all(v["n_points"] == 40 for v in calib["views"]), "40 corners per view"

    out2 = folder / "stage2.json"
    rc, _, err = run_cli(["calibrate", *tilted, "--target", target, "--pixel-pitch-mm", PITCH, "--fit", "tilt",
                          "--init", out1, "-o", out2], capfd)
    assert rc == 0, f"stage 2 failed: {err}"
    calib2 = read_calib(str(out2))
    assert calib2["w_mm"] == pytest.approx(calib["w_mm"]) and calib2["U_mm"] == pytest.approx(calib["U_mm"]), \
        "stage 2 holds w and U"
    assert 3.0 < calib2["theta_L_deg"] < 7.0 and calib2["model_selection"]["theta_F"]["justified"] is True, \
        f"a tilt is found: θL = {calib2['theta_L_deg']}"
    assert calib2["sigma"]["theta_L_deg"] > 0, "θL has an uncertainty"

    out3 = folder / "joint.json"
    rc, _, err = run_cli(["calibrate", *tilted, "--target", target, "--pixel-pitch-mm", PITCH, "--fit", "joint",
                          "--no-model-selection", "-q", "-o", out3], capfd)
    assert rc == 0 and err == "", f"joint, quiet: {err}"
    calib3 = read_calib(str(out3))
    assert abs(calib3["theta_L_deg"] - 5.0) < 0.1, f"joint θL {calib3['theta_L_deg']}"
    cam = camera_from_calib(calib3)
    assert cam.n_views == 6 and abs(cam.summary()["theta_L_deg"] - calib3["theta_L_deg"]) < 1e-9, \
        "CALIB.json round-trips into a camera"


def test_tilted_capture_with_the_defaults_suggests_the_tilt_without_a_blur_warning(files, capfd):
    """The untilted model misfits a tilted lens's blur; that is for the θF test to find, not a warning that the
    thin-lens blur model does not describe the lens (it does, with θF free)."""
    folder, target, _, tilted = files
    out = folder / "tilted_defaults.json"
    rc, _, err = run_cli(["calibrate", *tilted, "--target", target, "--pixel-pitch-mm", PITCH, "-o", out], capfd)
    assert rc == 0, err
    assert "warning" not in err, f"no warning on a tilted capture: {err}"
    calib = read_calib(str(out))
    assert calib["model_selection"]["theta_F"]["justified"] is True, "the tilt is suggested"
    assert calib["U_mm"] is not None and calib["warnings"] == [], "the blur model is kept"


def test_principal_point_can_be_forced_free_or_fixed(files, capfd):
    folder, target, untilted, _ = files
    W, H = PAPER_SENSOR["image_size_px"]
    for flag, fitted in (("--free-principal-point", True), ("--fixed-principal-point", False)):
        out = folder / f"pp{fitted}.json"
        rc, _, err = run_cli(["calibrate", *untilted, "--target", target, "--pixel-pitch-mm", PITCH, "--distortion",
                              "none", "--held-out", "0", flag, "-q", "-o", out], capfd)
        assert rc == 0, err
        calib = read_calib(str(out))
        assert calib["principal_point_fitted"] is fitted, f"{flag}: {calib['model_selection']['principal_point']}"
        if not fitted:
            assert calib["principal_point_px"] == [(W - 1) / 2, (H - 1) / 2], "held at the image centre"
    with pytest.raises(SystemExit) as exc:  # argparse's usage error
        main(["calibrate", *untilted, "--target", target, "--pixel-pitch-mm", str(PITCH), "--free-principal-point",
              "--fixed-principal-point", "-o", str(folder / "never.json")])
    err = capfd.readouterr().err
    assert exc.value.code == 2 and "not allowed with" in err, f"the two flags exclude each other: {err}"


# --- errors --------------------------------------------------------------------------------------------------

def test_missing_image(files, capfd):
    folder, target, untilted, _ = files
    out = str(folder / "never.json")
    missing = str(folder / "nope.png")
    rc, _, err = run_cli(["calibrate", untilted[0], missing, "--target", target, "--pixel-pitch-mm", PITCH,
                          "-o", out], capfd)
    assert_one_line_error(rc, err, missing, out)


@pytest.mark.parametrize("content, problem", [
    ("{not json", "not valid JSON"),
    ('{"type": "checkerboard", "x_edges": [0, 25, 50]}', "y_edges: missing key"),
])
def test_bad_target(files, capfd, content, problem):
    folder, _, untilted, _ = files
    bad = folder / "bad_target.json"
    bad.write_text(content)
    out = str(folder / "never.json")
    rc, _, err = run_cli(["calibrate", *untilted, "--target", bad, "--pixel-pitch-mm", PITCH, "-o", out], capfd)
    assert_one_line_error(rc, err, str(bad), out)
    assert problem in err, f"the problem is named: {err!r}"


def test_no_board_found(files, capfd):
    folder, target, untilted, _ = files
    empty = folder / "empty.json"
    empty.write_text(json.dumps({"image_size_px": [5472, 3648], "corners_px": [None] * 40, "blur_px": [None] * 40,
                                 "grid_found": False}))
    out = str(folder / "never.json")
    rc, _, err = run_cli(["calibrate", *untilted, empty, "--target", target, "--pixel-pitch-mm", PITCH,
                          "-o", out], capfd)
    assert_one_line_error(rc, err, str(empty), out)
    assert "no board found" in err, err


def test_missing_key_in_init(files, capfd):
    folder, target, _, tilted = files
    init = folder / "init_missing.json"
    init.write_text(json.dumps({"pixel_pitch_mm": PITCH, "image_size_px": [5472, 3648], "w_mm": 55.0}))
    out = str(folder / "never.json")
    rc, _, err = run_cli(["calibrate", *tilted, "--target", target, "--pixel-pitch-mm", PITCH, "--fit", "tilt",
                          "--init", init, "-o", out], capfd)
    assert_one_line_error(rc, err, str(init), out)
    assert "U_mm: missing key" in err, err


def test_truncated_image(files, capfd):
    folder, target, _, _ = files
    png = str(folder / "trunc.png")
    write_image(png, torch.rand(64, 96, 3).numpy())
    data = open(png, "rb").read()
    with open(png, "wb") as f:
        f.write(data[: len(data) // 2])
    out = str(folder / "never.json")
    rc, _, err = run_cli(["calibrate", png, "--target", target, "--pixel-pitch-mm", PITCH, "-o", out], capfd)
    assert_one_line_error(rc, err, png, out)


def test_non_converging_fit(files, capfd):
    folder, target, untilted, _ = files
    out = str(folder / "never.json")
    rc, _, err = run_cli(["calibrate", *untilted, "--target", target, "--pixel-pitch-mm", PITCH, "--fit", "joint",
                          "--max-iterations", 1, "-q", "-o", out], capfd)
    assert_one_line_error(rc, err, untilted[0] + f" (+{len(untilted) - 1} more)", out)
    assert "did not converge" in err, err


def test_tilt_without_init(files, capfd):
    folder, target, _, tilted = files
    out = str(folder / "never.json")
    rc, _, err = run_cli(["calibrate", *tilted, "--target", target, "--pixel-pitch-mm", PITCH, "--fit", "tilt",
                          "-o", out], capfd)
    assert_one_line_error(rc, err, "--init", out)


def test_detect_missing_image(files, capfd):
    folder, target, _, _ = files
    out = str(folder / "det_never.json")
    missing = str(folder / "missing.png")
    rc, _, err = run_cli(["detect", missing, "--target", target, "-o", out], capfd)
    assert_one_line_error(rc, err, missing, out)


def test_python_m_tiltfit(files):
    folder, target, untilted, _ = files
    help_run = subprocess.run([sys.executable, "-m", "tiltfit", "--help"], capture_output=True, text=True)
    assert help_run.returncode == 0 and "calibrate" in help_run.stdout and "detect" in help_run.stdout, \
        f"`python -m tiltfit --help` works: {help_run.stderr}"
    out = str(folder / "never.json")
    err_run = subprocess.run([sys.executable, "-m", "tiltfit", "calibrate", str(folder / "x.png"), "--target",
                              target, "--pixel-pitch-mm", str(PITCH), "-o", out], capture_output=True, text=True)
    assert err_run.returncode == 2 and err_run.stderr.count("\n") == 1, f"one line: {err_run.stderr!r}"
    assert err_run.stderr.startswith(f"tiltfit: {folder / 'x.png'}: "), err_run.stderr


@pytest.mark.slow
def test_end_to_end_on_rendered_images(tmp_path, capfd):
    """Render target photographs (tiltfit.experiments.synth), then `tiltfit calibrate` them: detection + fit."""
    from camio.files import srgb_to_linear
    from tiltfit.experiments.synth import PAPER_CAMERA, pose_from_axis_angle, render_view
    from tiltfit.target.design import design_target

    target = design_target(9, 6, 25.0, w_mm=W_MM, distance_mm=600.0, inclination_deg=15.0)
    target_file = str(tmp_path / "T.json")
    target.save(target_file)
    cam = PAPER_CAMERA.binned(8)  # 684 × 456 pixels of 52.3 µm: the paper's optics, a small image
    rvec, T = random_poses(5, seed=23, board_centre_mm=(112.5, 0.5 * target.y_edges[-1]))
    images = []
    for v in range(5):
        R, Tv = pose_from_axis_angle(rvec[v].numpy(), T[v].numpy())
        view = render_view(target, cam, R, Tv, noise_sigma=0.003, srgb8=True, seed=v)
        path = str(tmp_path / f"view{v}.png")
        # sRGB codes stored as they are: decoded to linear here, encoded back to the same codes by write_image.
        write_image(path, srgb_to_linear(view.image_srgb8 / 255.0))
        images.append(path)
    out = tmp_path / "calib.json"
    rc, _, err = run_cli(["calibrate", *images, "--target", target_file, "--pixel-pitch-mm", cam.sensor.pixel_pitch,
                          "-o", out], capfd)
    assert rc == 0, f"end-to-end calibration failed: {err}"
    calib = read_calib(str(out))
    print(f"\nrendered end to end: w {calib['w_mm']:.3f} ± {calib['sigma']['w_mm']:.3f}, U {calib['U_mm']:.1f} ± "
          f"{calib['sigma']['U_mm']:.1f}, d {calib['d_mm']:.3f} ± {calib['sigma']['d_mm']:.3f}; "
          f"RMS {[round(v['rms_reprojection_px'], 3) for v in calib['views']]} px")
    assert abs(calib["w_mm"] / W_MM - 1) < 0.005, f"w {calib['w_mm']}"
    assert abs(calib["U_mm"] / U_MM - 1) < 0.01, f"U {calib['U_mm']}"
    assert abs(calib["d_mm"] / D_MM - 1) < 0.03, f"d {calib['d_mm']}"
    assert calib["model_selection"]["theta_F"]["justified"] is False, "untilted photographs: no θF"


def test_calib_file_round_trip_and_atomic_write(tmp_path):
    from tiltfit.files.calib import CalibFileError, write_calib

    data = {"pixel_pitch_mm": PITCH, "image_size_px": [5472, 3648], "principal_point_px": [2735.5, 1823.5],
            "w_mm": W_MM, "U_mm": U_MM, "d_mm": D_MM, "theta_F_deg": 10.0,
            "views": [{"image": "a.png", "R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "T_mm": [0, 0, 600],
                       "rms_blur_px": float("nan")}]}
    path = str(tmp_path / "c.json")
    write_calib(path, data)
    back = read_calib(path)
    assert back["views"][0]["rms_blur_px"] is None, "non-finite numbers are written as null"
    assert os.listdir(tmp_path) == ["c.json"], "no temporary file left"
    cam = camera_from_calib(back)
    assert abs(cam.summary()["theta_F_deg"] - 10.0) < 1e-12 and cam.n_views == 1, "camera from the file"
    (tmp_path / "bad.json").write_text(json.dumps({**data, "w_mm": -1}))
    with pytest.raises(CalibFileError, match="w_mm: expected a positive number"):
        read_calib(str(tmp_path / "bad.json"))


@pytest.mark.slow
def test_training_example_runs_and_resumes(tmp_path, monkeypatch, capsys):
    here = os.path.dirname(os.path.abspath(__file__))
    example = os.path.join(here, "..", "..", "examples", "train_calibration.py")
    with open(os.path.join(os.path.dirname(example), "calib_config.json")) as f:
        cfg = json.load(f)
    cfg["data"]["n_views"] = 4
    cfg["optim"].update(adam_steps=20, lbfgs_steps=2, log_every=10, checkpoint_every=10)
    config = tmp_path / "cfg.json"
    config.write_text(json.dumps(cfg))
    # The script as `python example ...` runs it (its `__main__` guard, sys.argv, sys.exit), in this process: a
    # new interpreter for each of the two runs would import torch and tiltfit again, which is not what is tested.
    first = _run_script(example, ["--config", str(config), "--out", str(tmp_path)], monkeypatch, capsys)
    assert first.returncode == 0, first.stderr
    assert "step   10 [adam]" in first.stdout and "final report" in first.stdout, first.stdout
    assert os.path.exists(tmp_path / cfg["output"]["checkpoint"]), "checkpoint written"
    again = _run_script(example, ["--config", str(config), "--out", str(tmp_path), "--resume"], monkeypatch, capsys)
    assert again.returncode == 0 and "resumed from" in again.stderr, again.stderr


def _run_script(path, args, monkeypatch, capsys):
    """`python path *args` run in this process: its exit status and what it printed (a traceback fails the test)."""
    import runpy
    from types import SimpleNamespace

    capsys.readouterr()
    monkeypatch.setattr(sys, "argv", [path, *args])
    try:
        runpy.run_path(path, run_name="__main__")
        code = 0
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    out, err = capsys.readouterr()
    return SimpleNamespace(returncode=code, stdout=out, stderr=err)


def test_truncated_png_detect_exit_2_one_line_no_output(tmp_path, capfd):
    img = np.full((240, 360, 3), 0.5, dtype=np.float32)
    img[::20] = 0.05
    png = tmp_path / "board.png"
    write_image(str(png), img)
    data = png.read_bytes()
    png.write_bytes(data[: len(data) // 2])
    tjson = tmp_path / "target.json"
    TARGET.save(str(tjson))  # a file that cannot be read: exit status 2, one line on stderr, no output file
    out = tmp_path / "det.json"
    # tiltfit's main in this process (`python -m tiltfit` itself is test_python_m_tiltfit's); capfd reads file
    # descriptor 2, so a C library's message (libpng's) counts as a line, and so does a Python warning.
    import warnings

    capfd.readouterr()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rc = main(["detect", str(png), "--target", str(tjson), "-o", str(out)])
    stderr = capfd.readouterr().err + "".join(f"{w.category.__name__}: {w.message}\n" for w in caught)
    assert rc == 2, (rc, stderr)
    lines = stderr.strip().splitlines()
    assert len(lines) == 1, stderr
    assert lines[0].startswith("tiltfit: ") and "board.png" in lines[0], lines[0]
    assert not out.exists()
    assert not [f for f in os.listdir(tmp_path) if f.startswith(".tiltfit-")]
