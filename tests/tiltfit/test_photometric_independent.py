"""Photometric refinement judged on captures of a second, deliberately independent simulator.

`_capture` below shares no code with `renderer/` or `tiltfit/photometric/`: a physical thin lens tilted by θL
about the camera's x axis (each sensor point's conjugate by the lens formula along the tilted lens's normal, the
aperture a disc of diameter d in the tilted lens plane), its own sampling (per pixel 2 x 2 jittered sub-pixel
positions, each with its own stratified-jittered polar lens samples), paper and ink of non-zero reflectance, a
grey wall beyond the board's white margin, an illumination gradient and a glare spot that clips, sensor noise,
and a plain gamma-2.2 tone curve to 8 bits, read back as sRGB (so the fit meets a tone curve it does not know).
The truth (w, U, θF, d, θL) is derived from the same physics (U and θF from two conjugate points).

On those captures, started from the corner-and-blur fit (`tiltfit.detect.chessboard`, then the joint fit), the refinement
that `refine_photometric` keeps (`chosen_camera`: the refinement, or the corner fit where the held-out evidence
rejects it) is never worse than the corner fit by more than the photometric σ, for θL, θF and d, and better
where the corners are biased (heavy blur, ±5° tilt).
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from tiltfit.target.layout import Target

BOARD = Target(tuple(50.0 * i for i in range(7)), tuple(50.0 * j for j in range(5)), (0, 0), 25.0)
W_PX, H_PX, PITCH_MM, W_MM = 240, 160, 0.13, 55.0
PAPER, INK, WALL = 0.80, 0.06, 0.30
APERTURE = "auto"


# ------------------------------------------------------------------------------------------ the simulator

def _rot(rx_deg: float, ry_deg: float) -> np.ndarray:
    a, b = math.radians(rx_deg), math.radians(ry_deg)
    Rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    Ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    return Rx @ Ry


class TiltedThinLens:
    """A physical thin lens of focal length f at the origin, its plane tilted by `tilt_deg` about x, the sensor
    the plane z = −w (image inverted), aperture diameter d; camera frame x right, y down, z forward."""

    def __init__(self, w: float, f: float, d: float, tilt_deg: float):
        a = math.radians(tilt_deg)
        self.w, self.f, self.d = w, f, d
        self.n = np.array([0.0, -math.sin(a), math.cos(a)])          # the lens plane's normal
        self.e1 = np.array([1.0, 0.0, 0.0])
        self.e2 = np.cross(self.n, self.e1)
        # The truth in the calibration's terms: the plane of focus z = U + y tan θF through two conjugates.
        q0, q1 = self.conjugate(np.array([0.0, 0.0, -w])), self.conjugate(np.array([0.0, -2.0, -w]))
        self.U = float(q0[2])
        self.theta_F = math.atan2(q1[2] - q0[2], q1[1] - q0[1])
        self.theta_L = math.copysign(abs(a), self.theta_F)

    def sensor_point(self, u, v):
        return np.stack([-(u - (W_PX - 1) / 2) * PITCH_MM, -(v - (H_PX - 1) / 2) * PITCH_MM,
                         np.full(np.shape(u), -self.w)], -1)

    def conjugate(self, s: np.ndarray) -> np.ndarray:
        """Image of sensor point(s) s (..., 3): on the chief ray through the centre, at 1/s' = 1/f − 1/s measured
        along the lens's normal."""
        dist = -(s @ self.n)
        dist_img = 1.0 / (1.0 / self.f - 1.0 / dist)
        return -s * (dist_img / dist)[..., None]


