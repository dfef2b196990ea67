"""Synthetic observations of the target (public API, as in mrcal): truth corners and blur, and images.

Camera model (the paper's unified model with a tilted plane of focus, `docs/conventions.md`): a target point
X_target goes to the camera frame as p = R X_target + T (x right, y down, z forward, mm); its image is
    (u, v) = (cx + w x / (z p_px), cy + w y / (z p_px))                        (paper (3); p_px = pixel pitch)
and its blur-disc diameter on the sensor is
    b = w d |1/U − 1/z|                                                       (paper (2))
in mm, b / p_px in pixels, when untilted; with a tilted plane of focus the exact equivalent-area diameter of
the thin lens's blur ellipse (`renderer.cameras.optics.blur_diameter_exact`), of which the paper's (4),
b = w d |1/(U + y tan θF) − 1/z|, is an approximation. The principal point defaults to the image centre,
((W − 1)/2, (H − 1)/2).

Images (`render_view`):
- `analytic` (default): the exact "gather" model: each pixel is the average, over the pixel square, of the
  sharp image averaged over a disc of the local blur diameter b (evaluated at the target point seen by the
  pixel centre). The disc average of the projected checker is computed in closed form as the area of
  disc ∩ projected cell (a convex quadrilateral), summed over the cells the disc can reach; the pixel
  square is integrated with m × m midpoint sub-samples, m from 2 (large blur) to 8 (blur under 1 px).
  Blur varying across a disc is neglected (it varies by under 1 % per pixel at the paper's settings).
- `renderer`: the distributed ray tracer (`renderer`'s `thin_lens` camera and a `rectangle` with the target
  texture), when those components are registered; slower and noisy by construction (Monte Carlo).
Then optional vignetting, Gaussian read noise and shot noise, and 8-bit sRGB quantisation.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from renderer import Lens, axis_angle_to_matrix
from renderer.cameras.sensor import SensorResponse
from renderer.core.transforms import euler_xyz_deg, look_at_rotation

from tiltfit.target.layout import Target


#: The paper's camera (Canon EOS 6D, TS-E 45 mm at f/2.8, stage-1 estimates): 5472 × 3648, 6.54 µm pixels. The
#: synthetic captures take any `renderer.Lens` with a sensor; its projection and blur are the renderer's
#: (`Lens.project`, `Lens.blur_px`), the same code as `renderer.LensCamera`'s.
PAPER_CAMERA = Lens.paper()


@dataclass(frozen=True)
class Observation:
    """Truth for one view: feature points in the target's order.

    Attributes:
        corners_px: (N, 2) image positions (pinhole projection through the lens centre), pixels.
        blur_px: (N,) blur-disc diameters, pixels.
        p_cam: (N, 3) feature points in the camera frame, mm.
        in_image: (N,) bool, inside the image by at least `border_px`.
    """

    corners_px: np.ndarray
    blur_px: np.ndarray
    p_cam: np.ndarray
    in_image: np.ndarray


def pose_from_axis_angle(rvec, T) -> tuple[np.ndarray, np.ndarray]:
    """(R, T) from an axis-angle vector (radians) and a translation (mm)."""
    R = axis_angle_to_matrix(torch.as_tensor(np.asarray(rvec, dtype=np.float64))).numpy()
    return R, np.asarray(T, dtype=np.float64)


def look_at_pose(target: Target, camera_position_mm, look_at_mm=None, roll_deg: float = 0.0):
    """(R, T) for a camera at a target-frame position looking at a target point (default: the board centre).

    The camera's y axis is chosen along the target's +Y direction projected on the image plane (so the
    board appears upright: target X to the right, Y downwards), then rolled by `roll_deg` about the axis.
    """
    c = np.asarray(camera_position_mm, dtype=np.float64)
    if look_at_mm is None:
        look_at_mm = (0.5 * (target.x_edges[0] + target.x_edges[-1]), 0.5 * (target.y_edges[0] + target.y_edges[-1]),
                      0.0)
    # `up` is the target's −Y: the rows of R, the camera axes in the target frame, are look-at's columns.
    R = euler_xyz_deg((0.0, 0.0, roll_deg)).numpy() @ look_at_rotation(c, look_at_mm, (0.0, -1.0, 0.0)).numpy().T
    return R, -R @ c


def observe(target: Target, camera: Lens, R, T, border_px: float = 0.0) -> Observation:
    """Truth corners and blur of the target's feature points for pose (R, T) (X_cam = R X + T)."""
    R, T = np.asarray(R, dtype=np.float64), np.asarray(T, dtype=np.float64)
    p_cam = target.feature_points() @ R.T + T
    uv = camera.project(p_cam)
    inside = ((uv[:, 0] >= -0.5 + border_px) & (uv[:, 0] <= camera.sensor.width_px - 0.5 - border_px)
              & (uv[:, 1] >= -0.5 + border_px) & (uv[:, 1] <= camera.sensor.height_px - 0.5 - border_px)
              & (p_cam[:, 2] > 0))
    return Observation(uv, camera.blur_px(p_cam), p_cam, inside)


