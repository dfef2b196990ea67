"""The starting camera of a calibration: focal length from homographies, poses by PnP, blur parameters by a
linear scan.

    initialize(obs, mode, init=None, options=FitOptions(), blur=True) -> LensCamera
    start_blur(cam, obs, mode, init=None)                              -> cam (U, d, θF set in place)
    focal_from_homographies(obs, principal_point_px=None)              -> focal length, pixels, or None
    poses_from_pnp(obs, focal_px, principal_point_px, distortion=None) -> rvec (V, 3), T (V, 3, mm)
    blur_from_scan(p_cam, blur_px, mask, w_mm, pixel_pitch_mm, fit_tilt) -> U (mm), d (mm), θF (rad)
"""
from __future__ import annotations

import math

import numpy as np
import torch

from renderer.cameras import camera_matrix, image_centre_px

from tiltfit.calibrate.fit import FitError, FitOptions
from tiltfit.calibrate.model import Observations, LensCamera

#: Entries (candidates × widths) of one block of `blur_from_scan`'s table: 2M float64, 16 MB per temporary.
SCAN_ENTRIES = 1 << 21


def focal_from_homographies(obs: Observations, principal_point_px=None) -> float | None:
    """Focal length in pixels from the board homographies, principal point known and square pixels.

    Each homography H ~ K [r1 r2 t] gives two linear equations in 1/F² (r1 ⟂ r2, |r1| = |r2|); they are
    solved together in the least-squares sense (Zhang's method with the principal point fixed). Returns
    None for a planar target seen only fronto-parallel (no solution) or a non-planar target.
    """
    import cv2

    W, H = obs.image_size_px
    c = np.array(principal_point_px if principal_point_px is not None else image_centre_px(W, H))
    s = float(max(W, H))  # pixel coordinates in units of the image size keep the equations O(1)
    pts = obs.points_mm.numpy()
    if np.ptp(pts[:, 2]) > 1e-9:
        return None
    rows_a, rows_c = [], []
    mask = obs.corner_mask.numpy()  # once: the property checks every view's corners
    for v in range(obs.n_views):
        m = mask[v]
        if m.sum() < 4:
            continue
        Hm, _ = cv2.findHomography(pts[m, :2] / s, (obs.corners_px[v].numpy()[m] - c) / s, 0)
        if Hm is None:
            continue
        Hm = Hm / np.linalg.norm(Hm)
        h1, h2 = Hm[:, 0], Hm[:, 1]
        rows_a += [h1[0] * h2[0] + h1[1] * h2[1], h1[0] ** 2 + h1[1] ** 2 - h2[0] ** 2 - h2[1] ** 2]
        rows_c += [h1[2] * h2[2], h1[2] ** 2 - h2[2] ** 2]
    a, cc = np.array(rows_a), np.array(rows_c)
    if len(a) == 0 or float(a @ a) <= 0:
        return None
    inv_f2 = -float(a @ cc) / float(a @ a)
    if not inv_f2 > 0:
        return None
    F = s / math.sqrt(inv_f2)
    return F if 0.05 * s < F < 50 * s else None


