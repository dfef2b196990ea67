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

Designed targets: `tiltfit.target.design`; images of the board (textures, printables): `tiltfit.target.raster`
and `tiltfit.target.printable`.
"""
from __future__ import annotations

import functools
import json
import math
import os
from dataclasses import dataclass, field

import numpy as np

from camio.checks import describe, is_finite_number, is_number, read_json

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
        if not isinstance(v, list) or not all(is_number(e) for e in v):
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


def load_target(path: str) -> Target:
    """Read and validate a target file; raises TargetError with a one-line message naming file and field."""
    if not os.path.exists(path):
        raise TargetError(f"{path}: no such file")
    return target_from_dict(read_json(path, TargetError, "target file"), path)


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