def projected_square_px(target: Target, camera: Lens, R, T) -> np.ndarray:
    """(N,) smallest distance from each feature point to its grid neighbours in the image, pixels."""
    uv = observe(target, camera, R, T).corners_px.reshape(*target.grid_shape, 2)
    d = np.full(target.grid_shape, np.inf)
    dx = np.hypot(*np.diff(uv, axis=1).transpose(2, 0, 1))
    dy = np.hypot(*np.diff(uv, axis=0).transpose(2, 0, 1))
    d[:, :-1] = np.minimum(d[:, :-1], dx)
    d[:, 1:] = np.minimum(d[:, 1:], dx)
    d[:-1] = np.minimum(d[:-1], dy)
    d[1:] = np.minimum(d[1:], dy)
    return d.ravel()


def with_blur_ratio(camera: Lens, target: Target, R, T, ratio: float,
                    U_mm: float | None = None) -> Lens:
    """The camera with the aperture d set so the median blur of the feature points is `ratio` × the median
    projected square (a synthetic knob: d may be unphysically large). `U_mm` moves the focus first."""
    cam = camera if U_mm is None else camera.with_(U=U_mm)
    ob = observe(target, cam.with_(d=1.0), R, T)
    return cam.with_(d=ratio * float(np.median(projected_square_px(target, cam, R, T)))
                   / float(np.median(ob.blur_px)))


@dataclass
class SynthView:
    """A synthetic image and its truth.

    Attributes:
        image: (H, W, 3) float32 linear image, as `camio.files.read_image` would return it (for 8-bit
            output: the quantised sRGB values decoded back to linear).
        image_srgb8: (H, W, 3) uint8 sRGB-encoded image when `srgb8` was asked for, else None.
        clean: (H, W) float32 noise-free linear image (before vignetting and noise).
        truth: the Observation (corners, blur).
    """

    image: np.ndarray
    image_srgb8: np.ndarray | None
    clean: np.ndarray = field(repr=False)
    truth: Observation = field(repr=False)


