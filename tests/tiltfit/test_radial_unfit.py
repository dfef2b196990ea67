"""Detection's radial unfit test on a large board: memory linear in the corners, and a different board still
refused."""
from __future__ import annotations

import tracemalloc

import numpy as np

from tiltfit.target.layout import Target, target_from_dict

def _grid_target(nx: int, ny: int) -> Target:
    return target_from_dict({"type": "checkerboard", "x_edges": [10.0 * i for i in range(nx + 2)],
                             "y_edges": [10.0 * j for j in range(ny + 2)]})


def _barrel(target: Target, k: float, size=(4000, 3000)) -> np.ndarray:
    """The target's corners seen face-on filling the image, bent by x_d = c + (x − c)(1 + k r²) (r over the
    half diagonal)."""
    XY = target.feature_points()[:, :2]
    c = np.asarray(size, dtype=np.float64) / 2
    uv = (XY - XY.mean(0)) / np.ptp(XY, 0).max() * 0.9 * size[0] + c
    d = (uv - c) / np.hypot(*c)
    return c + (uv - c) * (1 + k * (d * d).sum(1, keepdims=True))


def test_radial_unfit_keeps_memory_linear_in_the_corners():
    """`labelling_problem`'s radial test on a board of 2,500 corners bent by barrel distortion: its corner spacing
    came from an N × N distance matrix (25 of them, 100 MB each here; a 40,000-corner board asked for 25 GB). The
    bent right board is still accepted, and the peak memory stays that of a few arrays of N points."""
    from tiltfit.detect.chessboard import labelling_problem

    t = _grid_target(50, 50)
    uv = _barrel(t, -0.25)
    tracemalloc.start()
    try:
        problem = labelling_problem(uv, t, (4000, 3000))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert problem == "", f"a bent view of the right board is accepted: {problem!r}"
    assert peak < 20e6, f"peak memory {peak / 1e6:.0f} MB for {t.n_points} corners"


def test_radial_unfit_still_refuses_a_different_board():
    """A board whose columns are unequal (another target) seen through the same lens stays refused."""
    from tiltfit.detect.chessboard import CONTRADICTS, labelling_problem

    t = _grid_target(12, 9)
    xe = np.cumsum([0.0] + [10.0 if i % 2 else 25.0 for i in range(13)])  # another board: unequal columns
    other = target_from_dict({"type": "checkerboard", "x_edges": xe.tolist(), "y_edges": list(t.y_edges)})
    uv = _barrel(other, -0.1)
    problem = labelling_problem(uv, t, (4000, 3000))
    assert problem.startswith(CONTRADICTS), f"a different board is refused: {problem!r}"
    assert labelling_problem(_barrel(t, -0.1), t, (4000, 3000)) == "", "the right board through the same lens"
