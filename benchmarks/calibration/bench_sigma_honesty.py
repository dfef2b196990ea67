"""σ honesty (issue 22): predicted against empirical σ for every parameter, ours (the classical σ and the
per-view cluster-robust σ, `tiltfit.uncertainty.covariance`) and OpenCV's `calibrateCameraExtended` (stdDeviationsIntrinsics),
on the same corners, in one run.

    python benchmarks/calibration/bench_sigma_honesty.py [--draws 60] [--out benchmarks/results/sigma_honesty]

Monte Carlo: a capture from an independent generator (pinhole + Brown k1 projector and a thin-lens blur-circle
formula written here, not tiltfit's camera), 8 views of a 7×5 board, per-view correlated corner errors (a
random shift 0.3 px and affine warp 3e-4 of each view's corners, a random 2 % scale of its blur widths) plus
independent noise (0.05 px; blur 3 %); each draw is fitted ("joint": w, U, d, θF, principal point, k1, poses)
and OpenCV calibrates the same corners (aspect ratio fixed, k1 only). Ratio = RMS of the predicted σ over the draws
/ standard deviation of the estimates (1 is honest; the test accepts 0.8–1.25).

Real subsets: GoPro (36 photos, rational distortion) split into 3 interleaved groups, industrial_ds1 (20 photos,
opencv5) into 2 halves; each calibrated alone by us and by OpenCV. Spread/σ pooled over the pairs:
sqrt(mean over pairs (a, b) of Δ² / (σ_a² + σ_b²)) (1 is honest; with 2–3 subsets it is noisy: one or two
independent differences per parameter).

Real poses: industrial_ds1 (20 photos) calibrated with the flat board and with the fitted board (what `board
auto` chooses there: RMS 0.39 -> 0.05-0.09 px). The flat fit's poses minus the fitted board's, less their mean
over the views (the shift the globals' difference causes, the same for every view), over the flat fit's pose σ:
the RMS of that z over the views (1 when each view's own pose σ covers what the board's shape does to it).
"""
from __future__ import annotations

import itertools
import math
import os
import sys
import time

import cv2
import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from tests.real_detections import REAL, observations  # noqa: E402
from benchmarks.results_io import run_benchmark, write_lines  # noqa: E402

from tiltfit.calibrate.flow import calibrate  # noqa: E402
from tiltfit.calibrate.fit import FitOptions  # noqa: E402
from tiltfit.calibrate.model import (PAPER_LENS, PAPER_SENSOR, Observations, axis_angle_to_matrix,  # noqa: E402
                           board_points_mm, random_poses)

W_MM, U_MM, D_MM = PAPER_LENS["w_mm"], PAPER_LENS["U_mm"], PAPER_LENS["d_mm"]
PITCH = PAPER_SENSOR["pixel_pitch_mm"]
SIZE = PAPER_SENSOR["image_size_px"]
BOARD = board_points_mm(7, 5, 25.0).numpy()
V = 8
CX, CY = (SIZE[0] - 1) / 2 + 12.0, (SIZE[1] - 1) / 2 - 8.0
K1 = -0.05
OPENCV_FLAGS = {"k1": cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
                "opencv5": 0, "rational": cv2.CALIB_RATIONAL_MODEL,
                "rational5": cv2.CALIB_RATIONAL_MODEL | cv2.CALIB_FIX_K3 | cv2.CALIB_FIX_K5 | cv2.CALIB_FIX_K6}
# OpenCV's stdDeviationsIntrinsics order: fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6, ...
CV_INDEX = {"f_px": 0, "cx_px": 2, "cy_px": 3, "k1": 4}


def capture():
    rvec, T = random_poses(V, 3)
    R, T = axis_angle_to_matrix(rvec).numpy(), T.numpy()
    pc = np.einsum("vij,nj->vni", R, BOARD) + T[:, None, :]
    xy = pc[..., :2] / pc[..., 2:3]
    xy = xy * (1 + K1 * (xy ** 2).sum(-1, keepdims=True))
    uv = np.stack([CX + W_MM / PITCH * xy[..., 0], CY + W_MM / PITCH * xy[..., 1]], -1)
    w_z = 1.0 / (1.0 / (W_MM * U_MM / (W_MM + U_MM)) - 1.0 / pc[..., 2])
    return uv, D_MM * np.abs(W_MM - w_z) / w_z / PITCH


def draw(uv, blur, rng):
    c = uv.mean(1, keepdims=True)
    A = rng.normal(0, 3e-4, (V, 2, 2))
    uv = uv + rng.normal(0, 0.3, (V, 1, 2)) + np.einsum("vij,vnj->vni", A, uv - c) + rng.normal(0, 0.05, uv.shape)
    blur = blur * (1 + rng.normal(0, 0.02, (V, 1))) + rng.normal(0, 0.03 * np.median(blur), blur.shape)
    return Observations(torch.tensor(BOARD), torch.tensor(uv), torch.tensor(blur), SIZE, PITCH)


