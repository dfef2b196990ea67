"""The calibration target: a checkerboard with non-uniform row spacing (Maruyama & Kanatani).

Target frame (mm): the board lies in Z = 0, X along the columns (to the right on the print), Y along the rows
(downwards on the print), origin where the file's edges put it (designed targets: the top-left corner of the
checkered area). `x_edges` / `y_edges` are the ascending column / row boundaries of the checkered area;
cell (i, j) (column i, row j) is dark when i + j has the parity of `dark_cell[0] + dark_cell[1]`; a white
margin of `margin` mm surrounds the checkered area.

Feature points are the interior intersections (x_edges[1:-1] × y_edges[1:-1]), ordered row by row
(Y outer, X inner): feature point k = j · nx + i sits at (x_edges[i + 1], y_edges[j + 1], 0), where
nx = len(x_edges) − 2. Corner (i, j) touches cells (i, j), (i + 1, j), (i, j + 1) and (i + 1, j + 1).

Target file (JSON), as in the contract:
    {"type": "checkerboard", "units": "mm", "x_edges": [...], "y_edges": [...], "dark_cell": [0, 0],
     "margin": 25}
`type`, `x_edges`, `y_edges` are required; `units` ["mm"], `dark_cell` [[0, 0]], `margin` [25] and the
informational `name`, `description` are optional.

ChArUco boards (`CharucoTarget`, OpenCV's `cv2.aruco.CharucoBoard`): uniform squares with an ArUco marker
centred in every white cell, so a partial view still names its corners. Target file:
    {"type": "charuco", "units": "mm", "dictionary": "DICT_5X5_100", "squares": [sx, sy], "square_mm": s,
     "marker_mm": m, "margin": 25, "dark_cell": [0, 0]}
The checkered area spans [0, sx·s] × [0, sy·s]; feature point k is OpenCV's ChArUco corner id k (the same
row-by-row order); markers take ids 0, 1, … in the white cells row by row, as OpenCV places them. The top-left
square is dark (`dark_cell` [0, 0], OpenCV ≥ 4.6); `dark_cell` of odd parity is OpenCV's legacy pattern (top-left
white), which OpenCV draws only for an even number of rows.

Design (`design_target`): for a target inclined by φ about its X axis at distance D in front of a camera
with lens-to-sensor distance w, a target point at height Y (from the design centre) images at
    y = w · Y cos φ / (D + Y sin φ)                                   (sensor mm)
a projective map of Y. Its inverse Y = y D / (w cos φ − y sin φ) turns equally spaced image rows
y_k = (k − n/2) Δ into the row edges, so the projected rows are equally spaced (the paper's Fig. 4 target).
"""
from __future__ import annotations

import functools
import json
import math
import os
from dataclasses import dataclass, field

import numpy as np

from camio.checks import describe, is_finite_number, read_json

# Stated limit for target files: at most this many edges per axis (200 × 200 feature points, detection's own
# limit MAX_FEATURE_POINTS), so an absurd file is refused when it is loaded. Real boards have tens.
MAX_EDGES = 201
# The largest target `tiltfit.detect.chessboard` accepts (200 × 200 corners): beyond it the indexing (every placement of the
# seen corners on the target) and the bookkeeping per feature point would run for minutes or exhaust memory.
MAX_FEATURE_POINTS = 40_000
# Edge positions and the margin, mm: beyond a kilometre is a unit mistake, not a target.
MAX_MM = 1e6


class TargetError(ValueError):
    """A bad target file or target description; the message is one line naming the file and the field."""