def _radiance(Xb: np.ndarray, Yb: np.ndarray, board: Target, glare) -> np.ndarray:
    """Radiance of board points: ink in the dark cells, paper in the white ones and on the margin, a grey wall
    beyond; lit by a gradient across the board and a glare spot."""
    xe, ye = np.asarray(board.x_edges), np.asarray(board.y_edges)
    i = np.searchsorted(xe, Xb) - 1
    j = np.searchsorted(ye, Yb) - 1
    inside = (i >= 0) & (i < len(xe) - 1) & (j >= 0) & (j < len(ye) - 1)
    dark = inside & ((i + j) % 2 == (board.dark_cell[0] + board.dark_cell[1]) % 2)
    x0, y0, x1, y1 = board.extent_mm
    on_board = (Xb >= x0) & (Xb <= x1) & (Yb >= y0) & (Yb <= y1)
    rho = np.where(on_board, np.where(dark, INK, PAPER), WALL)
    light = 1.0 + 0.25 * (Xb - (x0 + x1) / 2) / (x1 - x0) - 0.15 * (Yb - (y0 + y1) / 2) / (y1 - y0)
    gx, gy = glare
    light = light + 0.6 * np.exp(-((Xb - gx) ** 2 + (Yb - gy) ** 2) / (2 * 8.0 ** 2))
    return rho * light


def _capture(lens: TiltedThinLens, R: np.ndarray, T: np.ndarray, board: Target, seed: int, lens_rings: int = 4,
             lens_sectors: int = 8) -> np.ndarray:
    """(H, W) 8-bit capture (as float 0-255) of the board at pose (R, T) through `lens`."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:H_PX, 0:W_PX].astype(np.float64)
    total = np.zeros((H_PX, W_PX))
    n_b = R[:, 2]
    x0, y0, x1, y1 = board.extent_mm
    glare = ((75.0, 25.0), (125.0, 75.0), (225.0, 125.0))[seed % 3]   # the middle of a white cell
    count = 0
    for sx in (-0.25, 0.25):
        for sy in (-0.25, 0.25):
            uu = u + sx + rng.uniform(-0.25, 0.25, u.shape)
            vv = v + sy + rng.uniform(-0.25, 0.25, v.shape)
            q = lens.conjugate(lens.sensor_point(uu, vv))                       # (H, W, 3)
            for ring in range(lens_rings):
                for sector in range(lens_sectors):
                    # Stratified in (r², φ) with a jitter per pixel: uniform over the disc.
                    r2 = (ring + rng.uniform(0, 1, u.shape)) / lens_rings
                    phi = 2 * math.pi * (sector + rng.uniform(0, 1, u.shape)) / lens_sectors
                    r = 0.5 * lens.d * np.sqrt(r2)
                    L = (r * np.cos(phi))[..., None] * lens.e1 + (r * np.sin(phi))[..., None] * lens.e2
                    dirn = q - L
                    t = ((T - L) @ n_b) / (dirn @ n_b)
                    P = L + t[..., None] * dirn
                    Xb = (P - T) @ R                                            # board frame: Rᵀ (P − T)
                    total += _radiance(Xb[..., 0], Xb[..., 1], board, glare)
                    count += 1
    linear = 0.85 * total / count
    linear = linear + rng.normal(0.0, 0.004, linear.shape)
    encoded = np.clip(linear, 0.0, 1.0) ** (1 / 2.2)                          # the camera's own tone curve
    return np.round(encoded * 255.0)


def _srgb_to_linear(c8: np.ndarray) -> np.ndarray:
    c = c8 / 255.0
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


#: The cases: (name, lens tilt °, aperture mm, focus distance mm untilted, views (rx°, ry°, distance mm)).
CASES = {
    "tilt +5°": (5.0, 40.0, 760.0, ((20.0, 5.0, 780.0), (-15.0, 15.0, 820.0), (-10.0, -10.0, 800.0))),
    "tilt -5°": (-5.0, 40.0, 760.0, ((20.0, 5.0, 780.0), (-15.0, 15.0, 820.0), (-10.0, -10.0, 800.0))),
    "heavy blur": (2.0, 60.0, 600.0, ((20.0, 5.0, 780.0), (-15.0, 15.0, 820.0), (-10.0, -10.0, 800.0))),
}


def _views(case: str, seed: int = 0):
    tilt, d, U0, views = CASES[case]
    f = 1.0 / (1.0 / W_MM + 1.0 / U0)
    lens = TiltedThinLens(W_MM, f, d, tilt)
    x0, y0, x1, y1 = BOARD.extent_mm
    centre = np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0])
    images, poses = [], []
    for k, (rx, ry, dist) in enumerate(views):
        R = _rot(rx, ry)
        T = np.array([0.0, 0.0, dist]) - R @ centre
        images.append(_capture(lens, R, T, BOARD, seed=1000 * seed + k))
        poses.append((R, T))
    return lens, images, poses


def _corner_start(case: str):
    """(lens, linear images, Observations, corner fit) of one case: tiltfit's detector and joint fit."""
    from tiltfit.calibrate.flow import calibrate
    from tiltfit.detect.chessboard import detect
    from tiltfit.calibrate.fit import FitOptions
    from tiltfit.calibrate.model import Observations

    lens, images, poses = _views(case)
    linear = [_srgb_to_linear(im) for im in images]
    dets = [detect(im, BOARD) for im in linear]
    found = [int(d.found.sum()) for d in dets]
    assert min(found) == BOARD.n_points, f"{case}: corners found {found}: the corner fit is the baseline"
    obs = Observations(BOARD.feature_points(), np.stack([d.corners_px for d in dets]),
                       np.stack([d.blur_px for d in dets]), (W_PX, H_PX), PITCH_MM)
    corner = calibrate(obs, "joint", options=FitOptions(model_selection=False, nominal_focal_mm=W_MM))
    return lens, linear, obs, corner


