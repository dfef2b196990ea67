"""Checks of an indexed board against the target file: a target too large to detect, a labelling another one fits
far better (`labelling_problem`, `labelling_note`) and colours that contradict the file (`colour_problem`,
`invert_photo` for white-on-black prints). Messages are one line, for the person who chose the target file.
"""
from __future__ import annotations

import math

import numpy as np

from tiltfit.detect.detection import DetectionError
from tiltfit.detect.imaging import _bilinear, apply_homography
from tiltfit.target.layout import MAX_FEATURE_POINTS, Target


def check_target_size(target: Target) -> None:
    """Raise DetectionError (one line) for a target too large to detect in bounded time."""
    ny, nx = target.grid_shape
    if target.n_points > MAX_FEATURE_POINTS:
        raise DetectionError(f"target: {nx} × {ny} = {target.n_points} corners; detection handles at most "
                             f"{MAX_FEATURE_POINTS} (200 × 200)")


# A labelling is contradicted when another labelling of the same corners fits the target's geometry (a plane
# homography) this many times better in RMS, and its own RMS exceeds MIN_CONTRADICTION_PX (lens distortion
# alone leaves a pixel or two); the factor is that of `tiltfit.files.det.mirrored`.
CONTRADICTION_FACTOR = 5.0


MIN_CONTRADICTION_PX = 1.0


# ... or when no labelling fits: the homography RMS above this fraction of the median corner spacing.
MAX_UNFIT_SPACING = 0.25


CONTRADICTS = "the photo contradicts the target file"


def _alternative_labellings(target: Target) -> dict:
    """{name: permutation} of the feature points under the target's symmetries that the colour reading can
    confuse: the half turn and the two mirror images (index arrays into feature order)."""
    ny, nx = target.grid_shape
    j, i = np.divmod(np.arange(nx * ny), nx)
    return {"turned by 180°": (ny - 1 - j) * nx + (nx - 1 - i),
            "mirrored left-right": j * nx + (nx - 1 - i),
            "mirrored top-bottom": (ny - 1 - j) * nx + i}


def _radial_unfit(XY: np.ndarray, corners_px: np.ndarray, grid_shape, image_size=None) -> float:
    """The smallest homography RMS over the corner spacing once a one-parameter radial distortion (the division
    model x_u = c + (x − c) / (1 + λ r²), r over the farthest corner's distance from c, c the image centre or
    the corners' centroid, λ in [−0.6, 0.6]) is undone: a wide-angle lens bends a close board's rows by a
    quarter of a cell, which no other labelling of its corners undoes, while a different board stays unfit.

    Args:
        XY: (N, 2) the target's feature points; corners_px: (N, 2) their image positions, NaN where missing;
        grid_shape: (ny, nx) with N = ny·nx, row by row (the spacing is the median step between grid neighbours,
        as in `labelling_problem`: memory linear in N); image_size: (W, H) or None.
    """
    from tiltfit.files.det import _homography_rms

    found = np.isfinite(corners_px).all(-1)
    uv = corners_px[found]
    c = np.asarray(image_size, dtype=np.float64) / 2 if image_size is not None else uv.mean(0)
    r0 = max(float(np.linalg.norm(uv - c, axis=1).max()), 1.0)
    d = (corners_px - c) / r0
    best = math.inf
    for lam in np.linspace(-0.6, 0.6, 25):
        u = c + r0 * d / (1.0 + lam * (d * d).sum(1, keepdims=True))  # NaN where missing
        rms = _homography_rms(XY[found], u[found])
        # the corner spacing in the undistorted points: the homography's scale, from the grid neighbours
        g = u.reshape(*grid_shape, 2)
        steps = np.concatenate([np.linalg.norm(np.diff(g, axis=1), axis=-1).ravel(),
                                np.linalg.norm(np.diff(g, axis=0), axis=-1).ravel()])
        spacing = float(np.nanmedian(steps)) if np.isfinite(steps).any() else 0.0
        best = min(best, rms / spacing if spacing > 0 else math.inf)
    return best


