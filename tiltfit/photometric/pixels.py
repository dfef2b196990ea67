"""Which pixels the photometric refinement fits and which it holds out: per view, candidates in the board's box whose
blur disc lies on the board, chosen where the start's prediction is informative (`_choose_pixels`)."""
from __future__ import annotations

import time

import numpy as np
import torch

from renderer.cameras import image_centre_px

from tiltfit.target.layout import Target
from .render import (SHARP_BLUR_PX, board_blur_px, on_board, pixel_blur_px, predicted_dark_fraction, board_box,
                     usable_pixels)
from .options import CLOSED_FORM_MIN_BLUR_PX, MIN_USABLE_PIXELS, PhotometricError, PhotometricOptions, _ViewsLeftOut
from .problem import _View


#: Candidate pixels of a view whose brightness is predicted before picking the pixels to fit: at most this many
#: drawn at random from the board's bounding box (a 1280 x 1024 photo's board has about 700,000: predicting all
#: of them took most of the 30-60 s of set-up a view).
MAX_CANDIDATE_PIXELS = 1 << 16


def _select_pixels(predicted: np.ndarray, usable: np.ndarray, white: float, black: float, max_pixels: int,
                   rng: np.random.Generator) -> np.ndarray:
    """Indices (flat) of the pixels to fit: mostly transitions (edges, blur), some flat ones for the levels."""
    span = max(white - black, 1e-6)
    frac = (white - predicted) / span
    edge = usable & (frac > 0.03) & (frac < 0.97)
    flat = usable & ~edge
    idx_edge, idx_flat = np.flatnonzero(edge), np.flatnonzero(flat)
    n_edge = min(idx_edge.size, int(0.8 * max_pixels))
    n_flat = min(idx_flat.size, max_pixels - n_edge)
    pick = [rng.choice(idx_edge, n_edge, replace=False) if n_edge else idx_edge[:0],
            rng.choice(idx_flat, n_flat, replace=False) if n_flat else idx_flat[:0]]
    return np.sort(np.concatenate(pick))


def _initial_levels(vals: np.ndarray) -> tuple[float, float]:
    return float(np.percentile(vals, 97)), float(np.percentile(vals, 3))


def _choose_pixels(imgs: list, views: list, target: Target, opts: PhotometricOptions, disc_only: bool, say,
                   t0: float):
    """Per view the pixels to fit (the same count in every view) and the held-out ones, where the start's
    prediction is between the levels (edges, blur) or flat; and the start's levels. Returns (data, held_data,
    levels): `_View`s, closed-form pixels first. Raises `_ViewsLeftOut` naming the views without enough usable
    pixels."""
    W, H = views[0].width, views[0].height
    rng = np.random.default_rng(opts.seed)
    rng_held = np.random.default_rng([opts.seed, 1])   # its own stream: the fitted pixels do not depend on it
    rng_cand = np.random.default_rng([opts.seed, 2])
    picks, held, levels, left_out = [], [], [], []
    for k, (im, vc) in enumerate(zip(imgs, views)):
        if im.shape != (H, W):
            raise PhotometricError(f"view {k}: image is {im.shape[1]}x{im.shape[0]}, expected {W}x{H}")
        found, why = _candidates(im, vc, target, opts, rng_cand)
        if found is None:
            left_out.append((k, why))
            continue
        if left_out:   # this view is usable, but the fit restarts without the left-out ones
            continue
        cand, uv_all, n_box = found
        pick, held_pick, view_levels = _view_pixels(im, vc, target, cand, uv_all, opts, rng, rng_held)
        picks.append(pick)
        held.append(held_pick)
        levels.append(view_levels)
        if say:
            say(f"photometric: view {k + 1} of {len(imgs)}: {cand.size} usable pixels of {n_box} in the board's box, "
                f"{picks[-1].size} chosen ({time.perf_counter() - t0:.1f} s)")
    if left_out:
        raise _ViewsLeftOut(left_out)
    # The solver's per-view blocks need the same number of pixels in every view.
    n_rows = min(p.size for p in picks)
    picks = [p if p.size == n_rows else np.sort(rng.choice(p, n_rows, replace=False)) for p in picks]
    data = [_view_data(im, vc, pick, opts, disc_only) for im, vc, pick in zip(imgs, views, picks)]
    held_data = [_view_data(im, vc, pick, opts, disc_only) for im, vc, pick in zip(imgs, views, held)]
    return data, held_data, levels


