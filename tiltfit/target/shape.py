"""The target as it is: a printed board's shape fitted beside the camera (mrcal's board deformation, OpenCV's
release-object method). How much of it the views support is chosen in `tiltfit.select.board`.

    Board(nominal_mm, model)                -> points(θ) = nominal + B θ   (B constant: the shape is linear in θ)
    with_points(obs, points_mm)             -> the observations with other target points

Models (`BOARD_MODELS`), each fixing the gauge the poses leave free (a rigid motion of the board is a change of
every pose, and a scale of board and poses together changes no image, so no corner fit can see the board's
overall size; the nominal pitch along the target's X axis sets it):
    flat  the nominal points (no parameters).
    warp  three: the sag of the board out of its plane, dZ = c_x (1 − u²) + c_y (1 − v²) with u, v ∈ [−1, 1]
          the normalised target coordinates (mrcal's `calobject_warp`: a board bent along X and along Y), in mm
          at the centre relative to the edges; and the print scale along Y relative to X,
          Y' = Y_c + s (Y − Y_c) with s = 1 + `scale_y_minus_1` (a print stretched along one axis; Y_c the board's
          centre row).
    free  every point moves in 3D (OpenCV's `calibrateCameraRO`), except a gauge of 7 coordinates: the first
          point (3), the last point of the first row (3: with the first, the board's X axis and its length, as
          OpenCV's `iFixedPoint`) and the Z of the last point (the rotation about that axis).

Lengths in mm in the target frame (X along columns, Y along rows, Z = 0 the nominal plane).
"""
from __future__ import annotations

import torch

from tiltfit.calibrate.model import Observations

BOARD_MODELS = ("flat", "warp", "free")
#: Parameter names of the warp model (units: mm, mm, 1).
WARP_PARAMETERS = ("sag_x_mm", "sag_y_mm", "scale_y_minus_1")
#: A richer board model must predict held-out views better than the simpler one by this fraction to be chosen:
#: K-fold held-out errors on a few dozen views scatter by about 1 % (`tiltfit.select.held_out.HELD_OUT_TOLERANCE`).
BOARD_TOLERANCE = 0.01
#: ... and by this many standard errors of its gain over the views (the per-view differences of held-out squared
#: error, a paired comparison): over a dozen views a board with dozens of parameters wins a 1 % margin by chance
#: (sony_small: 13 views of 24 corners; 2: a one-sided chance of about 2.5 %).
BOARD_GAIN_Z = 2.0
#: A board model the views cannot carry is not tried by the automatic choice: at least this many corners seen
#: (over all views) per parameter of the board. The free model gives each point three coordinates, fixed only by
#: that point's own sightings (one corner, two numbers, per view) beside the poses and the lens they share: at 2
#: corners a parameter (a free board seen in about 6 views) each coordinate rests on 4 numbers of which the rest
#: of the fit takes its part; below it the points follow the corners' noise and trade against the lens (4 ChArUco
#: views, 48 corners for 29 parameters: f 396 ± 43 px where every other estimate was 610-684, issue 33 §5).
MIN_CORNERS_PER_BOARD_PARAMETER = 2.0
#: The board's Jacobian block is dense (V·N·3 rows by K parameters, a few copies of it in the solve): the free
#: model (K ≈ 3N) is not tried beyond this many entries (1.6e8 bytes a copy; 20 views of 160 points: 4.5e6).
MAX_BOARD_JACOBIAN_ENTRIES = 2e7