def labelling_problem(corners_px: np.ndarray, target: Target, image_size=None) -> str:
    """Why the labelled corners (N, 2, feature order, NaN where missing) contradict the target's geometry,
    or '' when they do not.

    The cell colours choose the labelling; the corner positions must then be a projective view of the
    target's feature points. A target file whose dark_cell parity (or dark and light) does not match the
    board, a mirrored photo, or a target with its rows and columns swapped gives a labelling that a plane
    homography does not fit, while (for the first two) a turned or mirrored labelling fits
    CONTRADICTION_FACTOR times better. A board that looks alike under the symmetry (uniform rows and
    columns) cannot be told apart and is not flagged.
    """
    from tiltfit.files.det import _homography_rms

    found = np.isfinite(corners_px).all(-1)
    if found.sum() < 8:
        return ""
    XY = target.feature_points()[:, :2]
    rms = _homography_rms(XY[found], corners_px[found])
    if not rms > MIN_CONTRADICTION_PX:
        return ""
    alternatives = {name: _homography_rms(XY[perm][found], corners_px[found])
                    for name, perm in _alternative_labellings(target).items()}
    name = min(alternatives, key=alternatives.get)
    if alternatives[name] * CONTRADICTION_FACTOR < rms:
        # The fitting labelling's handedness: target X, Y seen from the printed side map to image x right,
        # y down (det > 0, as in `tiltfit.files.det.mirrored`); det < 0 is a mirror image.
        P = XY[_alternative_labellings(target)[name]][found]
        A = np.linalg.lstsq(np.column_stack([P, np.ones(len(P))]), corners_px[found], rcond=None)[0][:2].T
        if np.linalg.det(A) < 0:
            why = ("a mirror image of the board: a mirrored photo, or a target file with x_edges/y_edges swapped "
                   "or reversed")
        else:
            why = ("the board turned by 180° with the other colour parity: dark_cell (or dark and light) swapped, or "
                   "a photo mirrored across uniform columns or rows")
        return (f"{CONTRADICTS}: the corners fit {why} (homography RMS {alternatives[name]:.2g} px), not the "
                f"labelling the cell colours give (RMS {rms:.2g} px)")
    ny, nx = target.grid_shape
    grid = corners_px.reshape(ny, nx, 2)
    steps = np.concatenate([np.linalg.norm(np.diff(grid, axis=1), axis=-1).ravel(),
                            np.linalg.norm(np.diff(grid, axis=0), axis=-1).ravel()])
    spacing = float(np.nanmedian(steps)) if np.isfinite(steps).any() else math.inf
    if rms > MAX_UNFIT_SPACING * spacing and _radial_unfit(XY, corners_px, (ny, nx), image_size) > MAX_UNFIT_SPACING:
        return (f"{CONTRADICTS}: no projective view of its {nx}×{ny} corners fits the photo's (homography RMS "
                f"{rms:.3g} px at a corner spacing of {spacing:.3g} px): a different board, or x_edges and "
                "y_edges swapped")
    return ""


def labelling_note(corners_px: np.ndarray, target: Target) -> str:
    """A note saying how the labelled corners (N, 2, feature order) lie when the target's columns (its X
    axis) run closer to the image's vertical than its horizontal: a board turned by 90° in the photo, or a
    target file with x_edges and y_edges swapped (on a board with uniform rows and columns both label the
    corners consistently, so only the note can tell); '' otherwise."""
    found = np.isfinite(corners_px).all(-1)
    if found.sum() < 3:
        return ""
    XY = target.feature_points()[found, :2]
    A = np.linalg.lstsq(np.column_stack([XY, np.ones(len(XY))]), corners_px[found], rcond=None)[0][:2].T
    if abs(A[1, 0]) <= abs(A[0, 0]):
        return ""
    ny, nx = target.grid_shape
    return (f"labelled with the target's {nx} corners a row (x_edges) running along the image's vertical: the "
            "board is turned by 90° in the photo, or the target file's x_edges and y_edges are swapped")


# What one photo of a checkerboard with uniform cells can tell about the target file (docs/charuco.md,
# "Inverted prints and mirror images"): every lattice symmetry changes a cell's parity i + j by a constant, so the
# colours fix the placement only up to that constant. A labelling is checked by (1) the cells' colours: the share
# of the cells next to found corners whose colour it predicts; 0 when no placement explains them (the target
# file's other dark_cell parity; or, on a board of even × even cells, a mirrored photo, which is the same
# picture); 1 when right. Below MIN_COLOUR_AGREEMENT, the midpoint, it is refused. (2) the margin: next to a light
# border cell, within the margin, the photo must stay light (one white sheet), read MARGIN_PROBE_SQUARES of a
# square out (at most half the margin) and normalised between the median dark (0) and light (1) cell; below
# 0.5 on most such probes the margin is dark: inverted colours (a white-on-black print, or an inverted photo).
# Blur spreads a cell's edge symmetrically, so a probe any distance out stays on its side of 0.5.
MIN_COLOUR_AGREEMENT = 0.5


MARGIN_PROBE_SQUARES = 0.15


# the least number of margin probes (inside the image) that decide, and the share of them that must be dark
MIN_MARGIN_PROBES = 3


DARK_MARGIN_SHARE = 0.75


def invert_photo(gray: np.ndarray) -> np.ndarray:
    """A photo of a white-on-black board as its dark-on-white counterpart: max − I (affine, so the corners and
    the blur widths stay where they are)."""
    return (np.float32(gray.max()) - gray).astype(np.float32)