def ours_row(d: dict, pitch: float, pose=None) -> dict:
    out = {"f_px": d["w_mm"] / pitch, "cx_px": d["principal_point_px"][0], "cy_px": d["principal_point_px"][1],
           "k1": d["distortion"][0] if isinstance(d.get("distortion"), list) else None}
    for k in ("w_mm", "U_mm", "d_mm", "theta_F_deg", "theta_L_deg", "blur_offset_px"):
        out[k] = d.get(k)
    return out


def values_row(res, pitch: float) -> dict:
    row = ours_row(res.values | {"distortion": [float(c) for c in res.camera.distortion.detach()]}, pitch)
    row["rvec0_deg"] = math.degrees(float(res.camera.rvec.detach()[0, 0]))
    row["Tz0_mm"] = float(res.camera.T_mm.detach()[0, 2])
    return row


def sigma_row(res, sig: dict, view_sig, pitch: float) -> dict:
    row = ours_row(sig, pitch)
    row["rvec0_deg"] = view_sig[0]["sigma_rvec_deg"][0] if view_sig else None
    row["Tz0_mm"] = view_sig[0]["sigma_T_mm"][2] if view_sig else None
    return row


def opencv(obs: Observations, model: str, views=None):
    """cv2.calibrateCameraExtended on the observations (each view's detected corners); {key: (value, σ)}."""
    idx = range(obs.n_views) if views is None else views
    obj, img = [], []
    for v in idx:
        ok = np.isfinite(obs.corners_px[v].numpy()).all(-1)
        obj.append(obs.points_mm.numpy()[ok].astype(np.float32))
        img.append(obs.corners_px[v].numpy()[ok].astype(np.float32))
    W, H = obs.image_size_px
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    rms, K, dist, rv, tv, sd_i, sd_e, per_view = cv2.calibrateCameraExtended(
        obj, img, (W, H), None, None, flags=OPENCV_FLAGS[model] | cv2.CALIB_FIX_ASPECT_RATIO, criteria=crit)
    sd_i, sd_e = sd_i.ravel(), sd_e.ravel()
    vals = {"f_px": K[0, 0], "cx_px": K[0, 2], "cy_px": K[1, 2], "k1": dist.ravel()[0],
            "rvec0_deg": math.degrees(rv[0].ravel()[0]), "Tz0_mm": tv[0].ravel()[2]}
    sig = {k: sd_i[i] for k, i in CV_INDEX.items()} | {"rvec0_deg": math.degrees(sd_e[0]), "Tz0_mm": sd_e[5]}
    sig["f_px"] = max(sd_i[0], sd_i[1])  # with the aspect ratio fixed OpenCV reports fx's σ as 0 and fy's
    return {k: float(v) for k, v in vals.items()}, {k: float(v) for k, v in sig.items()}


