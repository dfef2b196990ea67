"""Exact captures of a checkerboard through a tilted thin lens: a second generator, independent of the code it checks.

It shares no code with `renderer/` or `tiltfit/photometric/` (no camera class, no lens class, no blur closed form,
no sample set, no sRGB helper): numpy only, the physics written out again. Used to judge the photometric forward
model pixel by pixel (`benchmarks/photometric/bench_photometric_forward.py`) and the refinement (`tests/tiltfit/
test_photometric_exact.py`).

The camera (frame x right, y down, z forward; lens centre at the origin):
- a thin lens of focal length f whose plane is tilted by θL about the x axis, its unit normal
  n = (0, −sin θL, cos θL) (so the lens plane is z = y tan θL), the aperture a disc of diameter d in that plane;
- the sensor is the plane z = −w, read out upright: pixel (x, y) is the sensor point
  P = (−(x − (W−1)/2) p, −(y − (H−1)/2) p, −w) (the contract's pixel convention, the image inverted by the lens);
- every ray of P leaves its lens point L and passes through P's conjugate q: on the line from P through the
  lens centre, at the distance along n given by the lens formula 1/a + 1/b = 1/f (a, b measured along n).
  That is how an ideal thin lens refracts, whatever the tilt; nothing is linearised or integrated in closed form;
- each pixel is sampled over its area (S x S strata, a uniform jitter in each) and each sensor point over the
  aperture (A x A strata of the unit square, a uniform jitter in each, mapped to the disc by (√u, 2πv): equal
  areas); every ray is intersected with the board's plane and the board evaluated where it lands;
- rays carry weight 1 (the ideal lens of graphics; `radiometry="cos4"` weights each by the cosines at sensor and
  lens over the squared distance, the physical irradiance, to measure what that changes).

The board: the target's checkered area (ink reflectance in dark cells, paper in white ones), the white margin
(paper), and beyond it a background of its own reflectance; lit uniformly, or by a linear gradient across the
board (`light_gradient`).

The sensor: exposure scales radiance to a linear signal; photo-electrons are Poisson with `full_well` at signal 1,
read noise is Gaussian (electrons), then clipped, sRGB-encoded (IEC 61966-2-1, written out here) and rounded to
8 bits.

The truth in the calibration's terms (`ExactLens.truth`): w; U, the z where the optical axis meets the plane of
focus (the conjugate of the sensor's centre); θF, that plane's slope in y (from a second conjugate); θL; d.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ExactLens:
    """An ideal thin lens tilted by `tilt_deg` about the camera x axis, and its sensor.

    Attributes:
        w_mm: lens centre to sensor plane along z.
        f_mm: focal length.
        d_mm: aperture diameter.
        tilt_deg: θL, the lens plane's tilt (z = y tan θL).
        width_px, height_px, pitch_mm: the sensor.
    """

    w_mm: float
    f_mm: float
    d_mm: float
    tilt_deg: float
    width_px: int
    height_px: int
    pitch_mm: float

    @classmethod
    def focused_at(cls, w_mm: float, U0_mm: float, d_mm: float, tilt_deg: float, width_px: int, height_px: int,
                   pitch_mm: float) -> "ExactLens":
        """The lens whose untilted focus distance at sensor distance w is U0 (f from 1/f = 1/w + 1/U0)."""
        return cls(w_mm, 1.0 / (1.0 / w_mm + 1.0 / U0_mm), d_mm, tilt_deg, width_px, height_px, pitch_mm)

    @property
    def normal(self) -> np.ndarray:
        a = math.radians(self.tilt_deg)
        return np.array([0.0, -math.sin(a), math.cos(a)])

    def sensor_point(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """(..., 3) sensor points of pixel positions x (column), y (row)."""
        p = self.pitch_mm
        return np.stack([-(x - (self.width_px - 1) / 2) * p, -(y - (self.height_px - 1) / 2) * p,
                         np.full(np.shape(x), -self.w_mm)], -1)

    def conjugate(self, s: np.ndarray) -> np.ndarray:
        """(..., 3) the conjugates of points s (..., 3) behind the lens: on the line through the lens centre, at
        distance b along the normal with 1/a + 1/b = 1/f, a the point's distance along the normal."""
        a = -(s @ self.normal)
        b = 1.0 / (1.0 / self.f_mm - 1.0 / a)
        return -s * (b / a)[..., None]

    def truth(self) -> dict:
        """w_mm, U_mm, theta_F_deg, theta_L_deg, d_mm, f_mm of this lens in the calibration's terms."""
        q0 = self.conjugate(np.array([0.0, 0.0, -self.w_mm]))
        q1 = self.conjugate(np.array([0.0, -1.0, -self.w_mm]))    # a sensor point above the centre: image below
        theta_F = math.atan((q1[2] - q0[2]) / (q1[1] - q0[1]))
        return {"w_mm": self.w_mm, "U_mm": float(q0[2]), "theta_F_deg": math.degrees(theta_F),
                "theta_L_deg": self.tilt_deg, "d_mm": self.d_mm, "f_mm": self.f_mm}