def _truth(lens: TiltedThinLens) -> dict:
    return {"theta_L_deg": math.degrees(lens.theta_L), "theta_F_deg": math.degrees(lens.theta_F),
            "d_mm": lens.d, "U_mm": lens.U, "w_mm": lens.w}


def _fits(case: str):
    """(truth, corner fit, photometric result) of one case."""
    from tiltfit.photometric import PhotometricOptions, refine_photometric

    lens, linear, obs, corner = _corner_start(case)
    res = refine_photometric(linear, BOARD, corner.camera, PhotometricOptions(max_pixels=800, aperture=APERTURE),
                             start_sigma=corner.sigma, corners=obs)
    return _truth(lens), corner, res


@pytest.fixture(scope="module")
def fits():
    return {case: _fits(case) for case in CASES}


KEYS = ("theta_L_deg", "theta_F_deg", "d_mm")


def _summary(case, truth, corner, res) -> str:
    chosen = res.chosen_camera.summary()
    return f"{case} (kept: {res.kept}{'; ' + res.rejected_because if res.rejected_because else ''}): " + "; ".join(
        f"{k} truth {truth[k]:.4f}, corners {corner.values[k] - truth[k]:+.4f} (σ {corner.sigma[k]:.4f}), "
        f"photometric {res.values[k] - truth[k]:+.4f} (σ {res.sigma[k]:.4f}), chosen {chosen[k] - truth[k]:+.4f}"
        for k in KEYS)


@pytest.mark.slow
def test_the_kept_calibration_is_never_worse_than_the_corner_fit_beyond_its_sigma(fits):
    for case, (truth, corner, res) in fits.items():
        chosen = res.chosen_camera.summary()
        for k in KEYS:
            err, err_c = abs(chosen[k] - truth[k]), abs(corner.values[k] - truth[k])
            assert err <= err_c + 2 * res.sigma[k], f"{k} worse than the corner fit: {_summary(case, truth, corner, res)}"


@pytest.mark.slow
def test_refinement_is_better_where_corners_are_biased(fits):
    for case, (truth, corner, res) in fits.items():
        chosen = res.chosen_camera.summary()
        # In units of each value's corner-fit σ, the three errors together.
        total = sum(((chosen[k] - truth[k]) / corner.sigma[k]) ** 2 for k in KEYS)
        total_c = sum(((corner.values[k] - truth[k]) / corner.sigma[k]) ** 2 for k in KEYS)
        assert total < total_c, f"no better than the corner fit: {_summary(case, truth, corner, res)}"