def render_view(target: Target, camera: Lens, R, T, *, dark: float = 0.05, white: float = 0.8,
                background: float = 0.3, noise_sigma: float = 0.0, shot_noise: float = 0.0,
                vignetting: float = 0.0, srgb8: bool = False, seed: int = 0, method: str = "analytic",
                spp: int = 64) -> SynthView:
    """Render the target seen by `camera` from pose (R, T), with the truth.

    Args:
        dark, white, background: linear radiance of dark cells, white cells and margin, and beyond the board.
        noise_sigma: standard deviation of additive Gaussian noise, linear units.
        shot_noise: variance per unit signal of signal-dependent noise (variance = noise_sigma² + shot·I).
        vignetting: relative darkening at the image corners, falling off as (radius / half-diagonal)².
        srgb8: quantise to 8-bit sRGB (the returned linear `image` is then the decoded 8-bit image).
        method: `analytic` or `renderer` (the ray tracer's thin-lens camera; see the module docs).
        spp: samples per pixel for `renderer`.
    """
    R, T = np.asarray(R, dtype=np.float64), np.asarray(T, dtype=np.float64)
    if method == "analytic":
        clean = render_analytic(target, camera, R, T, dark, white, background)
    elif method == "renderer":
        clean = render_with_renderer(target, camera, R, T, dark, white, background, spp=spp, seed=seed)
    else:
        raise ValueError(f"method: expected analytic or renderer, got {method!r}")
    sensor = SensorResponse(vignetting=vignetting, read_noise=noise_sigma,
                            full_well=1.0 / shot_noise if shot_noise else None,
                            encoding="srgb8" if srgb8 else "float")
    recorded = sensor.expose(clean, np.random.default_rng(seed), centre=camera.center_px)
    img, enc = sensor.decode(recorded), None
    if srgb8:
        enc = np.repeat(recorded[..., None], 3, axis=-1)
    image = np.repeat(img.astype(np.float32)[..., None], 3, axis=-1)
    return SynthView(image, enc, clean.astype(np.float32), observe(target, camera, R, T))


# --- analytic renderer -------------------------------------------------------------------------------------
def plane_homography(camera: Lens, R: np.ndarray, T: np.ndarray) -> np.ndarray:
    """(3, 3) homography from target-plane (X, Y, 1) to homogeneous pixels: K [r1 r2 T]."""
    return camera.K @ np.stack([R[:, 0], R[:, 1], T], axis=1)


def _disc_polygon_area(c: np.ndarray, r: np.ndarray, verts: np.ndarray) -> np.ndarray:
    """Signed area of disc(c, r) ∩ polygon, summed over the polygon's edges.

    Deliberately not `tiltfit.photometric.aperture`'s disc geometry: these images are the test data of the
    photometric fit that uses that code (tests/tiltfit/test_photometric.py), so the generator shares none of it.

    Args:
        c: (..., 2) disc centres; r: (...,) radii; verts: (..., V, 2) polygon vertices (convex or not: the
            sum of per-edge triangle areas is exact for any simple polygon).
    Returns:
        (...,) signed area (positive for counter-clockwise vertices in an x-right, y-up frame).
    """
    ax = verts[..., 0] - c[..., None, 0]
    ay = verts[..., 1] - c[..., None, 1]
    bx = np.roll(ax, -1, axis=-1)
    by = np.roll(ay, -1, axis=-1)
    r2 = (r * r)[..., None]
    dx, dy = bx - ax, by - ay
    a = np.maximum(dx * dx + dy * dy, 1e-300)
    bq = ax * dx + ay * dy
    disc = bq * bq - a * (ax * ax + ay * ay - r2)
    hit = disc > 0
    sq = np.sqrt(np.where(hit, disc, 0.0))
    s1 = np.where(hit, np.clip((-bq - sq) / a, 0.0, 1.0), 0.0)
    s2 = np.where(hit, np.clip((-bq + sq) / a, 0.0, 1.0), 0.0)
    p1x, p1y = ax + s1 * dx, ay + s1 * dy
    p2x, p2y = ax + s2 * dx, ay + s2 * dy
    # sector angles A -> P1 and P2 -> B, and the triangle (0, P1, P2) inside the disc
    ang = (np.arctan2(ax * p1y - ay * p1x, ax * p1x + ay * p1y)
           + np.arctan2(p2x * by - p2y * bx, p2x * bx + p2y * by))
    per_edge = 0.5 * (r2 * ang + (p1x * p2y - p1y * p2x))
    return per_edge.sum(-1)


