"""An independent capture generator for a tilted thin lens whose radial distortion acts about the lens's own axis
(issue 33 §1): no projection, distortion or blur code of the project (nor OpenCV's) is called.

The lens, as docs/conventions.md defines it: centre at the origin of the camera frame (x right, y down, z forward),
sensor at z = −w, the lens plane tilted by θL about the axis (cos φ, sin φ, 0) so that its normal, the lens axis,
is n = (sin θL sin φ, −sin θL cos φ, cos θL). The chief ray of a point P passes the lens centre undeviated and
meets the sensor at the ideal image point. The radial distortion is symmetric about n: the ideal point's direction
is written in a frame whose z is n (any such frame: a radial distortion does not depend on the frame's turn about
n), distorted there with r² about n, and turned back; the distorted direction's central projection gives the pixel.
The frame here is the shortest rotation from ẑ to n (Rodrigues), not OpenCV's R_y(τy) R_x(τx).

The blur widths come from tracing rays: from P through points of the aperture's rim on the tilted lens plane, each
refracted by the thin-lens rule in slope form (its transverse slope relative to n loses (rim point) / f), met with
the sensor plane; the outline's equivalent-area diameter is the width. Gaussian noise is added to both.
"""
from __future__ import annotations

import math

import numpy as np

# The lens and sensor: an EOS 6D binned 4×4 behind a 50.8 mm lens (the paper's TS-E 45 mm as fitted), f/2.7.
WIDTH_PX, HEIGHT_PX, PITCH_MM = 1368, 912, 0.02616
W_MM = 55.39
F_MM = 1.0 / (1.0 / W_MM + 1.0 / 618.4)
D_MM = 18.81
PP_PX = ((WIDTH_PX - 1) / 2.0, (HEIGHT_PX - 1) / 2.0)

# The board: 8 × 5 interior corners, 25 mm squares (X along columns, Y along rows, Z = 0).
BOARD_MM = np.array([[25.0 * i, 25.0 * j, 0.0] for j in range(5) for i in range(8)])

# Board poses (turn about the camera x axis, about the y axis, distance of the board's centre, mm): 3 and 6 views.
POSES_3 = ((28.0, 0.0, 560.0), (-22.0, 18.0, 500.0), (8.0, -30.0, 660.0))
POSES_6 = POSES_3 + ((-30.0, -8.0, 610.0), (18.0, 24.0, 470.0), (0.0, 0.0, 720.0))


def _rotation(rx_deg: float, ry_deg: float) -> np.ndarray:
    a, b = math.radians(rx_deg), math.radians(ry_deg)
    Rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    Ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    return Ry @ Rx


def lens_axis(theta_L: float, phi: float) -> np.ndarray:
    return np.array([math.sin(theta_L) * math.sin(phi), -math.sin(theta_L) * math.cos(phi), math.cos(theta_L)])


def _frame_to(n: np.ndarray) -> np.ndarray:
    """The shortest rotation taking ẑ to the unit vector n (its columns the frame's axes, camera frame)."""
    z = np.array([0.0, 0.0, 1.0])
    v, c = np.cross(z, n), float(z @ n)
    if np.linalg.norm(v) < 1e-15:
        return np.eye(3)
    V = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + V + V @ V / (1.0 + c)


def project(p_cam: np.ndarray, theta_L: float, phi: float, k: tuple, about_axis: bool = True) -> np.ndarray:
    """(N, 3) camera-frame points -> (N, 2) pixels: the chief ray's direction, distorted radially about the lens
    axis (k1, k2, ... of r² in the lens frame; with `about_axis` False about the principal point, the camera
    frame's z), projected onto the sensor at w."""
    R = _frame_to(lens_axis(theta_L, phi)) if about_axis else np.eye(3)
    q = p_cam @ R                                  # lens-frame coordinates (Rᵀ p)
    x, y = q[:, 0] / q[:, 2], q[:, 1] / q[:, 2]
    r2 = x * x + y * y
    s = 1.0 + sum(c * r2 ** (i + 1) for i, c in enumerate(k))
    d = np.c_[x * s, y * s, np.ones_like(x)] @ R.T  # back to the camera frame along the distorted chief ray
    return np.c_[PP_PX[0] + W_MM / PITCH_MM * d[:, 0] / d[:, 2], PP_PX[1] + W_MM / PITCH_MM * d[:, 1] / d[:, 2]]


def blur_px(p_cam: np.ndarray, theta_L: float, phi: float, rim_points: int = 2048) -> np.ndarray:
    """(N, 3) camera-frame points -> (N,) blur diameters (pixels) by tracing rays through the aperture's rim."""
    n = lens_axis(theta_L, phi)
    R = _frame_to(n)
    t = np.linspace(0.0, 2 * math.pi, rim_points, endpoint=False)
    rim = 0.5 * D_MM * (np.cos(t)[:, None] * R[:, 0] + np.sin(t)[:, None] * R[:, 1])   # (M, 3) on the lens plane
    d_in = rim[None] - p_cam[:, None]                                                     # (N, M, 3) P -> rim
    # Thin lens, in slope form: the direction scaled to −1 along n (travelling from the scene to the sensor) has its
    # transverse part turned by −(rim point) / f; the image of P is where the refracted rays meet.
    out = -d_in / (d_in @ n)[..., None] - rim[None] / F_MM
    lam = (-W_MM - rim[None, :, 2]) / out[..., 2]  # rim + λ out on z = −w
    hit = rim[None] + lam[..., None] * out
    x, y = hit[..., 0], hit[..., 1]
    area = 0.5 * np.abs((x * np.roll(y, -1, 1) - np.roll(x, -1, 1) * y).sum(1))
    return 2 * np.sqrt(area / math.pi) / PITCH_MM


def capture(theta_L_deg: float, phi_deg: float, k: tuple, poses, seed: int, corner_noise_px: float = 0.07,
            blur_noise_px: float = 0.1, about_axis: bool = True):
    """(points (N, 3), corners (V, N, 2), blur widths (V, N)) of the board seen in `poses`."""
    theta_L, phi = math.radians(theta_L_deg), math.radians(phi_deg)
    rng = np.random.default_rng(seed)
    centre = BOARD_MM.mean(0)
    corners, widths = [], []
    for rx, ry, dist in poses:
        R = _rotation(rx, ry)
        T = np.array([0.0, 0.0, dist]) - R @ centre
        p = BOARD_MM @ R.T + T
        uv = project(p, theta_L, phi, k, about_axis)
        assert ((uv > 0) & (uv < (WIDTH_PX, HEIGHT_PX))).all(), f"pose {(rx, ry, dist)}: the board leaves the image"
        corners.append(uv + rng.normal(0, corner_noise_px, uv.shape))
        widths.append(blur_px(p, theta_L, phi) + rng.normal(0, blur_noise_px, len(p)))
    return BOARD_MM.copy(), np.stack(corners), np.stack(widths)