class Board:
    """A target's feature points as fitted: the nominal points plus a deformation linear in its parameters.

    Args:
        nominal_mm: (N, 3) the target file's feature points (row by row), mm.
        model: "flat", "warp" or "free" (module docstring).
        params: (K,) the deformation's parameters [zeros: the nominal board].
    Attributes:
        basis: (N, 3, K) ∂points/∂θ (constant); sigma: (K,) one-σ of the parameters once fitted, or None.
    """

    def __init__(self, nominal_mm, model: str = "flat", params=None):
        if model not in BOARD_MODELS:
            raise ValueError(f"board: expected one of {BOARD_MODELS}, got {model!r}")
        self.nominal_mm = torch.as_tensor(nominal_mm, dtype=torch.float64).clone()
        self.model = model
        self.basis = _basis(self.nominal_mm, model)
        K = self.basis.shape[-1]
        self.params = torch.zeros(K, dtype=torch.float64) if params is None else \
            torch.as_tensor(params, dtype=torch.float64).reshape(K).clone()
        self.sigma = None

    @property
    def n_params(self) -> int:
        return int(self.basis.shape[-1])

    def points(self, params: torch.Tensor | None = None) -> torch.Tensor:
        """(N, 3) the fitted points for `params` (default: the board's own), mm."""
        p = self.params if params is None else params
        return self.nominal_mm + self.basis @ p

    def copy(self) -> "Board":
        out = Board(self.nominal_mm, self.model, self.params)
        out.sigma = None if self.sigma is None else self.sigma.clone()
        return out

    def offsets_mm(self) -> torch.Tensor:
        """(N, 3) fitted minus nominal points, mm."""
        return self.points() - self.nominal_mm

    def summary(self) -> dict:
        """The fitted shape for CALIB.json: model, named parameters with σ (warp), and the points' offsets from the
        nominal board (largest in-plane and out-of-plane, and per point for `free`)."""
        off = self.offsets_mm()
        out = {"model": self.model,
               "max_offset_in_plane_mm": float(off[:, :2].norm(dim=-1).max()) if len(off) else 0.0,
               "max_offset_out_of_plane_mm": float(off[:, 2].abs().max()) if len(off) else 0.0}
        if self.model == "warp":
            out["parameters"] = {k: float(v) for k, v in zip(WARP_PARAMETERS, self.params)}
            if self.sigma is not None:
                out["sigma"] = {k: float(v) for k, v in zip(WARP_PARAMETERS, self.sigma)}
        if self.model == "free":
            out["points_mm"] = [[round(float(c), 5) for c in p] for p in self.points()]
            if self.sigma is not None:
                s = torch.zeros_like(off).reshape(-1)
                s[_free_index(self.nominal_mm)] = self.sigma
                out["sigma_points_mm"] = [[round(float(c), 5) for c in p] for p in s.reshape(-1, 3)]
        return out

    @classmethod
    def from_summary(cls, nominal_mm, entry: dict) -> "Board":
        """The board of a CALIB.json `board` entry (`summary`'s dict) over the target's nominal points."""
        model = entry.get("model", "flat")
        b = cls(nominal_mm, model)
        if model == "warp":
            b.params = torch.tensor([float(entry["parameters"][k]) for k in WARP_PARAMETERS], dtype=torch.float64)
        elif model == "free":
            pts = torch.as_tensor(entry["points_mm"], dtype=torch.float64)
            if pts.shape != b.nominal_mm.shape:
                raise ValueError(f"board.points_mm: expected {tuple(b.nominal_mm.shape)} points, "
                                 f"got {tuple(pts.shape)}")
            b.params = (pts - b.nominal_mm).reshape(-1)[_free_index(b.nominal_mm)]
        return b


def free_board_at(board: Board) -> Board:
    """A free board whose points start where `board`'s are (a warm start for the free model's fit from a simpler
    model's): every free coordinate at `board`'s, the gauge's 7 at their nominal values."""
    out = Board(board.nominal_mm, "free")
    out.params = board.offsets_mm().reshape(-1)[_free_index(board.nominal_mm)].clone()
    return out


def _free_index(nominal: torch.Tensor) -> torch.Tensor:
    """Flat (x, y, z per point) indices of the free model's parameters: all but the gauge (module docstring)."""
    n, c = nominal.shape[0], _row_length(nominal)
    fixed = {0, 1, 2, 3 * (c - 1), 3 * (c - 1) + 1, 3 * (c - 1) + 2, 3 * (n - 1) + 2}
    return torch.tensor([i for i in range(3 * n) if i not in fixed], dtype=torch.long)


def _row_length(nominal: torch.Tensor) -> int:
    """Points in the first row (equal Y), at least 2."""
    y0 = nominal[0, 1]
    n = int((torch.abs(nominal[:, 1] - y0) < 1e-9).sum())
    return max(n, 2)


def _basis(nominal: torch.Tensor, model: str) -> torch.Tensor:
    N = nominal.shape[0]
    if model == "flat":
        return torch.zeros(N, 3, 0, dtype=torch.float64)
    if model == "warp":
        lo, hi = nominal[:, :2].min(0).values, nominal[:, :2].max(0).values
        half = ((hi - lo) / 2).clamp_min(1e-9)
        mid = (hi + lo) / 2
        u, v = ((nominal[:, :2] - mid) / half).unbind(-1)
        B = torch.zeros(N, 3, 3, dtype=torch.float64)
        B[:, 2, 0] = 1 - u * u
        B[:, 2, 1] = 1 - v * v
        B[:, 1, 2] = nominal[:, 1] - mid[1]
        return B
    if N < _row_length(nominal) + 1:
        raise ValueError(f"board: the free model needs at least two rows of points, got {N} points")
    idx = _free_index(nominal)
    B = torch.zeros(3 * N, idx.numel(), dtype=torch.float64)
    B[idx, torch.arange(idx.numel())] = 1.0
    return B.reshape(N, 3, -1)


def with_points(obs: Observations, points_mm) -> Observations:
    """The same detections of other target points (the fitted board's)."""
    out = Observations(torch.as_tensor(points_mm, dtype=torch.float64).detach().clone(), obs.corners_px, obs.blur_px,
                       obs.image_size_px, obs.pixel_pitch_mm, list(obs.names))
    if hasattr(obs, "skipped"):
        out.skipped = obs.skipped
    return out


def describe_board(entries: list) -> str:
    """One line: which board model `select_board` chose and why."""
    chosen = next((e for e in entries if e.get("chosen")), None)
    if chosen is None:
        return "no model chosen"
    scored = ", ".join(f"{e['model']} {e['held_out_rms_px']:.4f} px" for e in entries if "held_out_rms_px" in e)
    return f"{chosen['model']}" + (f" (held-out error per corner: {scored}; a richer model must gain "
                                   f"{100 * BOARD_TOLERANCE:g} %)" if scored else "")