@dataclass(frozen=True)
class Board:
    """The board's look: reflectances and lighting (the geometry comes from the target's edges and margin)."""

    paper: float = 0.80
    ink: float = 0.05
    background: float = 0.25
    light_gradient: tuple[float, float] = (0.0, 0.0)   # relative change of light across the board's X and Y


@dataclass(frozen=True)
class Sensor:
    """Exposure and noise: signal = exposure · radiance; `full_well` electrons at signal 1 (None: no shot noise);
    `read_noise_e` electrons; `encoding` "srgb8" (uint8 levels) or "linear" (float, no quantisation)."""

    exposure: float = 1.0
    full_well: float | None = 20000.0
    read_noise_e: float = 5.0
    encoding: str = "srgb8"


def rotation(rx_deg: float, ry_deg: float, rz_deg: float = 0.0) -> np.ndarray:
    """Rx · Ry · Rz (degrees): camera_from_board rotation of a board turned about its axes."""
    a, b, c = (math.radians(v) for v in (rx_deg, ry_deg, rz_deg))
    Rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    Ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    Rz = np.array([[math.cos(c), -math.sin(c), 0], [math.sin(c), math.cos(c), 0], [0, 0, 1]])
    return Rx @ Ry @ Rz


def pose_facing(target, rx_deg: float, ry_deg: float, distance_mm: float, shift_mm=(0.0, 0.0)):
    """(R, T) of a board turned by (rx, ry) whose centre sits at (shift_x, shift_y, distance) in the camera frame."""
    x0, y0, x1, y1 = _extent(target)
    R = rotation(rx_deg, ry_deg)
    T = np.array([shift_mm[0], shift_mm[1], distance_mm]) - R @ np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0])
    return R, T


def _extent(target) -> tuple[float, float, float, float]:
    m = float(target.margin)
    return (target.x_edges[0] - m, target.y_edges[0] - m, target.x_edges[-1] + m, target.y_edges[-1] + m)


def _reflectance(X: np.ndarray, Y: np.ndarray, target, board: Board) -> np.ndarray:
    xe, ye = np.asarray(target.x_edges, dtype=np.float64), np.asarray(target.y_edges, dtype=np.float64)
    i = np.searchsorted(xe, X, side="right") - 1
    j = np.searchsorted(ye, Y, side="right") - 1
    checkered = (i >= 0) & (i < xe.size - 1) & (j >= 0) & (j < ye.size - 1)
    dark = checkered & ((i + j) % 2 == (target.dark_cell[0] + target.dark_cell[1]) % 2)
    x0, y0, x1, y1 = _extent(target)
    on_board = (X >= x0) & (X <= x1) & (Y >= y0) & (Y <= y1)
    rho = np.where(on_board, np.where(dark, board.ink, board.paper), board.background)
    gx, gy = board.light_gradient
    if gx or gy:
        rho = rho * (1.0 + gx * (X - (x0 + x1) / 2) / (x1 - x0) + gy * (Y - (y0 + y1) / 2) / (y1 - y0))
    return rho