def poses_from_pnp(obs: Observations, focal_px: float, principal_point_px,
                   distortion=None) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-view rvec (V, 3) and T (V, 3, mm) by OpenCV's solvePnP on the detected corners.

    `distortion`: None or up to 8 Brown–Conrady coefficients in OpenCV's order."""
    import cv2

    K = camera_matrix(focal_px, principal_point_px)
    dist = None if distortion is None or not any(float(v) for v in distortion) else \
        np.array([float(v) for v in distortion], dtype=np.float64)
    pts = obs.points_mm.numpy()
    rv, tv = [], []
    mask = obs.corner_mask.numpy()  # once: the property checks every view's corners
    for v in range(obs.n_views):
        m = mask[v]
        if m.sum() < 4:
            raise FitError(f"{obs.names[v]}: only {int(m.sum())} corners detected, at least 4 are needed")
        planar = np.ptp(pts[m, 2]) < 1e-9
        # IPPE for a flat board; SQPnP where it fails (a board exactly facing the camera gave IPPE NaNs with
        # opencv-python-headless 5.0.0 on a GPU machine), then the iterative method.
        for flags in ([cv2.SOLVEPNP_IPPE] if planar else []) + [cv2.SOLVEPNP_SQPNP, cv2.SOLVEPNP_ITERATIVE]:
            try:  # OpenCV asserts on what it cannot solve (e.g. corners undistorted by an absurd start)
                ok, r, t = cv2.solvePnP(pts[m], obs.corners_px[v].numpy()[m], K, dist, flags=flags)
            except cv2.error:
                continue
            if ok and np.isfinite(r).all() and np.isfinite(t).all():
                break
        else:
            raise FitError(f"{obs.names[v]}: cannot find the board's pose")
        # The iterative refinement only polishes the first pose (the joint fit refines it again); some OpenCV
        # builds refuse it where the first pose is fine (seen with opencv-python-headless 5.0.0 on a GPU
        # machine), so its failure keeps the first pose instead of failing the calibration.
        try:
            ok2, r2, t2 = cv2.solvePnP(pts[m], obs.corners_px[v].numpy()[m], K, dist, r.copy(), t.copy(), True,
                                       cv2.SOLVEPNP_ITERATIVE)
        except cv2.error:
            ok2 = False
        if ok2 and np.isfinite(r2).all() and np.isfinite(t2).all():
            r, t = r2, t2
        if not (np.isfinite(r).all() and np.isfinite(t).all()):
            raise FitError(f"{obs.names[v]}: cannot find the board's pose (degenerate corner layout)")
        rv.append(r.ravel())
        tv.append(t.ravel())
    return torch.tensor(np.array(rv)), torch.tensor(np.array(tv))