@dataclass(frozen=True)
class Target:
    """A checkerboard target.

    Attributes:
        x_edges: ascending column boundaries of the checkered area, mm (at least 3: one interior edge).
        y_edges: ascending row boundaries, mm (at least 3).
        dark_cell: a (column, row) cell that is dark [(0, 0)]; only its parity matters.
        margin: width of the white border around the checkered area, mm [25].
        inverted: printed white on black [False]: the dark cells (and markers, margin) light and the light ones
            dark; detection inverts the photo first (OpenCV's `detectInvertedMarker`).
    """

    x_edges: tuple[float, ...]
    y_edges: tuple[float, ...]
    dark_cell: tuple[int, int] = (0, 0)
    margin: float = 25.0
    inverted: bool = field(default=False, kw_only=True)

    def __post_init__(self):
        object.__setattr__(self, "x_edges", tuple(float(v) for v in self.x_edges))
        object.__setattr__(self, "y_edges", tuple(float(v) for v in self.y_edges))
        object.__setattr__(self, "dark_cell", (int(self.dark_cell[0]), int(self.dark_cell[1])))
        object.__setattr__(self, "margin", float(self.margin))
        object.__setattr__(self, "inverted", bool(self.inverted))
        for name in ("x_edges", "y_edges"):
            problem = _edges_problem(getattr(self, name))
            if problem:
                raise TargetError(f"{name}: expected {problem}, got {list(getattr(self, name))}")
        if not (math.isfinite(self.margin) and self.margin >= 0):
            raise TargetError(f"margin: expected a non-negative number of mm, got {self.margin}")

    # --- sizes -------------------------------------------------------------------------------------------
    @property
    def n_cols(self) -> int:
        """Number of cell columns."""
        return len(self.x_edges) - 1

    @property
    def n_rows(self) -> int:
        """Number of cell rows."""
        return len(self.y_edges) - 1

    @property
    def grid_shape(self) -> tuple[int, int]:
        """(ny, nx): feature points per column and per row."""
        return len(self.y_edges) - 2, len(self.x_edges) - 2

    @property
    def n_points(self) -> int:
        ny, nx = self.grid_shape
        return nx * ny

    @property
    def extent_mm(self) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max) of the board including the margin, target frame, mm."""
        m = self.margin
        return self.x_edges[0] - m, self.y_edges[0] - m, self.x_edges[-1] + m, self.y_edges[-1] + m

    # --- features and colours ----------------------------------------------------------------------------
    def feature_points(self) -> np.ndarray:
        """(N, 3) float64 feature points in the target frame, mm, row by row (Y outer, X inner), Z = 0."""
        xs = np.asarray(self.x_edges[1:-1])
        ys = np.asarray(self.y_edges[1:-1])
        X, Y = np.meshgrid(xs, ys)  # (ny, nx)
        return np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], axis=-1)

    def feature_index(self, i, j):
        """Feature-point index k of corner (i, j) (column i, row j of interior intersections)."""
        return np.asarray(j) * self.grid_shape[1] + np.asarray(i)

    def is_dark(self, col, row) -> np.ndarray:
        """Whether cell (col, row) is dark; cells outside the checkered area (the margin) are white."""
        col, row = np.asarray(col), np.asarray(row)
        inside = (col >= 0) & (col < self.n_cols) & (row >= 0) & (row < self.n_rows)
        parity = (self.dark_cell[0] + self.dark_cell[1]) % 2
        return inside & ((col + row) % 2 == parity)

    def cell_colours(self) -> np.ndarray:
        """(n_rows, n_cols) bool, True where the cell is dark."""
        r, c = np.meshgrid(np.arange(self.n_rows), np.arange(self.n_cols), indexing="ij")
        return self.is_dark(c, r)

    def dark_rectangles(self) -> list[tuple[float, float, float, float]]:
        """Dark rectangles (x0, y0, x1, y1), mm, drawn inside white cells (ChArUco markers); none here."""
        return []

    @property
    def white_cell_clear_mm(self) -> float | None:
        """How far into a white cell from its edges it stays white, mm (None: the whole cell is white)."""
        return None

    def caption(self) -> str:
        """What the printable's caption says about the board."""
        return (f"{self.n_cols}x{self.n_rows} cells, board {self.x_edges[-1] - self.x_edges[0]:.1f} x "
                f"{self.y_edges[-1] - self.y_edges[0]:.1f} mm, margin {self.margin:g} mm")

    # --- files -------------------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        return {"type": "checkerboard", "units": "mm", "x_edges": list(self.x_edges),
                "y_edges": list(self.y_edges), "dark_cell": list(self.dark_cell), "margin": self.margin,
                **({"inverted": True} if self.inverted else {})}

    def save(self, path: str) -> None:
        """Write the target file (JSON)."""
        from camio.files import write_text

        write_text(path, json.dumps(self.to_dict(), indent=1) + "\n")


def _edges_problem(edges) -> str | None:
    if len(edges) < 3:
        return "at least 3 edges (one interior intersection)"
    if not all(is_finite_number(v) and abs(v) <= MAX_MM for v in edges):
        return f"finite numbers within ±{MAX_MM:g} mm"
    if any(b <= a for a, b in zip(edges, edges[1:])):
        return "strictly ascending values"
    return None


_KNOWN_KEYS = ("type", "units", "x_edges", "y_edges", "dark_cell", "margin", "inverted", "name", "description")


