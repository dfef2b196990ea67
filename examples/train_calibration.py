"""Calibrate a tilt-lens camera the way one trains a model: config file, optimizer loop, logs, checkpoints.

Uses only tiltfit's public API: `LensCamera` (an nn.Module whose parameters are the lens and the poses),
`synthesize_observations`, `loss`, `tiltfit.calibrate.start.initialize` (PnP poses, homography focal length, linear blur
scan) and, for comparison, `tiltfit.calibrate.flow.calibrate` (Levenberg–Marquardt).

    python examples/train_calibration.py [--config examples/calib_config.json] [--resume] [--out DIR]

By default the observations are synthetic: the paper's camera with the lens tilted by `data.theta_L_deg`
about its centre (U and θF from the exact thin-lens relations), `data.n_views` random board poses, Gaussian
noise on corners and blur widths. The loop runs Adam for `optim.adam_steps` steps, then L-BFGS for
`optim.lbfgs_steps` steps, logs the loss every `optim.log_every` steps (stdout and a CSV), writes a
checkpoint every `optim.checkpoint_every` steps, and `--resume` continues from the last checkpoint.
The final report compares the result with the truth and with the Levenberg–Marquardt fit.
"""
from __future__ import annotations

import argparse
import csv
import json
import math
import os
import sys
import time

import torch

from tiltfit.calibrate.flow import calibrate
from tiltfit.calibrate.fit import FitOptions
from tiltfit.calibrate.model import LensCamera, board_points_mm, loss, random_poses, synthesize_observations
from tiltfit.calibrate.start import initialize

HERE = os.path.dirname(os.path.abspath(__file__))


def make_data(cfg: dict):
    """The true camera and its synthetic observations, as the config describes."""
    d, c = cfg["data"], cfg["camera"]
    rvec, T = random_poses(d["n_views"], d["pose_seed"])
    truth = LensCamera.from_tilted_lens(d["n_views"], c["image_size_px"], c["pixel_pitch_mm"], c["w_mm"],
                                            c["f_mm"], c["d_mm"], math.radians(d["theta_L_deg"]), rvec=rvec,
                                            T_mm=T)
    b = d["board"]
    obs = synthesize_observations(truth, board_points_mm(b["nx"], b["ny"], b["pitch_mm"]), d["noise_px"],
                                  d["noise_blur_px"], seed=d["noise_seed"])
    return truth, obs


def save_checkpoint(path, camera, optimizer, phase, step, log_rows):
    tmp = path + ".tmp"
    torch.save({"camera": camera.state_dict(), "optimizer": optimizer.state_dict(), "phase": phase,
                "step": step, "log": log_rows}, tmp)
    os.replace(tmp, path)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=os.path.join(HERE, "calib_config.json"))
    ap.add_argument("--out", default=".", help="folder for the checkpoint and the log [.]")
    ap.add_argument("--resume", action="store_true", help="continue from the checkpoint in --out")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    with open(args.config) as f:
        cfg = json.load(f)
    fit, opt_cfg = cfg["fit"], cfg["optim"]
    os.makedirs(args.out, exist_ok=True)
    ckpt_path = os.path.join(args.out, cfg["output"]["checkpoint"])
    log_path = os.path.join(args.out, cfg["output"]["log"])

    truth, obs = make_data(cfg)
    # Start like the Levenberg–Marquardt fit does; the optimizer takes it from there.
    camera = initialize(obs, "joint", options=FitOptions(blur_model=fit["blur_model"]))
    camera.freeze("all").free(*fit["free"])
    params = [p for p in camera.parameters() if p.requires_grad]
    sigmas = dict(sigma_corner_px=fit["sigma_corner_px"], sigma_blur_px=fit["sigma_blur_px"],
                  robust=fit["robust"])

    phase, step, log_rows = "adam", 0, []
    adam = torch.optim.Adam(params, lr=opt_cfg["adam_lr"])
    lbfgs = torch.optim.LBFGS(params, lr=1.0, max_iter=20, line_search_fn="strong_wolfe")
    if args.resume and os.path.exists(ckpt_path):
        ck = torch.load(ckpt_path, weights_only=False)
        camera.load_state_dict(ck["camera"])
        phase, step, log_rows = ck["phase"], ck["step"], ck["log"]
        (adam if phase == "adam" else lbfgs).load_state_dict(ck["optimizer"])
        print(f"resumed from {ckpt_path}: phase {phase}, step {step}", file=sys.stderr)

    def closure():
        lbfgs.zero_grad()
        value = loss(camera, obs, **sigmas)
        value.backward()
        return value

    def record(value):
        s = camera.summary()
        row = {"step": step, "phase": phase, "loss": float(value), "w_mm": s["w_mm"], "U_mm": s["U_mm"],
               "d_mm": s["d_mm"], "theta_L_deg": s["theta_L_deg"]}
        log_rows.append(row)
        if step % opt_cfg["log_every"] == 0:
            print(f"step {step:4d} [{phase}] loss {row['loss']:.6g}  w {row['w_mm']:.3f}  U {row['U_mm']:.2f}  "
                  f"d {row['d_mm']:.3f}  θL {row['theta_L_deg']:.4f}°", flush=True)

    t0 = time.perf_counter()
    total = opt_cfg["adam_steps"] + opt_cfg["lbfgs_steps"]
    while step < total:
        if phase == "adam" and step >= opt_cfg["adam_steps"]:
            phase = "lbfgs"
        if phase == "adam":
            adam.zero_grad()
            value = loss(camera, obs, **sigmas)
            value.backward()
            adam.step()
        else:
            value = lbfgs.step(closure)
        step += 1
        record(value.detach())
        if step % opt_cfg["checkpoint_every"] == 0 or step == total:
            save_checkpoint(ckpt_path, camera, adam if phase == "adam" else lbfgs, phase, step, log_rows)
    with open(log_path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(log_rows[0]))
        writer.writeheader()
        writer.writerows(log_rows)

    lm = calibrate(obs, "joint", options=FitOptions(blur_model=fit["blur_model"], model_selection=False))
    s, t = camera.summary(), truth.summary()
    print(f"\nfinal report ({time.perf_counter() - t0:.1f} s of optimisation; log {log_path})")
    print(f"{'':14s}{'truth':>12s}{'torch optim':>14s}{'LM':>12s}{'LM 1σ':>10s}")
    for key in ("w_mm", "U_mm", "d_mm", "theta_F_deg", "theta_L_deg", "theta_L_paper_deg"):
        print(f"{key:14s}{t[key]:12.4f}{s[key]:14.4f}{lm.values[key]:12.4f}{lm.sigma[key]:10.4f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