def blur_from_scan(p_cam: torch.Tensor, blur_px: torch.Tensor, mask: torch.Tensor, w_mm: float,
                   pixel_pitch_mm: float, fit_tilt: bool) -> tuple[float, float, float]:
    """Starting U, d (mm) and θF (rad) by a scan: for each candidate U (and tan θF) the blur model is linear in
    the scale w·d, solved in closed form; the candidate with the least squared error wins.

    Uses b = w d |U + y tan θF − z| / (U z) (the first-order model, eq (2) for θF = 0).
    """
    y = p_cam[..., 1][mask].double()
    z = p_cam[..., 2][mask].double()
    b = blur_px[mask].double() * pixel_pitch_mm
    if b.numel() < 3:
        raise FitError(f"only {b.numel()} blur measurements, at least 3 are needed")
    zmin, zmax = float(z.min()), float(z.max())
    U = torch.exp(torch.linspace(math.log(0.3 * zmin), math.log(3.0 * zmax), 241, dtype=torch.float64))
    tans = torch.tan(torch.deg2rad(torch.arange(-80.0, 80.5, 1.0, dtype=torch.float64))) if fit_tilt \
        else torch.zeros(1, dtype=torch.float64)
    best = (math.inf, None, None, None)
    # candidates U in chunks: a (241, n) table of thousands of views' widths would take a GB per temporary
    chunk = max(1, SCAN_ENTRIES // max(b.numel(), 1))
    for t in tans:
        for Uc in U.split(chunk):
            m = torch.abs(Uc[:, None] + y[None] * t - z[None]) / (Uc[:, None] * z[None])  # (chunk, n)
            c = (m @ b) / (m * m).sum(-1).clamp(min=1e-300)
            rss = ((c[:, None] * m - b[None]) ** 2).sum(-1)
            i = int(torch.argmin(rss))
            if float(rss[i]) < best[0]:
                best = (float(rss[i]), float(Uc[i]), float(c[i]), float(torch.atan(t)))
    _, U0, wd, th = best
    if wd is None or not wd > 0:
        raise FitError("cannot start the blur parameters: the blur widths show no defocus")
    return U0, wd / w_mm, th


def _blur_rss(cam: LensCamera, obs: Observations, U_mm: float, d_mm: float, theta_F: float) -> float:
    with torch.no_grad():
        cam.set_lens(U_mm=U_mm, d_mm=d_mm, theta_F=theta_F)
        b = cam.blur(obs.points_mm)
        r = torch.where(obs.blur_mask, b - torch.nan_to_num(obs.blur_px), torch.zeros_like(b))
        rss = float((r * r).sum())
    return rss if math.isfinite(rss) else math.inf


def initialize(obs: Observations, mode: str = "unified", init: LensCamera | None = None,
               options: FitOptions = FitOptions(), blur: bool = True, poses=None) -> LensCamera:
    """A starting camera for `calibrate`.

    Poses from PnP with w from `init`, else the nominal focal length, else the homographies; or `poses`
    ((rvec (V, 3), T_mm (V, 3)) of `obs`'s views, e.g. a fit's on more views) where given. The blur
    parameters are the best (least squared blur error) of: `init`'s U, d, θF; the linear scan
    (`blur_from_scan`, θF scanned too in `joint` mode) unless `tilt` mode holds U and d; and, in `tilt` mode,
    a scan of θF over ±80° with `init`'s U and d. With `blur` False the blur parameters are `init`'s (or
    U = 600 mm, d = 10 mm) and θF = 0: they are not fitted then. `init`'s distortion is kept.
    """
    W, H = obs.image_size_px
    dist = None
    if init is not None:  # read, never changed: no copy
        with torch.no_grad():
            pp = [float(v) for v in init.principal_point_px]
            w_mm = float(init.w_mm)
            dist = [float(v) for v in init.distortion]
    else:
        pp = list(image_centre_px(W, H))
        if options.nominal_focal_mm is not None:
            w_mm = float(options.nominal_focal_mm)
        else:
            F = focal_from_homographies(obs, pp)
            if F is None:
                raise FitError("cannot estimate the focal length from these views (too fronto-parallel, or the "
                               "target does not match the detections); give a nominal focal length")
            w_mm = F * obs.pixel_pitch_mm
    rvec, T = poses if poses is not None else poses_from_pnp(obs, w_mm / obs.pixel_pitch_mm, pp, dist)
    U0, d0 = (float(init.U_mm.detach()), float(init.d_mm.detach())) if init is not None else (600.0, 10.0)
    if not U0 > 0:  # a start beyond infinity (1/U ≤ 0) is focus at infinity: never a negative U in a lens
        U0 = math.inf
    cam = LensCamera(obs.n_views, obs.image_size_px, obs.pixel_pitch_mm, w_mm, U0, d0, rvec=rvec,
                         T_mm=T, principal_point_px=pp, blur_model=options.blur_model, distortion=dist)
    if init is not None:
        with torch.no_grad():
            cam.blur_offset_px.copy_(init.blur_offset_px)
    if blur:
        start_blur(cam, obs, mode, init)
    return cam


def start_blur(cam: LensCamera, obs: Observations, mode: str, init: LensCamera | None = None):
    """Set cam's U, d, θF to the best start (see `initialize`) for its current poses; returns cam."""
    w_mm = float(cam.w_mm.detach())
    candidates = []
    if init is not None:
        th = float(init.theta_F.detach()) if mode != "unified" else 0.0
        candidates.append((float(init.U_mm.detach()), float(init.d_mm.detach()), th))
    if mode == "tilt":
        U0, d0 = float(init.U_mm.detach()), float(init.d_mm.detach())
        candidates += [(U0, d0, math.radians(a)) for a in np.arange(-80.0, 80.5, 1.0)]
    else:
        with torch.no_grad():
            p_cam = cam.to_camera(obs.points_mm)
        candidates.append(blur_from_scan(p_cam, obs.blur_px, obs.blur_mask, w_mm, obs.pixel_pitch_mm,
                                         fit_tilt=(mode == "joint")))
    best = min(candidates, key=lambda c: _blur_rss(cam, obs, *c))
    _blur_rss(cam, obs, *best)
    return cam