def _inverted(data: dict, fail) -> bool:
    """The optional `inverted` key: a JSON boolean (false by default)."""
    value = data.get("inverted", False)
    if not isinstance(value, bool):
        fail("inverted", "true or false (a board printed white on black)", value)
    return value


def target_from_dict(data, source: str = "<target>") -> Target:
    """Validate a target description (the parsed JSON) and build the Target; errors name `source` and field."""

    def fail(field, expected, got):
        shown = describe(got) if not isinstance(got, list) or len(got) <= 12 else f"a list of {len(got)} values"
        raise TargetError(f"{source}: {field}: expected {expected}, got {shown}")

    if not isinstance(data, dict):
        raise TargetError(f"{source}: expected a JSON object, got {type(data).__name__}")
    if data.get("type") == "charuco":
        return charuco_from_dict(data, source)
    unknown = [k for k in data if k not in _KNOWN_KEYS]
    if unknown:
        raise TargetError(f"{source}: {unknown[0]}: unknown key (expected one of: {', '.join(_KNOWN_KEYS)})")
    for key in ("type", "x_edges", "y_edges"):
        if key not in data:
            raise TargetError(f"{source}: {key}: missing key")
    if data["type"] != "checkerboard":
        fail("type", '"checkerboard" or "charuco"', data["type"])
    if data.get("units", "mm") != "mm":
        fail("units", '"mm"', data["units"])
    edges = {}
    for key in ("x_edges", "y_edges"):
        v = data[key]
        if not isinstance(v, list) or not all(_is_number(e) for e in v):
            fail(key, "a list of numbers (mm)", v)
        problem = _edges_problem(v) or (f"at most {MAX_EDGES} edges" if len(v) > MAX_EDGES else None)
        if problem:
            fail(key, problem, v)
        edges[key] = v
    dark = data.get("dark_cell", [0, 0])
    if (not isinstance(dark, list) or len(dark) != 2
            or not all(is_finite_number(e) and float(e) == int(e) and abs(e) < 2**31 for e in dark)):
        fail("dark_cell", "[column, row] integers", dark)
    margin = data.get("margin", 25.0)
    if not is_finite_number(margin) or not 0 <= margin <= MAX_MM:
        fail("margin", "a non-negative number of mm", margin)
    inverted = _inverted(data, fail)
    return Target(tuple(edges["x_edges"]), tuple(edges["y_edges"]), (int(dark[0]), int(dark[1])), float(margin),
                  inverted=inverted)


def _is_number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def load_target(path: str) -> Target:
    """Read and validate a target file; raises TargetError with a one-line message naming file and field."""
    if not os.path.exists(path):
        raise TargetError(f"{path}: no such file")
    return target_from_dict(read_json(path, TargetError, "target file"), path)


# --- ChArUco boards ----------------------------------------------------------------------------------------
def aruco_dictionaries() -> list[str]:
    """Names of OpenCV's predefined ArUco dictionaries (`cv2.aruco.DICT_*`)."""
    import cv2

    return sorted(n for n in dir(cv2.aruco) if n.startswith("DICT_") and isinstance(getattr(cv2.aruco, n), int))


def aruco_dictionary(name: str):
    """OpenCV's predefined dictionary `name` (e.g. "DICT_5X5_100")."""
    import cv2

    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))


@functools.lru_cache(maxsize=8)
def _marker_bits(name: str, n_markers: int) -> tuple[np.ndarray, ...]:
    """Per marker id, its (b + 2, b + 2) bool image, True where dark (the border included), rows downwards."""
    d = aruco_dictionary(name)
    side = d.markerSize + 2
    return tuple(d.generateImageMarker(k, side) < 128 for k in range(n_markers))