def monte_carlo(n_draws: int) -> dict:
    uv, blur = capture()
    rng = np.random.default_rng(0)
    opts = FitOptions(model_selection=False, free_principal_point=True, distortion="k1", max_rms_px=None)
    rows = {"ours": [], "ours_new_sigma": [], "ours_classical_sigma": [], "opencv": [], "opencv_sigma": []}
    t0 = time.perf_counter()
    for i in range(n_draws):
        obs = draw(uv, blur, rng)
        res = calibrate(obs, "joint", options=opts)
        rows["ours"].append(values_row(res, PITCH))
        rows["ours_new_sigma"].append(sigma_row(res, res.sigma, res.views and [
            {"sigma_rvec_deg": v["sigma_rvec_deg"], "sigma_T_mm": v["sigma_T_mm"]} for v in res.views], PITCH))
        rows["ours_classical_sigma"].append(sigma_row(res, res.sigma_classical, None, PITCH))
        v, s = opencv(obs, "k1")
        rows["opencv"].append(v)
        rows["opencv_sigma"].append(s)
        if (i + 1) % 10 == 0:
            print(f"  {i + 1}/{n_draws} draws, {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
    truth = {"f_px": W_MM / PITCH, "cx_px": CX, "cy_px": CY, "k1": K1, "w_mm": W_MM, "U_mm": U_MM, "d_mm": D_MM,
             "theta_F_deg": 0.0, "theta_L_deg": 0.0}
    table = {}
    for k in rows["ours"][0]:
        est = np.array([r[k] for r in rows["ours"]], dtype=float)
        emp = float(est.std(ddof=1))
        entry = {"empirical": emp, "truth": truth.get(k), "mean": float(est.mean())}
        for name in ("new", "classical"):
            s = np.array([r[k] for r in rows[f"ours_{name}_sigma"]], dtype=float)
            entry[f"ours_{name}"] = float(np.sqrt(np.mean(s ** 2)))
            entry[f"ratio_{name}"] = entry[f"ours_{name}"] / emp if emp > 0 else None
        if k in rows["opencv"][0]:
            ec = np.array([r[k] for r in rows["opencv"]], dtype=float)
            sc = np.array([r[k] for r in rows["opencv_sigma"]], dtype=float)
            entry |= {"opencv_empirical": float(ec.std(ddof=1)), "opencv_predicted": float(np.sqrt(np.mean(sc ** 2)))}
            entry["ratio_opencv"] = entry["opencv_predicted"] / entry["opencv_empirical"]
        table[k] = entry
    return {"draws": n_draws, "views": V, "board": "7x5", "table": table,
            "seconds": time.perf_counter() - t0}


def real_subsets(name: str, pitch: float, model: str, k: int, board: str = "flat") -> dict:
    obs, _ = observations(os.path.join(REAL, name), pitch)
    opts = FitOptions(distortion=model, free_principal_point=True, model_selection=False, max_rms_px=None,
                      board=board)
    groups = [list(range(g, obs.n_views, k)) for g in range(k)]
    fits, cvs = [], []
    for views in groups:
        res = calibrate(obs.subset(views), "unified", options=opts)
        fits.append((values_row(res, pitch), ours_row(res.sigma | {}, pitch), ours_row(res.sigma_classical, pitch),
                     res.sigma_model))
        cvs.append(opencv(obs, model, views))
    table = {}
    for key in ("f_px", "cx_px", "cy_px", "k1"):
        entry = {}
        for label, vals, sig in (("ours_new", [f[0] for f in fits], [f[1] for f in fits]),
                                 ("ours_classical", [f[0] for f in fits], [f[2] for f in fits]),
                                 ("opencv", [c[0] for c in cvs], [c[1] for c in cvs])):
            z = [(vals[a][key] - vals[b][key]) ** 2 / (sig[a][key] ** 2 + sig[b][key] ** 2)
                 for a, b in itertools.combinations(range(k), 2)]
            entry[label] = math.sqrt(float(np.mean(z)))
        entry["values_ours"] = [f[0][key] for f in fits]
        entry["sigma_new"] = [f[1][key] for f in fits]
        entry["sigma_classical"] = [f[2][key] for f in fits]
        entry["values_opencv"] = [c[0][key] for c in cvs]
        entry["sigma_opencv"] = [c[1][key] for c in cvs]
        table[key] = entry
    pooled = {}
    for label in ("ours_new", "ours_classical", "opencv"):
        pooled[label] = math.sqrt(float(np.mean([table[k][label] ** 2 for k in ("f_px", "cx_px", "cy_px")])))
    return {"set": name, "model": model, "board": board, "subsets": k, "views": [len(g) for g in groups], "table": table,
            "pooled_f_cx_cy": pooled, "design_effect": [f[3].get("design_effect") for f in fits]}


POSE_KEYS = ("rx_deg", "ry_deg", "rz_deg", "Tx_mm", "Ty_mm", "Tz_mm")


def real_poses(name: str = "industrial_ds1", pitch: float = 0.0048, model: str = "opencv5") -> dict:
    """The flat-board fit's per-view pose errors (against the fitted board's poses, common shift removed) over
    their σ: ours (classical, views) and OpenCV's on the same corners (module docstring)."""
    from renderer import matrix_to_axis_angle

    obs, _ = observations(os.path.join(REAL, name), pitch)

    def fit(board, sigma_model):
        opts = FitOptions(distortion=model, free_principal_point=True, model_selection=False, max_rms_px=None,
                          board=board, sigma_model=sigma_model)
        r = calibrate(obs, "unified", options=opts)
        pose = [[math.degrees(float(a)) for a in matrix_to_axis_angle(torch.tensor(v["R"]))] + list(v["T_mm"])
                for v in r.views]
        return np.array(pose), np.array([v["sigma_rvec_deg"] + v["sigma_T_mm"] for v in r.views])

    flat, sig_views = fit("flat", "views")
    fitted, _ = fit("auto", "views")
    _, sig_classical = fit("flat", "classical")
    obj, img = [], []
    for v in range(obs.n_views):
        ok = np.isfinite(obs.corners_px[v].numpy()).all(-1)
        obj.append(obs.points_mm.numpy()[ok].astype(np.float32))
        img.append(obs.corners_px[v].numpy()[ok].astype(np.float32))
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    sd_e = cv2.calibrateCameraExtended(obj, img, tuple(obs.image_size_px), None, None, criteria=crit,
                                       flags=OPENCV_FLAGS[model] | cv2.CALIB_FIX_ASPECT_RATIO)[6].reshape(-1, 6)
    sig_cv = np.concatenate([np.degrees(sd_e[:, :3]), sd_e[:, 3:]], 1)
    d = flat - fitted
    d = d - d.mean(0)
    table = {k: {"scatter": float(d[:, i].std()),
                 **{label: float(np.sqrt(np.mean((d[:, i] / sig[:, i]) ** 2)))
                    for label, sig in (("ours_classical", sig_classical), ("ours_new", sig_views), ("opencv", sig_cv))},
                 "median_sigma_new": float(np.median(sig_views[:, i]))}
             for i, k in enumerate(POSE_KEYS)}
    return {"set": name, "views": obs.n_views, "table": table}


def write_markdown(path: str, res: dict) -> None:
    mc = res["monte_carlo"]
    lines = ["# σ honesty: predicted against empirical σ", "",
             "Generated by `python benchmarks/calibration/bench_sigma_honesty.py` (module docstring: what is measured). Ratio = "
             "predicted σ / empirical spread (1: honest; < 1: σ too small).", "",
             f"## Monte Carlo: {mc['draws']} draws, {mc['views']} views of a {mc['board']} board, independent "
             "generator, per-view correlated corner errors", "",
             "| parameter | empirical spread | ours, classical σ (ratio) | ours, views σ (ratio) | OpenCV spread | "
             "OpenCV σ (ratio) |", "|---|---|---|---|---|---|"]
    for k, e in mc["table"].items():
        if e["empirical"] == 0 or e["ours_new"] != e["ours_new"]:
            continue
        cv = (f"{e['opencv_empirical']:.4g} | {e['opencv_predicted']:.4g} ({e['ratio_opencv']:.2f})"
              if "ratio_opencv" in e else "— | —")
        cls = "—" if e["ours_classical"] != e["ours_classical"] else \
            f"{e['ours_classical']:.4g} ({e['ratio_classical']:.2f})"
        lines.append(f"| {k} | {e['empirical']:.4g} | {cls} | {e['ours_new']:.4g} ({e['ratio_new']:.2f}) | {cv} |")
    lines += ["", "Pose rows (rvec0_deg, Tz0_mm: view 0): the views model's pose σ = the globals' part plus the own "
              "part from a random affine error per view estimated from the residuals (`tiltfit.uncertainty.covariance`); the "
              "classical pose σ is not reported separately (—).", ""]
    lines += ["## Real subsets: spread/σ pooled over pairs, sqrt(mean Δ²/(σa² + σb²))", "",
              "| set | parameter | ours, classical σ | ours, views σ | OpenCV σ |", "|---|---|---|---|---|"]
    for r in res["real"]:
        for k, e in r["table"].items():
            lines.append(f"| {r['set']} ({r['subsets']} subsets, {r['model']}, board {r.get('board', 'flat')}) | {k} | {e['ours_classical']:.2f} | "
                         f"{e['ours_new']:.2f} | {e['opencv']:.2f} |")
        p = r["pooled_f_cx_cy"]
        lines.append(f"| {r['set']} (board {r.get('board', 'flat')}) | pooled f, cx, cy | {p['ours_classical']:.2f} | {p['ours_new']:.2f} | "
                     f"{p['opencv']:.2f} |")
    lines += ["", "Per-subset values and σ are in the JSON (`real[].table`).", ""]
    if res.get("real_poses"):
        rp = res["real_poses"]
        lines += [f"## Real poses: {rp['set']} ({rp['views']} views), flat-board fit against the fitted board's poses",
                  "", "Per-view pose error (common shift removed) / the flat fit's pose σ, RMS over the views "
                  "(1: honest; > 1: σ too small).", "",
                  "| pose | scatter | ours, classical σ | ours, views σ (median σ) | OpenCV σ |", "|---|---|---|---|---|"]
        for k, e in rp["table"].items():
            lines.append(f"| {k} | {e['scatter']:.3g} | {e['ours_classical']:.2f} | {e['ours_new']:.2f} "
                         f"({e['median_sigma_new']:.3g}) | {e['opencv']:.2f} |")
        lines.append("")
    write_lines(path, lines)


def measure(args) -> dict:
    torch.set_num_threads(1)
    return {"monte_carlo": monte_carlo(args.draws),
            "real": [real_subsets("gopro_wide", 0.00155, "rational", 3),
                     real_subsets("gopro_wide", 0.00155, "rational5", 3, board="auto"),
                     real_subsets("industrial_ds1", 0.0048, "opencv5", 2),
                     real_subsets("industrial_ds1", 0.0048, "opencv5", 2, board="auto")],
            "real_poses": real_poses()}


def main(argv=None) -> int:
    return run_benchmark(__doc__, "sigma_honesty", measure, write_markdown, argv, draws=60)


if __name__ == "__main__":
    sys.exit(main())
