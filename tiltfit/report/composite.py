"""CG rendered into a calibrated photo, and the check that the calibrated camera puts the board where the photo
shows it.

The camera is a calibration's view (`tiltfit.files.calibrated.Calibration`): its lens, distortion (about its centre),
defocus and pose, so a rendered object sits in the photo as the real lens would have imaged it. Rendering is
done on windows of the image only (`renderer.Lens.cropped`): a composite needs the pixels of the object and its
shadow, the check the pixels around each corner.

- `render_window(scene, calibration, view, window)`: the scene through the view's camera, one window of pixels.
- `differential_composite(photo, with_object, without_object, alpha, gain)`: differential rendering
  (Debevec, "Rendering synthetic objects into real scenes", SIGGRAPH 1998): the object's pixels from the render,
  elsewhere the photo times the render's ratio with / without the object (its shadow on the board).
- `board_alignment(calibration, view, photo_corners_px)`: the board rendered alone through the view's camera, its
  corners measured as `tiltfit detect` measures a photo's (`tiltfit.detect.chessboard.refine_symmetric`), against the
  photo's corners and against the calibration's own projection of the board.

`examples/composite.py` puts them together on a shipped real photo set.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Refinement window radius as a fraction of the distance to the nearest neighbouring corner, and its bounds (px):
#: `tiltfit.detect.chessboard.detect_corners`'s, so that rendered and photographed corners are measured alike.
WINDOW_FRACTION, WINDOW_MIN_PX, WINDOW_MAX_PX = 0.4, 3.0, 20.0
#: Pixels around a refinement window that the refinement reads (room to move, cubic support, its presmoothing).
REFINE_MARGIN_PX = 10


def render_window(scene, calibration, view, window, spp: int | None = None, seed: int = 0) -> np.ndarray:
    """(h, w, 3) linear radiance of the window (x0, y0, w, h) of a view's image: `scene` with its camera replaced
    by the calibration's camera of `view` (lengths in mm, world = target frame) read out on that window.

    Args:
        scene: a `renderer.Scene` (its own camera is ignored).
        calibration: a `tiltfit.files.calibrated.Calibration`; view: index or image name.
        window: (x0, y0, width, height) in pixels of the calibrated image (may reach past its edges).
        spp: samples per pixel [scene.image.spp].
    """
    import torch

    from renderer import render
    from renderer.cameras import ThinLensCamera

    x0, y0, w, h = (int(v) for v in window)
    R, T = calibration.pose(view)
    camera = ThinLensCamera.from_calibration(calibration.lens.cropped(x0, y0, w, h), torch.as_tensor(R),
                                             torch.as_tensor(T))
    # the scene's camera swapped in place (and restored), not a copy of the scene: what the scene derives from
    # its objects (an Embree scene, texture rasters) is kept for the next window
    own, scene.camera = scene.camera, camera
    try:
        result = render(scene, spp=spp, seed=seed, workers=1)
    finally:
        scene.camera = own
    return result.image.numpy().astype(np.float64)


def window_around(points_px, image_size_px, margin_px: float = 8.0) -> tuple[int, int, int, int]:
    """(x0, y0, w, h): the smallest window of whole pixels holding `points_px` (N, 2) plus `margin_px`, cut to
    the image (W, H). Raises ValueError when none of it lies in the image."""
    p = np.asarray(points_px, dtype=np.float64).reshape(-1, 2)
    p = p[np.isfinite(p).all(1)]
    W, H = (int(v) for v in image_size_px)
    x0, y0 = (max(0, int(math.floor(v - margin_px))) for v in p.min(0)) if len(p) else (W, H)
    x1, y1 = (int(math.ceil(v + margin_px)) + 1 for v in p.max(0)) if len(p) else (0, 0)
    x1, y1 = min(W, x1), min(H, y1)
    if x1 <= x0 or y1 <= y0:
        raise ValueError("window: the points lie outside the image")
    return x0, y0, x1 - x0, y1 - y0


def photo_gain(photo, board_render, min_fraction: float = 0.5) -> np.ndarray:
    """(3,) per-channel factors taking rendered radiance to the photo's linear values: the median ratio over
    the pixels where the rendered board is bright (its light squares and margin, `min_fraction` of the
    brightest), so the object gets the photo's exposure and white balance.

    Args:
        photo, board_render: (h, w, 3) linear images of the same pixels (the board without the object).
    """
    photo, board = np.asarray(photo, np.float64), np.asarray(board_render, np.float64)
    lum = board.mean(-1)
    bright = lum >= min_fraction * np.percentile(lum, 99)
    if bright.sum() < 10:
        raise ValueError("photo_gain: the window holds too few pixels of the rendered board")
    return np.median(photo[bright] / np.maximum(board[bright], 1e-6), axis=0)


def differential_composite(photo, with_object, without_object, alpha, gain=1.0, max_ratio: float = 2.0):
    """Differential rendering (Debevec 1998), multiplicative form: (h, w, 3) linear

        out = α · gain · with + (1 − α) · photo · clip(with / without, 0, max_ratio)

    so the photo keeps its own texture and light, darkened where the object shadows the rendered local scene
    (and brightened by what it reflects onto it, at most `max_ratio`), and the object's pixels come from the
    render at the photo's exposure (`photo_gain`).

    Args:
        photo: (h, w, 3) linear photo; with_object, without_object: (h, w, 3) renders of the same pixels with
            and without the object; alpha: (h, w) the object's coverage of each pixel in [0, 1].
    """
    photo = np.asarray(photo, np.float64)
    with_object, without_object = np.asarray(with_object, np.float64), np.asarray(without_object, np.float64)
    a = np.clip(np.asarray(alpha, np.float64), 0.0, 1.0)[..., None]
    lit = without_object > 1e-6
    ratio = np.where(lit, with_object / np.where(lit, without_object, 1.0), 1.0)
    return a * np.asarray(gain, np.float64) * with_object + (1.0 - a) * photo * np.clip(ratio, 0.0, max_ratio)


@dataclass
class BoardAlignment:
    """The board rendered through a view's camera against the photo's corners and the calibration's projection.

    Attributes:
        rendered_px: (N, 2) corners measured on the render (NaN where not measured).
        photo_px: (N, 2) the photo's corners (NaN where not detected).
        projected_px: (N, 2) the calibration's projection of the flat target's corners.
        rms_photo_px: RMS over corners of |rendered − photo| (px, per corner as `rms_reprojection_px`).
        rms_projection_px: RMS of |rendered − projected| (px): how well the renderer's camera equals the
            calibration's projection (distortion included).
        rms_reprojection_px: the calibration's own RMS of that view (CALIB.json views[k].rms_reprojection_px).
        n_corners: corners in both the render and the photo.
    """

    rendered_px: np.ndarray
    photo_px: np.ndarray
    projected_px: np.ndarray
    rms_photo_px: float
    rms_projection_px: float
    rms_reprojection_px: float | None
    n_corners: int


def _rms(a, b) -> float:
    d = np.asarray(a) - np.asarray(b)
    ok = np.isfinite(d).all(1)
    return float(np.sqrt(np.mean(np.sum(d[ok] ** 2, 1)))) if ok.any() else math.nan


def board_scene(target, camera, reflectance=None):
    """The `renderer.Scene` of the target's board alone (`tiltfit.files.scene_plugins.TargetBoard`, target frame) under
    unit ambient light, so the render is the print's albedo; `camera` is the scene's camera (any)."""
    from renderer import ImageSettings, Light, Material, Scene, SceneObject

    from tiltfit.files.scene_plugins import DEFAULT_REFLECTANCE, TargetBoard

    board = TargetBoard(target, reflectance or DEFAULT_REFLECTANCE)
    return Scene([SceneObject("board", board, Material(texture=board.texture))], [Light("ambient", (1.0, 1.0, 1.0))],
                 camera, ImageSettings(camera.width, camera.height))


def board_alignment(calibration, view, photo_corners_px, target=None, spp: int = 16,
                    corners=None) -> BoardAlignment:
    """Render the flat target alone through the calibration's camera of `view` (a window around each corner),
    measure its corners as `tiltfit detect` measures a photo's, and compare.

    Args:
        calibration: `tiltfit.files.calibrated.Calibration`; view: index or image name.
        photo_corners_px: (N, 2) the photo's detected corners in feature-point order (NaN: not found).
        target: the `tiltfit.target.layout.Target` [the calibration's].
        spp: samples per pixel of the render (anti-aliased edges).
        corners: indices of the corners to render [all the photo's].
    Returns:
        `BoardAlignment`.
    Raises:
        ValueError: no target, or `photo_corners_px` of the wrong shape.
    """
    from tiltfit.detect.chessboard import refine_symmetric, to_gray

    target = target if target is not None else calibration.target
    if target is None:
        raise ValueError(f"{calibration.path}: target: the calibration holds no target; pass one")
    points = np.asarray(target.feature_points(), dtype=np.float64)
    photo = np.asarray(photo_corners_px, dtype=np.float64)
    if photo.shape != (len(points), 2):
        raise ValueError(f"photo_corners_px: expected ({len(points)}, 2) corners in feature-point order, got "
                         f"{photo.shape}")
    projected = calibration.project(points, view)
    idx = np.nonzero(np.isfinite(photo).all(1))[0] if corners is None else np.asarray(corners, dtype=np.int64)
    # the detector's window: a fraction of the distance to the nearest neighbour, in the image
    dist = np.linalg.norm(projected[:, None] - projected[None], axis=-1)
    np.fill_diagonal(dist, np.inf)
    radius = np.clip(WINDOW_FRACTION * dist.min(1), WINDOW_MIN_PX, WINDOW_MAX_PX)
    scene = board_scene(target, calibration.camera(view))
    W, H = calibration.image_size_px
    canvas = np.zeros((H, W))
    for k in idx:
        half = int(math.ceil(radius[k])) + REFINE_MARGIN_PX
        x0, y0 = int(round(projected[k, 0])) - half, int(round(projected[k, 1])) - half
        image = to_gray(render_window(scene, calibration, view, (x0, y0, 2 * half + 1, 2 * half + 1), spp))
        ys, xs = slice(max(y0, 0), min(y0 + 2 * half + 1, H)), slice(max(x0, 0), min(x0 + 2 * half + 1, W))
        canvas[ys, xs] = image[ys.start - y0:ys.stop - y0, xs.start - x0:xs.stop - x0]
    rendered = np.full_like(projected, np.nan)
    if len(idx):
        xy, _, ok = refine_symmetric(canvas, projected[idx], radius[idx])
        rendered[idx[ok]] = xy[ok]
    views = calibration.views
    rms_view = views[calibration.view_index(view)].get("rms_reprojection_px") if views else None
    both = np.isfinite(rendered).all(1) & np.isfinite(photo).all(1)
    return BoardAlignment(rendered, photo, projected, _rms(rendered, photo), _rms(rendered, projected),
                          None if rms_view is None else float(rms_view), int(both.sum()))