@dataclass(frozen=True)
class CharucoTarget(Target):
    """A ChArUco board as OpenCV's `cv2.aruco.CharucoBoard` draws it: uniform squares, an ArUco marker centred in
    each white cell (ids 0, 1, … row by row), one-bit marker border.

    Attributes (besides Target's; the edges are uniform from 0):
        dictionary: OpenCV dictionary name, e.g. "DICT_5X5_100".
        marker_mm: marker side incl. its black border, mm (less than the square).
    """

    dictionary: str = "DICT_5X5_100"
    marker_mm: float = 0.0

    @classmethod
    def board(cls, squares, square_mm: float, marker_mm: float, dictionary: str = "DICT_5X5_100",
              margin: float = 25.0, dark_cell=(0, 0), inverted: bool = False) -> "CharucoTarget":
        """The board of squares = (columns, rows) cells of `square_mm`, checkered area from (0, 0)."""
        sx, sy = int(squares[0]), int(squares[1])
        return cls(tuple(square_mm * i for i in range(sx + 1)), tuple(square_mm * j for j in range(sy + 1)),
                   tuple(dark_cell), margin, dictionary, float(marker_mm), inverted=inverted)

    @property
    def square_mm(self) -> float:
        return self.x_edges[1] - self.x_edges[0]

    @property
    def squares(self) -> tuple[int, int]:
        """(columns, rows) of cells: OpenCV's `size`."""
        return self.n_cols, self.n_rows

    @property
    def legacy_pattern(self) -> bool:
        """OpenCV's legacy pattern: the top-left square white (odd `dark_cell` parity)."""
        return (self.dark_cell[0] + self.dark_cell[1]) % 2 == 1

    def marker_cells(self) -> np.ndarray:
        """(M, 2) int (column, row) of the white cells, row by row: marker id m sits in cell m."""
        dark = self.cell_colours()
        rows, cols = np.nonzero(~dark)
        return np.stack([cols, rows], -1)

    @property
    def white_cell_clear_mm(self) -> float:
        return 0.5 * (self.square_mm - self.marker_mm)

    def dark_rectangles(self, data_bits_only: bool = False) -> list[tuple[float, float, float, float]]:
        """The markers' dark bits as rectangles (x0, y0, x1, y1), mm, runs along each bit row merged;
        `data_bits_only`: without the black border (what makes a corner's neighbourhood asymmetric)."""
        cells = self.marker_cells()
        bits = _marker_bits(self.dictionary, len(cells))
        s, m = self.square_mm, self.marker_mm
        out = []
        for (i, j), b in zip(cells, bits):
            n = b.shape[0]
            bit = m / n
            x0 = self.x_edges[0] + (i + 0.5) * s - 0.5 * m
            y0 = self.y_edges[0] + (j + 0.5) * s - 0.5 * m
            if data_bits_only:
                b = b.copy()
                b[[0, -1], :] = False
                b[:, [0, -1]] = False
            for r in range(n):
                row = np.concatenate([[False], b[r], [False]])
                starts = np.nonzero(row[1:] & ~row[:-1])[0]
                ends = np.nonzero(~row[1:] & row[:-1])[0]
                out += [(x0 + a * bit, y0 + r * bit, x0 + e * bit, y0 + (r + 1) * bit) for a, e in zip(starts, ends)]
        return out

    def opencv_board(self):
        """The same board as `cv2.aruco.CharucoBoard` (lengths in mm; its corner id k is feature point k)."""
        import cv2

        board = cv2.aruco.CharucoBoard(self.squares, self.square_mm, self.marker_mm,
                                       aruco_dictionary(self.dictionary))
        board.setLegacyPattern(self.legacy_pattern)
        return board

    def caption(self) -> str:
        return (f"ChArUco {self.n_cols}x{self.n_rows} squares of {self.square_mm:g} mm, markers {self.marker_mm:g} mm "
                f"{self.dictionary}, margin {self.margin:g} mm")

    def to_dict(self) -> dict:
        return {"type": "charuco", "units": "mm", "dictionary": self.dictionary, "squares": list(self.squares),
                "square_mm": self.square_mm, "marker_mm": self.marker_mm, "margin": self.margin,
                "dark_cell": list(self.dark_cell), **({"inverted": True} if self.inverted else {})}


_CHARUCO_KEYS = ("type", "units", "dictionary", "squares", "square_mm", "marker_mm", "margin", "dark_cell", "inverted",
                 "name", "description")