def radiance(lens: ExactLens, R: np.ndarray, T: np.ndarray, target, board: Board = Board(), *,
             aperture_strata: int = 12, pixel_strata: int = 4, seed: int = 0, radiometry: str = "uniform",
             chunk_pixels: int = 4096) -> np.ndarray:
    """(H, W) mean radiance of each pixel (no sensor), by exact tracing: pixel_strata² area samples per pixel,
    each with aperture_strata² stratified aperture samples (both jittered), every ray through the thin lens to
    the board at pose X_cam = R X_board + T."""
    if radiometry not in ("uniform", "cos4"):
        raise ValueError(f"radiometry: expected uniform or cos4, got {radiometry!r}")
    rng = np.random.default_rng(seed)
    W, H = lens.width_px, lens.height_px
    n = lens.normal
    e1 = np.array([1.0, 0.0, 0.0])
    e2 = np.cross(n, e1)
    nb = R[:, 2]                       # the board's normal in the camera frame
    off = float(T @ nb)
    S, A = int(pixel_strata), int(aperture_strata)
    ys, xs = np.divmod(np.arange(W * H), W)
    out = np.empty(W * H)
    for a in range(0, W * H, chunk_pixels):
        px, py = xs[a:a + chunk_pixels].astype(np.float64), ys[a:a + chunk_pixels].astype(np.float64)
        m = px.size
        total = np.zeros(m)
        weights = np.zeros(m)
        for si in range(S):
            for sj in range(S):
                sx = px - 0.5 + (si + rng.random(m)) / S
                sy = py - 0.5 + (sj + rng.random(m)) / S
                P = lens.sensor_point(sx, sy)                              # (m, 3)
                q = lens.conjugate(P)                                      # (m, 3)
                u = (np.arange(A)[:, None, None] + rng.random((A, A, m))) / A
                v = (np.arange(A)[None, :, None] + rng.random((A, A, m))) / A
                r = 0.5 * lens.d_mm * np.sqrt(u.reshape(-1, m))
                phi = 2.0 * math.pi * v.reshape(-1, m)
                L = (r * np.cos(phi))[..., None] * e1 + (r * np.sin(phi))[..., None] * e2   # (A², m, 3)
                dirn = q[None] - L
                t = (off - L @ nb) / (dirn @ nb)
                hit = L + t[..., None] * dirn
                Xb = (hit - T) @ R                                         # board frame: Rᵀ (X − T)
                rho = _reflectance(Xb[..., 0], Xb[..., 1], target, board)
                if radiometry == "cos4":
                    ray = L - P[None]
                    dist2 = (ray * ray).sum(-1)
                    wgt = (ray[..., 2] / np.sqrt(dist2)) * ((ray @ n) / np.sqrt(dist2)) / dist2
                else:
                    wgt = np.ones_like(rho)
                wgt = np.where(t > 0, wgt, 0.0)
                total += (rho * wgt).sum(0)
                weights += wgt.sum(0) if radiometry == "cos4" else A * A
        out[a:a + chunk_pixels] = total / np.maximum(weights, 1e-300)
    return out.reshape(H, W)


def encode_srgb(linear: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB transfer of linear values in [0, 1]."""
    v = np.clip(linear, 0.0, 1.0)
    return np.where(v <= 0.0031308, 12.92 * v, 1.055 * v ** (1.0 / 2.4) - 0.055)


def expose(rad: np.ndarray, sensor: Sensor = Sensor(), seed: int = 0) -> np.ndarray:
    """The sensor's reading of radiance `rad` (H, W): uint8 sRGB levels, or linear float with `encoding="linear"`."""
    rng = np.random.default_rng([seed, 7])
    signal = sensor.exposure * rad
    if sensor.full_well:
        electrons = rng.poisson(np.clip(signal, 0.0, None) * sensor.full_well).astype(np.float64)
        electrons += rng.normal(0.0, sensor.read_noise_e, signal.shape)
        signal = electrons / sensor.full_well
    if sensor.encoding == "linear":
        return signal
    if sensor.encoding != "srgb8":
        raise ValueError(f"encoding: expected srgb8 or linear, got {sensor.encoding!r}")
    return np.round(encode_srgb(signal) * 255.0).astype(np.uint8)


def noise_sigma(level: float, sensor: Sensor = Sensor()) -> float:
    """σ of the linear signal at `level` (shot and read noise; quantisation not included)."""
    if not sensor.full_well:
        return 0.0
    return math.sqrt(max(level, 0.0) * sensor.full_well + sensor.read_noise_e ** 2) / sensor.full_well


def capture(lens: ExactLens, R, T, target, board: Board = Board(), sensor: Sensor = Sensor(), *, seed: int = 0,
            **trace) -> np.ndarray:
    """One photograph: `radiance` then `expose` (keyword arguments of `radiance` pass through)."""
    return expose(radiance(lens, np.asarray(R, float), np.asarray(T, float), target, board, seed=seed, **trace),
                  sensor, seed)