def render_analytic(target: Target, camera: Lens, R: np.ndarray, T: np.ndarray, dark: float = 0.05,
                    white: float = 0.8, background: float = 0.3, chunk: int = 1 << 15) -> np.ndarray:
    """(H, W) float64 noise-free linear image by the exact disc-gather model (see the module docs)."""
    W, H = camera.sensor.size_px
    Hm = plane_homography(camera, R, T)
    Hinv = np.linalg.inv(Hm)
    xe, ye = np.asarray(target.x_edges), np.asarray(target.y_edges)
    x0, y0, x1, y1 = target.extent_mm

    # Pixel centres -> target plane, blur and local scale (mm per pixel).
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    q = np.stack([u, v, np.ones_like(u)], -1) @ Hinv.T
    front = q[..., 2] * np.sign(np.linalg.det(Hinv)) > 0
    X, Y = q[..., 0] / q[..., 2], q[..., 1] / q[..., 2]
    p_cam = np.stack([X, Y, np.zeros_like(X)], -1) @ R.T + T
    front &= p_cam[..., 2] > 0
    radius = 0.5 * camera.blur_px(p_cam)
    jx_u = (Hinv[0, 0] - X * Hinv[2, 0]) / q[..., 2]
    jx_v = (Hinv[0, 1] - X * Hinv[2, 1]) / q[..., 2]
    jy_u = (Hinv[1, 0] - Y * Hinv[2, 0]) / q[..., 2]
    jy_v = (Hinv[1, 1] - Y * Hinv[2, 1]) / q[..., 2]
    scale = np.sqrt(jx_u ** 2 + jx_v ** 2 + jy_u ** 2 + jy_v ** 2)
    reach = 1.25 * (radius + 0.75) * scale + 1e-9  # mm; conservative over the disc and the pixel

    # Constant-colour pixels: no edge line within reach.
    def nearest(lines, t):
        k = np.clip(np.searchsorted(lines, t), 1, len(lines) - 1)
        return np.minimum(np.abs(t - lines[k - 1]), np.abs(t - lines[k]))

    xlines = np.concatenate([[x0], xe, [x1]])
    ylines = np.concatenate([[y0], ye, [y1]])
    simple = front & (nearest(xlines, X) > reach) & (nearest(ylines, Y) > reach)
    col = np.searchsorted(xe, X) - 1
    row = np.searchsorted(ye, Y) - 1
    inside_board = (X > x0) & (X < x1) & (Y > y0) & (Y < y1)
    img = np.where(inside_board, np.where(target.is_dark(col, row), dark, white), background)

    # Projected vertices of all cells and of the outer rectangle.
    gx, gy = np.meshgrid(xe, ye)
    gv = np.stack([gx, gy, np.ones_like(gx)], -1) @ Hm.T
    grid_px = gv[..., :2] / gv[..., 2:]
    outer = np.array([[x0, y0, 1], [x1, y0, 1], [x1, y1, 1], [x0, y1, 1]], dtype=np.float64) @ Hm.T
    outer_px = outer[:, :2] / outer[:, 2:]
    orient = np.sign(_shoelace(outer_px))

    todo = np.nonzero((~simple & front).ravel())[0]
    if todo.size:
        Xf, Yf, rf, reachf = X.ravel()[todo], Y.ravel()[todo], radius.ravel()[todo], reach.ravel()[todo]
        c_lo = np.clip(np.searchsorted(xe, Xf - reachf) - 1, 0, target.n_cols - 1)
        c_hi = np.clip(np.searchsorted(xe, Xf + reachf) - 1, 0, target.n_cols - 1)
        r_lo = np.clip(np.searchsorted(ye, Yf - reachf) - 1, 0, target.n_rows - 1)
        r_hi = np.clip(np.searchsorted(ye, Yf + reachf) - 1, 0, target.n_rows - 1)
        inside_outer = (Xf > x0) & (Xf < x1) & (Yf > y0) & (Yf < y1)
        near_outer = ((np.minimum(np.abs(Xf - x0), np.abs(Xf - x1)) <= reachf)
                      | (np.minimum(np.abs(Yf - y0), np.abs(Yf - y1)) <= reachf))
        m = np.clip(np.ceil(5.0 / np.maximum(rf, 1e-3)), 2, 8).astype(int)
        out = np.empty(todo.size)
        for mm in np.unique(m):
            sel_m = np.nonzero(m == mm)[0]
            off = (np.arange(mm) + 0.5) / mm - 0.5
            oy, ox = np.meshgrid(off, off, indexing="ij")
            sub = np.stack([ox.ravel(), oy.ravel()], -1)  # (S, 2)
            nc = (c_hi - c_lo + 1)[sel_m]
            nr = (r_hi - r_lo + 1)[sel_m]
            for kc in np.unique(nc):
                for kr in np.unique(nr[nc == kc]):
                    sel = sel_m[(nc == kc) & (nr == kr)]
                    per = max(1, chunk // (sub.shape[0] * max(1, kc * kr)))
                    for s0 in range(0, sel.size, per):
                        idx = sel[s0:s0 + per]
                        out[idx] = _pixels_value(todo[idx], W, sub, rf[idx], c_lo[idx], r_lo[idx], kc, kr,
                                                 near_outer[idx], inside_outer[idx], grid_px, outer_px, orient,
                                                 target, dark, white, background)
        flat = img.ravel()
        flat[todo] = out
        img = flat.reshape(H, W)
    return np.where(front, img, background)


def _shoelace(p: np.ndarray) -> np.ndarray:
    x, y = p[..., 0], p[..., 1]
    return 0.5 * (x * np.roll(y, -1, -1) - np.roll(x, -1, -1) * y).sum(-1)


def _pixels_value(flat_idx, W, sub, radius, c_lo, r_lo, kc, kr, near_outer, inside_outer, grid_px, outer_px,
                  orient, target, dark, white, background):
    """Mean over sub-samples of the disc-averaged scene for a batch of pixels (all with kc × kr cells).

    Pixels not `near_outer` lie, with their whole disc, inside (or outside) the outer rectangle as
    `inside_outer` says; only dark cells of the
    kc × kr block are evaluated (white cells and the margin share one colour).
    """
    P, S = flat_idx.size, sub.shape[0]
    centre = np.stack([flat_idx % W, flat_idx // W], -1).astype(np.float64)
    pts = centre[:, None, :] + sub[None]  # (P, S, 2)
    r = np.broadcast_to(np.maximum(radius, 1e-3)[:, None], (P, S))
    area_disc = math.pi * r * r
    value = np.where(inside_outer, white, background)[:, None].repeat(S, 1).astype(np.float64)
    if near_outer.any():
        o = np.nonzero(near_outer)[0]
        a_out = orient * _disc_polygon_area(pts[o], r[o], np.broadcast_to(outer_px, (o.size, S, 4, 2))) / area_disc[o]
        value[o] = background + (white - background) * a_out
    dc, dr = np.meshgrid(np.arange(kc), np.arange(kr), indexing="ij")
    cols = c_lo[:, None] + dc.ravel()[None]  # (P, K)
    rows = r_lo[:, None] + dr.ravel()[None]
    is_dark = target.is_dark(cols, rows)
    n_dark = int(is_dark.sum(1).max())
    if n_dark:
        order = np.argsort(~is_dark, axis=1, kind="stable")[:, :n_dark]
        cols = np.take_along_axis(cols, order, 1)
        rows = np.take_along_axis(rows, order, 1)
        is_dark = np.take_along_axis(is_dark, order, 1)
        quads = np.stack([grid_px[rows, cols], grid_px[rows, cols + 1], grid_px[rows + 1, cols + 1],
                          grid_px[rows + 1, cols]], axis=-2)  # (P, K, 4, 2)
        a_cells = orient * _disc_polygon_area(pts[:, :, None, :], r[:, :, None],
                                              quads[:, None]) / area_disc[..., None]
        value = value + (dark - white) * (a_cells * is_dark[:, None, :]).sum(-1)
    return value.mean(-1)


# --- the ray tracer ----------------------------------------------------------------------------------------
def renderer_scene(target: Target, camera: Lens, R, T, texture_file: str, spp: int = 64) -> dict:
    """The scene dict (contract's scene-file format) showing the target as `render_analytic` does.

    The world frame is the target frame; the camera sits at C = −Rᵀ T looking along Rᵀ (0, 0, 1) with
    up = Rᵀ (0, −1, 0) (so the camera frame equals R's). The board is a `rectangle` in z = 0 centred on the
    extent's centre with the target texture (`target_texture`: image column = X, row = Y), lit by an
    ambient light of unit intensity so each pixel shows the texture's albedo.
    """
    R, T = np.asarray(R, dtype=np.float64), np.asarray(T, dtype=np.float64)
    C = -R.T @ T
    x0, y0, x1, y1 = target.extent_mm
    W, H = camera.sensor.size_px
    return {
        "image": {"width": W, "height": H, "spp": spp, "max_depth": 1, "background": [0.0, 0.0, 0.0],
                  "sampler": "sobol"},
        "camera": {"position": C.tolist(), "look_at": (C + R.T @ [0, 0, 1.0]).tolist(),
                   "up": (R.T @ [0, -1.0, 0]).tolist(), **camera.scene_keys()},
        "lights": [{"type": "ambient", "intensity": [1.0, 1.0, 1.0]}],
        "objects": [{"name": "target",
                     "shape": {"type": "rectangle", "center": [(x0 + x1) / 2, (y0 + y1) / 2, 0.0],
                               "size": [x1 - x0, y1 - y0], "rotation_deg": [0.0, 0.0, 0.0]},
                     "material": {"color": [1.0, 1.0, 1.0], "diffuse": 0.0,
                                  "texture": {"type": "image", "file": texture_file, "size": [x1 - x0, y1 - y0]}}}],
    }


def render_with_renderer(target: Target, camera: Lens, R, T, dark: float, white: float, background: float,
                         spp: int = 64, seed: int = 0, px_per_mm: float = 10.0) -> np.ndarray:
    """(H, W) linear image from the ray tracer (thin-lens camera, textured rectangle); see `renderer_scene`.

    The renderer looks textures up by nearest texel, so edges are placed to 1/px_per_mm mm; its Monte Carlo
    noise falls as 1/sqrt(spp). A cross-check of `render_analytic`, not a substitute for its precision.
    """
    import torch

    from renderer import load_scene
    from renderer import render

    scene_dict = renderer_scene(target, camera, R, T, _texture_file(target, px_per_mm, dark, white), spp=spp)
    scene_dict["image"]["background"] = [background] * 3
    scene = load_scene(scene_dict)
    result = render(scene, spp=spp, seed=seed, dtype=torch.float32)
    return result.image.mean(-1).numpy().astype(np.float64)


#: Board textures `render_with_renderer` has written in this process, (target, px_per_mm, dark, white) -> file, at
#: most TEXTURES_KEPT (the oldest file removed first). Every view of a board reads the one file, rasterised and
#: written (a 3500 x 2500 EXR at 10 px/mm) once.
_TEXTURES: dict = {}
TEXTURES_KEPT = 8
_TEXTURE_FOLDER: dict = {}   # this process's texture folder ("folder"), its "pid", the files it has held ("count")


TEXTURE_PREFIX = "tiltfit-textures-"


def _remove_dead_texture_folders() -> None:
    """Remove the texture folders of processes that ended without their exit handlers (a pool's terminated
    workers): each folder is named by its process id."""
    import glob
    import os
    import shutil
    import tempfile

    for folder in glob.glob(os.path.join(tempfile.gettempdir(), TEXTURE_PREFIX + "*-*")):
        pid = os.path.basename(folder)[len(TEXTURE_PREFIX):].split("-")[0]
        if not pid.isdigit():
            continue
        try:
            os.kill(int(pid), 0)
        except ProcessLookupError:
            shutil.rmtree(folder, True)
        except OSError:
            pass  # alive, another user's


def _texture_file(target: Target, px_per_mm: float, dark: float, white: float) -> str:
    """The EXR file of `target`'s texture (`target_texture`; one channel: the scene reader repeats a grey image's
    channel into RGB, so the renders are the same to the bit), written once a process into a folder removed
    at exit."""
    import atexit
    import os
    import shutil
    import tempfile

    from renderer import write_image

    from tiltfit.target.raster import target_texture

    key = (target, float(px_per_mm), float(dark), float(white))
    path = _TEXTURES.get(key)
    if path is not None and os.path.isfile(path):
        return path
    if _TEXTURE_FOLDER.get("pid") != os.getpid():  # this process's first texture, or a forked child's
        _TEXTURES.clear()
        _remove_dead_texture_folders()
        _TEXTURE_FOLDER.update(pid=os.getpid(), count=0,
                               folder=tempfile.mkdtemp(prefix=f"{TEXTURE_PREFIX}{os.getpid()}-"))
        atexit.register(shutil.rmtree, _TEXTURE_FOLDER["folder"], True)
    while len(_TEXTURES) >= TEXTURES_KEPT:
        old = _TEXTURES.pop(next(iter(_TEXTURES)))
        if os.path.isfile(old):
            os.remove(old)
    _TEXTURE_FOLDER["count"] = _TEXTURE_FOLDER.get("count", 0) + 1
    path = os.path.join(_TEXTURE_FOLDER["folder"], f"target{_TEXTURE_FOLDER['count']}.exr")
    write_image(path, target_texture(target, px_per_mm, dark, white)[..., :1])
    _TEXTURES[key] = path
    return path


def render_constant_blur(target: Target, homography: np.ndarray, size_px: tuple[int, int], blur_px: float,
                         dark: float = 0.05, white: float = 0.8, background: float = 0.3,
                         supersample: int = 4, texture_px_per_mm: float | None = None) -> np.ndarray:
    """(H, W) noise-free linear image of any target (markers too) under one blur disc for the whole image.

    A generator independent of `render_analytic` and of the ray tracer: the target's exact area-averaged picture
    (`rasterise`, 50 texels a square unless given) is looked up bilinearly at `supersample`² points per pixel
    through `homography` (target (X, Y, 1) -> pixels), convolved with a disc of `blur_px` (constant: right
    for a view whose blur varies little) at the supersampled resolution and box-averaged to pixels.
    """
    import cv2

    from tiltfit.target.raster import rasterise

    W, H = size_px
    s = supersample
    x0, y0, x1, y1 = target.extent_mm
    ppm = texture_px_per_mm or 50.0 / min(np.diff(target.x_edges).min(), np.diff(target.y_edges).min())
    tw, th = int(round((x1 - x0) * ppm)), int(round((y1 - y0) * ppm))
    tex = rasterise(target, (x0, x1), (y0, y1), tw, th, dark, white)
    tex = np.pad(tex, 1, constant_values=background)
    v, u = np.mgrid[0:H * s, 0:W * s].astype(np.float64)
    pix = np.stack([(u + 0.5) / s - 0.5, (v + 0.5) / s - 0.5, np.ones_like(u)], -1)
    q = pix @ np.linalg.inv(homography).T
    X, Y = q[..., 0] / q[..., 2], q[..., 1] / q[..., 2]
    mx = ((X - x0) / (x1 - x0) * tw + 0.5).astype(np.float32)  # texel centres at +0.5, 1-texel pad
    my = ((Y - y0) / (y1 - y0) * th + 0.5).astype(np.float32)
    img = cv2.remap(tex, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=background)
    r = 0.5 * blur_px * s
    if r > 0.5:
        k = int(math.ceil(r)) + 1
        # the disc's area-weighted kernel (4 × 4 sub-samples per tap), so its size is not rounded to taps
        o = (np.arange(4) + 0.5) / 4 - 0.5
        yy, xx = np.mgrid[-k:k + 1, -k:k + 1].astype(np.float64)
        ker = sum(((xx + a) ** 2 + (yy + b) ** 2 <= r * r) for a in o for b in o).astype(np.float32)
        img = cv2.filter2D(img, -1, ker / ker.sum(), borderType=cv2.BORDER_REPLICATE)
    return img.reshape(H, s, W, s).mean((1, 3)).astype(np.float64)