def charuco_from_dict(data: dict, source: str = "<target>") -> CharucoTarget:
    """Validate a `"type": "charuco"` target description; errors are one line naming `source` and the field."""

    def fail(field, expected, got):
        raise TargetError(f"{source}: {field}: expected {expected}, got {describe(got)}")

    unknown = [k for k in data if k not in _CHARUCO_KEYS]
    if unknown:
        raise TargetError(f"{source}: {unknown[0]}: unknown key for a charuco target (expected one of: "
                          f"{', '.join(_CHARUCO_KEYS)})")
    for key in ("dictionary", "squares", "square_mm", "marker_mm"):
        if key not in data:
            raise TargetError(f"{source}: {key}: missing key")
    if data.get("units", "mm") != "mm":
        fail("units", '"mm"', data["units"])
    names = aruco_dictionaries()
    if data["dictionary"] not in names:
        fail("dictionary", "an OpenCV dictionary name such as DICT_5X5_100 (DICT_4X4_50 … DICT_ARUCO_ORIGINAL)",
             data["dictionary"])
    sq = data["squares"]
    if (not isinstance(sq, list) or len(sq) != 2
            or not all(is_finite_number(v) and float(v) == int(v) and 2 <= v <= MAX_EDGES - 1 for v in sq)):
        fail("squares", f"[columns, rows], integers 2 to {MAX_EDGES - 1}", sq)
    s, m = data["square_mm"], data["marker_mm"]
    if not is_finite_number(s) or not 0 < s <= MAX_MM:
        fail("square_mm", "a positive number of mm", s)
    if not is_finite_number(m) or not 0 < m < s:
        fail("marker_mm", f"a positive number of mm below square_mm ({s:g})", m)
    margin = data.get("margin", 25.0)
    if not is_finite_number(margin) or not 0 <= margin <= MAX_MM:
        fail("margin", "a non-negative number of mm", margin)
    dark = data.get("dark_cell", [0, 0])
    if (not isinstance(dark, list) or len(dark) != 2
            or not all(is_finite_number(e) and float(e) == int(e) and abs(e) < 2**31 for e in dark)):
        fail("dark_cell", "[column, row] integers", dark)
    if (int(dark[0]) + int(dark[1])) % 2 == 1 and int(sq[1]) % 2 == 1:
        fail("dark_cell", "even parity ([0, 0]: the top-left square dark); OpenCV's legacy pattern (top-left white) "
             f"exists only for an even number of rows, and squares has {int(sq[1])}", dark)
    inverted = _inverted(data, fail)
    target = CharucoTarget.board((int(sq[0]), int(sq[1])), float(s), float(m), data["dictionary"], float(margin),
                                 (int(dark[0]), int(dark[1])), inverted)
    n_markers, size = len(target.marker_cells()), aruco_dictionary(data["dictionary"]).bytesList.shape[0]
    if n_markers > size:
        fail("squares", f"a board with at most {size} white cells ({data['dictionary']} has {size} markers; this board "
             f"needs {n_markers})", sq)
    return target


# --- design ------------------------------------------------------------------------------------------------
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