def _cell_and_margin_samples(gray: np.ndarray, corners_px: np.ndarray, target: Target):
    """Grey levels at the centres of the cells next to found corners, and at margin probes beside the border
    cells, each placed by the local homography (`tiltfit.detect.blur._local_homographies`) of the nearest found corner.

    Returns:
        cells: (m, 3) [column, row, level]; margin: (p, 3) [column, row, level] of the border cell each probe
        is beside (probes outside the image left out).
    """
    import cv2

    from tiltfit.detect.blur import _local_homographies

    ny, nx = target.grid_shape
    found = np.isfinite(corners_px).all(-1)
    Hs = _local_homographies(target, corners_px, found)
    xe, ye = np.asarray(target.x_edges), np.asarray(target.y_edges)
    smooth = cv2.GaussianBlur(gray, (0, 0), 1.0)
    h, w = gray.shape
    cells, margin = {}, []
    for k, Hm in Hs.items():
        j, i = divmod(k, nx)
        for c, r in ((i, j), (i + 1, j), (i, j + 1), (i + 1, j + 1)):  # corner (i, j) touches cells i..i+1, j..j+1
            if (c, r) in cells:
                continue
            centre = np.array([[0.5 * (xe[c] + xe[c + 1]), 0.5 * (ye[r] + ye[r + 1])]])
            out = []
            s = min(xe[c + 1] - xe[c], ye[r + 1] - ye[r])
            d = min(MARGIN_PROBE_SQUARES * s, 0.5 * target.margin)
            if d > 0:
                if c == 0:
                    out.append([xe[0] - d, centre[0, 1]])
                if c == target.n_cols - 1:
                    out.append([xe[-1] + d, centre[0, 1]])
                if r == 0:
                    out.append([centre[0, 0], ye[0] - d])
                if r == target.n_rows - 1:
                    out.append([centre[0, 0], ye[-1] + d])
            xy = apply_homography(Hm, np.concatenate([centre, np.array(out).reshape(-1, 2)]))
            inside = (xy[:, 0] >= 2) & (xy[:, 0] <= w - 3) & (xy[:, 1] >= 2) & (xy[:, 1] <= h - 3)
            if not inside[0]:
                continue
            v = _bilinear(smooth, xy)
            cells[(c, r)] = v[0]
            margin += [[c, r, m] for m in v[1:][inside[1:]]]
    cells_a = np.array([[c, r, v] for (c, r), v in cells.items()]).reshape(-1, 3)
    return cells_a, np.array(margin).reshape(-1, 3)


def colour_problem(gray: np.ndarray, corners_px: np.ndarray, target: Target) -> str:
    """Why the labelled corners' colours contradict the target file (inverted colours, the other dark-cell
    parity or a mirrored photo), or '' when they do not or cannot be told (see the notes above
    MIN_COLOUR_AGREEMENT).

    Args:
        gray: (H, W) linear image, as detected (inverted already for an `inverted` target);
        corners_px: (N, 2) labelled corners, feature order, NaN where missing.
    """
    cells, margin = _cell_and_margin_samples(gray, corners_px, target)
    if len(cells) < 4:
        return ""
    lo, hi = np.percentile(cells[:, 2], [10, 90])
    if not hi > lo:
        return ""
    observed_dark = cells[:, 2] < 0.5 * (lo + hi)
    expected_dark = target.is_dark(cells[:, 0].astype(int), cells[:, 1].astype(int))
    if observed_dark.all() or not observed_dark.any():
        return ""
    dark_level = float(np.median(cells[observed_dark, 2]))
    light_level = float(np.median(cells[~observed_dark, 2]))
    # probes beside the border cells seen light: one white sheet with the margin, unless the colours are inverted
    light_cells = {(int(c), int(r)) for (c, r, _), d in zip(cells, observed_dark) if not d}
    beside_light = np.array([(int(c), int(r)) in light_cells for c, r, _ in margin], bool)
    probes = (margin[beside_light, 2] - dark_level) / (light_level - dark_level) if len(margin) else np.zeros(0)
    if len(probes) >= MIN_MARGIN_PROBES and np.mean(probes < 0.5) >= DARK_MARGIN_SHARE:
        if target.inverted:
            return (f"{CONTRADICTS}: inverted colours: the target file says \"inverted\": true, but the photo shows "
                    "dark cells on a light sheet (remove the key)")
        return (f"{CONTRADICTS}: inverted colours: the margin around the board is as dark as its dark cells "
                f"(median {np.median(probes):.2f} of the way from dark to light): a board printed white on black "
                "(add \"inverted\": true to the target file) or a colour-inverted photo")
    agreement = float(np.mean(observed_dark == expected_dark))
    if agreement < MIN_COLOUR_AGREEMENT:
        ny, nx = target.grid_shape
        mirror = (" or the photo is mirrored (on a board of an even number of cells each way a mirror image swaps "
                  "the colours)" if target.n_cols % 2 == 0 and target.n_rows % 2 == 0 else "")
        return (f"{CONTRADICTS}: the cells' colours match no placement of its {nx}×{ny} corners ({100 * agreement:.0f} % "
                f"of {len(cells)} cells agree with the best): its dark_cell has the other parity{mirror}")
    return ""