def _candidates(im: np.ndarray, vc, target: Target, opts: PhotometricOptions, rng_cand):
    """((candidate pixel indices (n,), their uv (n, 2) px, the pixels in the board's box), None) or (None, why
    the view is left out).

    Candidates: the board's bounding box only (a real photo is mostly elsewhere), at most MAX_CANDIDATE_PIXELS of
    its pixels drawn at random, less the saturated ones (glare: their brightness says nothing of the board's), the
    informative ones (`_informative`), then those whose blur disc lies on the board (`usable_pixels`)."""
    W = vc.width
    box = board_box(target, vc)
    if box is None:
        return None, "the board is not on the image at the start"
    bx0, by0, bx1, by1 = box
    bw, bh = bx1 - bx0 + 1, by1 - by0 + 1
    n_box = bw * bh
    local = np.arange(n_box) if n_box <= MAX_CANDIDATE_PIXELS else \
        np.sort(rng_cand.choice(n_box, MAX_CANDIDATE_PIXELS, replace=False))
    cand = (by0 + local // bw) * W + bx0 + local % bw
    n_drawn = cand.size
    if opts.saturation is not None:
        cand = cand[im.reshape(-1)[cand] < opts.saturation * float(im.max())]
    n_saturated = n_drawn - cand.size
    cand = _informative(cand, vc, target, W, opts, rng_cand)
    uv_all = torch.tensor(np.stack([cand % W, cand // W], -1), dtype=torch.float64)
    ok = usable_pixels(target, vc, uv_all)
    cand, uv_all = cand[ok], uv_all[torch.from_numpy(ok)]
    if cand.size < MIN_USABLE_PIXELS:
        return None, (f"the board covers {cand.size} usable pixels, fewer than {MIN_USABLE_PIXELS} (pixels "
                      f"whose blur disc lies on the board inside its margin; {n_saturated} of the {n_drawn} "
                      "in the board's box saturated)")
    return (cand, uv_all, n_box), None


def _view_pixels(im: np.ndarray, vc, target: Target, cand, uv_all, opts: PhotometricOptions, rng, rng_held):
    """(the view's fitted pixel indices, its held-out ones, its start levels (white, black)): chosen among the
    candidates by the start's prediction (`_select_pixels`)."""
    W, H = vc.width, vc.height
    usable = np.zeros(H * W, dtype=bool)
    usable[cand] = True
    white, black = _initial_levels(im.reshape(-1)[cand])
    pred_img = np.full(H * W, np.nan)
    for a in range(0, uv_all.shape[0], 1 << 16):
        dark = predicted_dark_fraction(target, vc, uv_all[a:a + (1 << 16)])
        pred_img[cand[a:a + (1 << 16)]] = (white - (white - black) * dark).numpy()
    pick = _select_pixels(pred_img, usable, white, black, opts.max_pixels, rng)
    rest = usable.copy()
    rest[pick] = False
    held_pick = (_select_pixels(pred_img, rest, white, black, opts.held_out_pixels, rng_held)
                 if opts.held_out_pixels else pick[:0])
    return pick, held_pick, (white, black)


def _view_data(im: np.ndarray, vc, pick, opts: PhotometricOptions, disc_only: bool) -> _View:
    """The `_View` of one view's chosen pixels: closed-form pixels first, the sharp ones (more points a pixel)
    before the others; then the samples'."""
    W, H = vc.width, vc.height
    hx, hy = image_centre_px(W, H)
    uv = torch.tensor(np.stack([pick % W, pick // W], -1), dtype=torch.float64)
    observed = torch.tensor(im.reshape(-1)[pick], dtype=torch.float64)
    blur = pixel_blur_px(vc, uv) if disc_only else None
    if opts.aperture == "closed_form":
        closed = torch.ones(uv.shape[0], dtype=torch.bool)
    elif disc_only:
        closed = blur >= CLOSED_FORM_MIN_BLUR_PX
    else:
        closed = torch.zeros(uv.shape[0], dtype=torch.bool)
    sharp = closed & (blur < SHARP_BLUR_PX) if disc_only else closed & False
    order = torch.argsort(torch.where(sharp, 0, torch.where(closed, 1, 2)).to(torch.int8), stable=True)
    uv = uv[order]
    rho2 = ((uv[:, 0] - hx) ** 2 + (uv[:, 1] - hy) ** 2) / (hx ** 2 + hy ** 2)
    return _View(uv, observed[order], int(closed.sum()), rho2,
                 torch.stack([(uv[:, 0] - hx) / hx, (uv[:, 1] - hy) / hy], 1), int(sharp.sum()))


def _informative(cand: np.ndarray, vc, target: Target, W: int, opts: PhotometricOptions,
                 rng: np.random.Generator) -> np.ndarray:
    """The candidates worth predicting (flat indices, sorted): pixels carry geometric information only within
    the blur disc of a cell edge. From the chief ray's point on the board, each candidate's distance to the
    nearest cell edge in pixels (the chief-ray map's scale: the 90th percentile over 256 of them); those within half the view's blur disc + 2 px
    are edge candidates, the others flat. Keeps up to 4 x what the selection takes of each, at random."""
    if cand.size == 0:   # nothing of the board's box left (saturated): the view is left out
        return cand
    uv = torch.tensor(np.stack([cand % W, cand // W], -1), dtype=torch.float64)
    probe = uv[torch.from_numpy(rng.choice(cand.size, min(cand.size, 256), replace=False))]
    steps = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]], dtype=torch.float64)
    with torch.no_grad():
        XY = on_board(vc.generate_rays(uv))[:, :2].numpy()
        hit = on_board(vc.generate_rays((probe[:, None, :] + steps).reshape(-1, 2))).reshape(-1, 3, 3)
    J = (hit[:, 1:, :2] - hit[:, :1, :2]).numpy()                    # (n, 2 (du, dv), 2 (X, Y)) mm per px
    with np.errstate(all="ignore"):
        near = np.full(cand.size, np.inf)
        for axis, edges in ((0, np.asarray(target.x_edges)), (1, np.asarray(target.y_edges))):
            dist_mm = np.abs(XY[:, axis, None] - edges[None, :]).min(1)
            per_px = np.nanpercentile(np.hypot(J[:, 0, axis], J[:, 1, axis]), 90)   # mm along this axis per px
            near = np.minimum(near, dist_mm / max(per_px, 1e-300))
    near = np.where(np.isfinite(near), near, np.inf)
    reach = 0.5 * board_blur_px(vc, target) + 2.0
    edge, flat = np.flatnonzero(near <= reach), np.flatnonzero(near > reach)
    want = 4 * (opts.max_pixels + opts.held_out_pixels)
    keep = [rng.choice(edge, min(edge.size, want), replace=False),
            rng.choice(flat, min(flat.size, want // 2), replace=False)]
    return np.sort(cand[np.concatenate(keep)])
