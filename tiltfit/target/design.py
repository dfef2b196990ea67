"""Designed targets (Maruyama & Kanatani): a checkerboard whose rows project equally spaced in a chosen view.

Design (`design_target`): for a target inclined by φ about its X axis at distance D in front of a camera
with lens-to-sensor distance w, a target point at height Y (from the design centre) images at
    y = w · Y cos φ / (D + Y sin φ)                                   (sensor mm)
a projective map of Y. Its inverse Y = y D / (w cos φ − y sin φ) turns equally spaced image rows
y_k = (k − n/2) Δ into the row edges, so the projected rows are equally spaced (the paper's Fig. 4 target).
"""
from __future__ import annotations

import math

import numpy as np

from .layout import Target, TargetError


def design_target(n_cols: int, n_rows: int, square_mm: float | None = None, *, w_mm: float, distance_mm: float,
                  inclination_deg: float = 0.0, pixel_pitch_mm: float | None = None,
                  square_px: float | None = None, margin_mm: float = 25.0, dark_cell=(0, 0),
                  decimals: int = 2) -> Target:
    """A target whose rows project equally spaced for the design view (Maruyama & Kanatani).

    The design view: the camera (lens-to-sensor distance w) looks along its axis at the design centre of
    the board, D away; the board is inclined by φ about its X axis, so a point (X, Y) from the design
    centre is at camera-frame (X, Y cos φ, D + Y sin φ) (φ > 0: rows further down the print are further
    away). Rows then image at y = w Y cos φ / (D + Y sin φ); the row edges are chosen as the inverse images
    Y_k = y_k D / (w cos φ − y_k sin φ) of y_k = (k − n_rows/2) Δ, with Δ = square · w cos φ / D (the
    projected square at the centre). Columns are uniform. Edges are rounded to `decimals` and shifted so the
    checkered area starts at (0, 0). `designed_pose` gives the design view's pose.

    Args:
        n_cols, n_rows: number of cells (use n_cols + n_rows odd so a 180° turn changes the corner colour).
        square_mm: column width and central row height, mm; or give `square_px` and `pixel_pitch_mm` for
            the square's projected size at the centre, pixels.
        w_mm, distance_mm, inclination_deg: the design view (w, D, φ).
    Returns:
        Target.
    """
    if n_cols < 2 or n_rows < 2:
        raise TargetError(f"n_cols, n_rows: expected at least 2 cells each, got {n_cols}, {n_rows}")
    if w_mm <= 0 or distance_mm <= 0:
        raise TargetError(f"w_mm, distance_mm: expected positive lengths, got {w_mm}, {distance_mm}")
    phi = math.radians(inclination_deg)
    if not abs(phi) < math.pi / 2:
        raise TargetError(f"inclination_deg: expected |φ| < 90, got {inclination_deg}")
    if square_mm is None:
        if square_px is None or pixel_pitch_mm is None:
            raise TargetError("square_mm: give square_mm, or square_px with pixel_pitch_mm")
        square_mm = square_px * pixel_pitch_mm * distance_mm / (w_mm * math.cos(phi))
    if not square_mm > 0:
        raise TargetError(f"square_mm: expected a positive length, got {square_mm}")
    delta = square_mm * w_mm * math.cos(phi) / distance_mm
    y_img = (np.arange(n_rows + 1) - n_rows / 2.0) * delta
    denom = w_mm * math.cos(phi) - y_img * math.sin(phi)
    if np.any(denom <= 0):
        raise TargetError("inclination_deg: the board would reach behind the camera; use fewer rows or less tilt")
    ys = y_img * distance_mm / denom
    xs = (np.arange(n_cols + 1) - n_cols / 2.0) * square_mm
    xs, ys = xs - xs[0], ys - ys[0]
    return Target(tuple(np.round(xs, decimals)), tuple(np.round(ys, decimals)), tuple(dark_cell), margin_mm)


def design_centre_mm(target: Target) -> tuple[float, float]:
    """(X_c, Y_c): the board point `design_target` placed on the optical axis.

    Rows of a designed target are a projective image of equally spaced indices, Y(k) = (αk + β)/(γk + 1),
    so three edges determine the map; the design centre is Y(n_rows / 2).
    """
    ys = np.asarray(target.y_edges)
    n = target.n_rows
    k = np.array([0.0, n // 2, n])
    Yk = ys[[0, n // 2, n]]
    # Y (γ k + 1) = α k + β  ->  [k, 1, −k Y] · (α, β, γ) = Y
    A = np.stack([k, np.ones(3), -k * Yk], axis=1)
    alpha, beta, gamma = np.linalg.solve(A, Yk)
    kc = n / 2.0
    return 0.5 * (target.x_edges[0] + target.x_edges[-1]), float((alpha * kc + beta) / (gamma * kc + 1.0))


def designed_pose(target: Target, distance_mm: float, inclination_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Pose (R, T), X_cam = R X_target + T, of the view `design_target` was made for.

    R is the rotation about the x axis by the inclination; the design centre sits at (0, 0, D).
    """
    from renderer.core.transforms import euler_xyz_deg

    R = euler_xyz_deg((inclination_deg, 0.0, 0.0)).numpy()
    xc, yc = design_centre_mm(target)
    T = np.array([0.0, 0.0, distance_mm]) - R @ np.array([xc, yc, 0.0])
    return R, T


def projected_row_spacing(target: Target, w_mm: float, distance_mm: float, inclination_deg: float) -> np.ndarray:
    """(n_rows,) projected row heights in the design view, sensor mm (uniform for a designed target)."""
    from renderer import project_pinhole

    R, T = designed_pose(target, distance_mm, inclination_deg)
    xc, _ = design_centre_mm(target)
    p = np.stack([np.full(target.n_rows + 1, xc), np.asarray(target.y_edges), np.zeros(target.n_rows + 1)], 1)
    pc = p @ R.T + T
    return np.diff(project_pinhole(pc, w_mm, (0.0, 0.0))[:, 1])  # sensor mm: focal w, centre 0