# --- images of the board -----------------------------------------------------------------------------------
def _cumulative_sign(edges: np.ndarray, first_sign: float, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Along one axis: (length of [e0, x] inside the checkered span, ∫ of the ±1 column sign up to x)."""
    e = np.asarray(edges, dtype=np.float64)
    signs = first_sign * (-1.0) ** np.arange(len(e) - 1)
    knots_sign = np.concatenate([[0.0], np.cumsum(signs * np.diff(e))])
    inside = np.interp(x, e, e - e[0], left=0.0, right=e[-1] - e[0])
    signed = np.interp(x, e, knots_sign, left=0.0, right=knots_sign[-1])
    return inside, signed


def rasterise(target: Target, x_range_mm, y_range_mm, width_px: int, height_px: int,
              dark: float = 0.0, white: float = 1.0) -> np.ndarray:
    """Exact area-averaged (H, W) image of the board over a rectangle of the target plane.

    Pixel (c, r) covers X in x0 + [c, c + 1]·(x1 − x0)/W and Y likewise (column = X, row = Y). The checker is
    separable in ±1 signs, so each pixel's dark fraction is (A + ε · Sx · Sy) / 2 with A the overlap of the
    pixel with the checkered area and Sx, Sy the signed overlaps along each axis.
    """
    x0, x1 = x_range_mm
    y0, y1 = y_range_mm
    bx = np.linspace(x0, x1, width_px + 1)
    by = np.linspace(y0, y1, height_px + 1)
    ax, sx = (np.diff(v) for v in _cumulative_sign(target.x_edges, 1.0, bx))
    ay, sy = (np.diff(v) for v in _cumulative_sign(target.y_edges, 1.0, by))
    eps = 1.0 if (target.dark_cell[0] + target.dark_cell[1]) % 2 == 0 else -1.0
    dark_area = 0.5 * (np.outer(ay, ax) + eps * np.outer(sy, sx))
    add_rectangles(dark_area, bx, by, target.dark_rectangles())
    dark_frac = dark_area / (np.diff(by)[:, None] * np.diff(bx)[None, :])
    return (white + (dark - white) * dark_frac).astype(np.float32)


def add_rectangles(dark_area: np.ndarray, bx: np.ndarray, by: np.ndarray, rectangles) -> None:
    """Add to `dark_area` (H, W) each rectangle's (x0, y0, x1, y1) overlap with the pixels bounded by bx (W + 1)
    and by (H + 1), ascending, mm (separable: the outer product of the overlaps along each axis)."""
    for rx0, ry0, rx1, ry1 in rectangles:
        cx = np.diff(np.clip(bx, rx0, rx1))
        cy = np.diff(np.clip(by, ry0, ry1))
        c0, c1 = max(int(np.searchsorted(bx, rx0)) - 1, 0), int(np.searchsorted(bx, rx1)) + 1
        r0, r1 = max(int(np.searchsorted(by, ry0)) - 1, 0), int(np.searchsorted(by, ry1)) + 1
        dark_area[r0:r1, c0:c1] += np.outer(cy[r0:r1], cx[c0:c1])


def render_target(target: Target, dpi: float) -> np.ndarray:
    """(H, W) float32 reflectance image of the board incl. margin at `dpi` (dark 0, white 1, edges area-averaged).

    Row 0 is the top of the print (smallest Y), column 0 the left (smallest X); one pixel is 25.4 / dpi mm.
    The image is the whole number of pixels that covers the board; any fraction left over is white.
    """
    x0, y0, x1, y1 = target.extent_mm
    px = 25.4 / dpi
    W, H = int(math.ceil((x1 - x0) / px - 1e-9)), int(math.ceil((y1 - y0) / px - 1e-9))
    return rasterise(target, (x0, x0 + W * px), (y0, y0 + H * px), W, H)


def target_texture(target: Target, px_per_mm: float, dark: float = 0.0, white: float = 1.0) -> np.ndarray:
    """(H, W, 3) float32 linear texture of the board incl. margin, for a textured `rectangle`.

    Orientation: image column = target X, image row = target Y; column 0 / row 0 at (x_min, y_min) of
    `target.extent_mm`, the last column / row at (x_max, y_max). The image covers the extent exactly:
    W = round(width · px_per_mm), so the actual scale is W / width (likewise H). Edges are area-averaged.
    """
    x0, y0, x1, y1 = target.extent_mm
    W = max(1, int(round((x1 - x0) * px_per_mm)))
    H = max(1, int(round((y1 - y0) * px_per_mm)))
    img = rasterise(target, (x0, x1), (y0, y1), W, H, dark, white)
    return np.repeat(img[..., None], 3, axis=-1)


def write_printable(target: Target, png_path: str | None, pdf_path: str | None, dpi: float = 300.0,
                    scale_bar_mm: float | None = None) -> None:
    """Write the board at true size with a scale bar below it: a PNG at `dpi` and/or a vector PDF.

    The page is the board incl. margin plus a 15 mm strip at the bottom holding a scale bar of
    `scale_bar_mm` (default: the largest of 10/20/50/100/200 mm that fits) with 10 mm ticks and a caption;
    print at 100 % and check the bar with a ruler.
    """
    x0, y0, x1, y1 = target.extent_mm
    width, strip = x1 - x0, 15.0
    if not (math.isfinite(dpi) and MIN_PRINT_DPI <= dpi <= MAX_PRINT_DPI):
        raise TargetError(f"dpi: expected {MIN_PRINT_DPI:g} to {MAX_PRINT_DPI:g} dots per inch, got {dpi:g}")
    if max(width, y1 + strip - y0) > MAX_PRINT_MM:
        raise TargetError(f"margin: the page would be {width / 1000:.3g} × {(y1 + strip - y0) / 1000:.3g} m "
                          f"(at most {MAX_PRINT_MM / 1000:g} m a side); use a smaller margin or board")
    if scale_bar_mm is None:
        fits = [v for v in (10.0, 20.0, 50.0, 100.0, 200.0) if v <= 0.8 * width]
        scale_bar_mm = fits[-1] if fits else 0.5 * width
    bar_room = x1 - _bar_geometry(target, strip, 0.0)[0]
    if not (math.isfinite(scale_bar_mm) and 0 < scale_bar_mm <= bar_room):
        raise TargetError(f"scale_bar_mm: expected a length in (0, {bar_room:.4g}] mm (the bar fits on the page), "
                          f"got {scale_bar_mm:g}")
    caption = f"{target.caption()}; bar = {scale_bar_mm:g} mm"
    if png_path:
        pixels = (width / 25.4 * dpi) * ((y1 + strip - y0) / 25.4 * dpi)
        if not (dpi > 0 and pixels <= MAX_PRINT_PIXELS):
            raise TargetError(f"dpi: {dpi:g} dpi gives a {pixels / 1e6:.0f}-megapixel PNG of this "
                              f"{width:.0f} × {y1 - y0:.0f} mm board (at most {MAX_PRINT_PIXELS / 1e6:.0f}); "
                              f"lower the dpi or print the PDF")
        _write_png(target, png_path, dpi, strip, scale_bar_mm, caption)
    if pdf_path:
        _write_pdf(target, pdf_path, strip, scale_bar_mm, caption)


# the largest PNG `write_printable` writes (a poster of 1.2 × 0.85 m at 600 dpi)
MAX_PRINT_PIXELS = 400e6
# Print resolutions: below 10 dpi a square is a few pixels; above 10,000 no printer resolves it.
MIN_PRINT_DPI, MAX_PRINT_DPI = 10.0, 10000.0
# The largest page side, mm (a 10 m banner); larger is a unit mistake in the margin or edges.
MAX_PRINT_MM = 10000.0


def _bar_geometry(target, strip, bar_mm):
    x0, _, _, y1 = target.extent_mm
    bx0 = x0 + max(5.0, 0.1 * target.margin)
    by0 = y1 + 4.0
    return bx0, by0, bar_mm, 2.0  # left, top, length, thickness (mm)


# Rows of the board rasterised at a time by `_write_png`: about 2^20 pixels a strip, so a poster needs tens of
# MB (rasterise holds a few float64 arrays of the strip), however large the page.
PNG_STRIP_PIXELS = 1 << 20


def _write_png(target, path, dpi, strip, bar_mm, caption):
    """The board rasterised exactly at `dpi`, the bar and its ticks drawn in pixels, the caption (the bar's
    length) drawn as text over the strip; an 8-bit grey PNG that records its dpi so viewers and printers keep
    true size. Written through OpenImageIO in strips of rows (`PNG_STRIP_PIXELS`): memory does not grow with the
    page (a 0.71 m board at 300 dpi, 72 megapixels, once took 10 GB as one float image)."""
    import OpenImageIO as oiio

    from camio.files import atomic_output, quiet_c_stderr

    x0, y0, x1, y1 = target.extent_mm
    px = 25.4 / dpi
    W, H = int(math.ceil((x1 - x0) / px - 1e-9)), int(math.ceil((y1 + strip - y0) / px - 1e-9))
    Hb = int(math.ceil((y1 - y0) / px - 1e-9))
    spec = oiio.ImageSpec(W, H, 1, oiio.UINT8)
    spec.attribute("XResolution", float(dpi))
    spec.attribute("YResolution", float(dpi))
    spec.attribute("ResolutionUnit", "in")
    spec.attribute("oiio:ColorSpace", "sRGB")
    rects = np.asarray(target.dark_rectangles(), dtype=np.float64).reshape(-1, 4)
    rows = max(1, PNG_STRIP_PIXELS // W)
    with atomic_output(path) as tmp:
        out = oiio.ImageOutput.create("png")
        if not out or not out.open(tmp, spec):
            raise OSError(f"cannot write PNG ({(out.geterror() if out else '') or oiio.geterror()})")
        try:
            for r0 in range(0, Hb, rows):
                r1 = min(Hb, r0 + rows)
                ya, yb = y0 + r0 * px, y0 + r1 * px
                near = rects[(rects[:, 3] > ya) & (rects[:, 1] < yb)]  # the markers this strip crosses
                img = rasterise(_WithRectangles(target, near), (x0, x0 + W * px), (ya, yb), W, r1 - r0)
                _write_rows(out, r0, _srgb8(img))
            _write_rows(out, Hb, _scale_bar_rows(target, dpi, strip, bar_mm, caption, W, H, Hb))
        except BaseException:
            with quiet_c_stderr():  # libpng complains of the unfinished file, which atomic_output removes
                out.close()
            raise
        if not out.close():
            raise OSError(f"cannot write PNG ({out.geterror() or 'close failed'})")


class _WithRectangles:
    """A target seen through `rasterise` with only some of its dark rectangles (those a strip crosses)."""

    def __init__(self, target, rectangles):
        self._target, self._rectangles = target, rectangles

    def __getattr__(self, name):
        return getattr(self._target, name)

    def dark_rectangles(self):
        return self._rectangles


def _srgb8(linear: np.ndarray) -> np.ndarray:
    from camio.files import linear_to_srgb

    return np.clip(np.round(linear_to_srgb(linear) * 255.0), 0, 255).astype(np.uint8)


def _write_rows(out, r0: int, rows_u8: np.ndarray) -> None:
    if not out.write_scanlines(r0, r0 + rows_u8.shape[0], 0, np.ascontiguousarray(rows_u8[..., None])):
        raise OSError(f"cannot write PNG ({out.geterror() or 'write failed'})")


def _scale_bar_rows(target, dpi, strip, bar_mm, caption, W, H, Hb) -> np.ndarray:
    """(H − Hb, W) uint8 rows below the board: white, the bar and its 10 mm ticks in pixels, the caption drawn
    by matplotlib 2 mm below the bar at 6 pt, as in the PDF (only the caption's box is drawn, so a wide page
    costs no more than a narrow one)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    x0, y0, _, _ = target.extent_mm
    px = 25.4 / dpi
    rows = np.full((H - Hb, W), 255, dtype=np.uint8)  # white; black is 0 in any encoding
    bx0, by0, L, t = _bar_geometry(target, strip, bar_mm)
    c = lambda x: int(round((x - x0) / px))  # noqa: E731
    r = lambda y: int(round((y - y0) / px)) - Hb  # noqa: E731
    rows[max(r(by0), 0):max(r(by0 + t), 0), c(bx0):c(bx0 + L)] = 0
    for k in range(int(L // 10) + 1):
        xk = bx0 + 10.0 * k
        rows[max(r(by0 - 1.5), 0):max(r(by0 + t), 0), c(xk) - 1:c(xk) + 1] = 0
    top, left = max(r(by0 + t + 2.0), 0), c(bx0)
    # The caption's box: 6 pt a character is wider than any glyph of the font at 6 pt; to the strip's bottom.
    box_w, box_h = min(W - left, int(math.ceil(len(caption) * 6 / 72 * dpi)) + 2), H - Hb - top
    if box_w > 0 and box_h > 0:
        fig = Figure(figsize=(box_w / dpi, box_h / dpi), dpi=dpi, facecolor="white")
        canvas = FigureCanvasAgg(fig)
        fig.text(0.0, 1.0, caption, fontsize=6, va="top", ha="left", color="black")
        canvas.draw()
        text = np.asarray(canvas.buffer_rgba())[:box_h, :box_w, 0]
        region = rows[top:top + text.shape[0], left:left + text.shape[1]]
        np.minimum(region, text[:region.shape[0], :region.shape[1]], out=region)
    return rows


def _save_atomic(fig, path: str, fmt: str, **kwargs) -> None:
    """`fig.savefig` through `camio.files.atomic_output`: nothing partial at `path` on an error or signal."""
    from camio.files import atomic_output

    with atomic_output(path) as tmp:
        with open(tmp, "wb") as f:
            fig.savefig(f, format=fmt, **kwargs)


def _write_pdf(target, path, strip, bar_mm, caption):
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle

    x0, y0, x1, y1 = target.extent_mm
    Wmm, Hmm = x1 - x0, y1 + strip - y0
    fig = Figure(figsize=(Wmm / 25.4, Hmm / 25.4))
    ax = fig.add_axes((0, 0, 1, 1))
    ax.set_xlim(x0, x1)
    ax.set_ylim(y1 + strip, y0)  # Y down, as on the print
    ax.set_axis_off()
    xe, ye = target.x_edges, target.y_edges
    dark = target.cell_colours()
    for j in range(target.n_rows):
        for i in range(target.n_cols):
            if dark[j, i]:
                ax.add_patch(Rectangle((xe[i], ye[j]), xe[i + 1] - xe[i], ye[j + 1] - ye[j], facecolor="black",
                                       edgecolor="none", linewidth=0, antialiased=False))
    for rx0, ry0, rx1, ry1 in target.dark_rectangles():
        ax.add_patch(Rectangle((rx0, ry0), rx1 - rx0, ry1 - ry0, facecolor="black", edgecolor="none", linewidth=0,
                               antialiased=False))
    bx0, by0, L, t = _bar_geometry(target, strip, bar_mm)
    ax.add_patch(Rectangle((bx0, by0), L, t, facecolor="black", edgecolor="none"))
    for k in range(int(L // 10) + 1):
        ax.plot([bx0 + 10.0 * k] * 2, [by0 - 1.5, by0 + t], color="black", linewidth=0.5)
    ax.text(bx0, by0 + t + 2.0, caption, fontsize=6, va="top", ha="left")
    _save_atomic(fig, path, "pdf")
