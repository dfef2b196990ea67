"""Stage 5 of the checkerboard detector (`tiltfit.detect.chessboard`): which target corner (i, j) each lattice node
is, scored by the colours each placement predicts (cells between, and one and two rings beyond, the corners), ties
broken by a homography fit, the board's 180° turn settled by image geometry.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from tiltfit.detect.imaging import _bilinear, apply_homography, homography_dlt, homography_dlt_batch
from tiltfit.target.layout import Target


def _rot(k: int, ab: np.ndarray) -> np.ndarray:
    """Rotate integer lattice coordinates by k quarter turns (orientation preserving)."""
    a, b = ab[..., 0], ab[..., 1]
    for _ in range(k % 4):
        a, b = -b, a
    return np.stack([a, b], -1)


@dataclass
class IndexResult:
    """Lattice nodes mapped to target corners: ij (n, 2) per node (in node order), or None; message."""

    ij: np.ndarray | None
    message: str
    scores: list = field(default_factory=list)


def _cell_probes(nodes: np.ndarray, xy: np.ndarray, shape) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Image positions of the cell centres near the lattice nodes, for reading the cells' colours.

    A cell (a, b) spans nodes a..a+1, b..b+1; it is probed when a node lies within its 4 × 4 neighbourhood
    (nodes a−1..a+2, b−1..b+2), at the centre (a + ½, b + ½) mapped by a homography fitted on the nodes within
    2.6 of it (an affine fit when fewer than 6; skipped when fewer than 4 or collinear, or outside the image).

    Args:
        nodes: (n, 2) integer lattice coordinates; xy: (n, 2) their positions, pixels; shape: (h, w) image.
    Returns:
        probe_xy (m, 2) positions, probe_ab (m, 2) cells, interior (m,) bool: all four corners are nodes.
    """
    h, w = shape
    amin, bmin = nodes.min(0)
    amax, bmax = nodes.max(0)
    # occupancy grid over the nodes' bounding box with a margin of 4, indexed [a − amin + 4, b − bmin + 4]
    occ = np.zeros((amax - amin + 9, bmax - bmin + 9), bool)
    occ[nodes[:, 0] - amin + 4, nodes[:, 1] - bmin + 4] = True
    index = np.full(occ.shape, -1)
    index[nodes[:, 0] - amin + 4, nodes[:, 1] - bmin + 4] = np.arange(len(nodes))
    A, Bc = np.meshgrid(np.arange(amin - 2, amax + 2), np.arange(bmin - 2, bmax + 2), indexing="ij")
    A, Bc = A.ravel(), Bc.ravel()
    ia, ib = A - amin + 4, Bc - bmin + 4
    near = np.zeros(A.shape, bool)
    for da in range(-1, 3):
        for db in range(-1, 3):
            near |= occ[ia + da, ib + db]
    known = occ[ia, ib].astype(int) + occ[ia + 1, ib] + occ[ia, ib + 1] + occ[ia + 1, ib + 1]
    A, Bc, ia, ib, known = A[near], Bc[near], ia[near], ib[near], known[near]
    # the nodes within 2.6 of a centre (a + ½, b + ½) are those of indices a−2..a+3, b−2..b+3
    off = np.arange(-2, 4)
    oa, ob = np.meshgrid(off, off, indexing="ij")
    nb_idx = index[ia[:, None] + oa.ravel()[None], ib[:, None] + ob.ravel()[None]]  # (m, 36), −1: no node
    valid = nb_idx >= 0
    count = valid.sum(1)
    src = np.stack([A[:, None] + oa.ravel()[None], Bc[:, None] + ob.ravel()[None]], -1).astype(np.float64)
    dst = np.where(valid[..., None], xy[np.maximum(nb_idx, 0)], 0.0)
    centre = np.stack([A + 0.5, Bc + 0.5], -1)
    Hs = homography_dlt_batch(src, dst, valid & (count >= 6)[:, None])
    c = np.full((len(A), 2), np.nan)
    use_h = (count >= 6) & np.isfinite(Hs).all((1, 2))
    if use_h.any():
        q = np.einsum("mij,mj->mi", Hs[use_h], np.c_[centre[use_h], np.ones(use_h.sum())])
        c[use_h] = q[:, :2] / q[:, 2:]
    # affine fit (weighted least squares with 0/1 weights) where the homography is not used
    wv = valid.astype(np.float64)[..., None]
    D = np.concatenate([src - centre[:, None], np.ones(src.shape[:2] + (1,))], -1) * wv  # (m, 36, 3)
    G = D.transpose(0, 2, 1) @ D
    full_rank = (count >= 4) & (np.linalg.matrix_rank(G[:, :2, :2]) >= 2)
    aff = ~use_h & full_rank
    if aff.any():
        coef = np.linalg.solve(G[aff], D[aff].transpose(0, 2, 1) @ (dst[aff] * wv[aff]))
        c[aff] = coef[:, 2]
    # where a homography was possible but failed, the original falls back to the affine fit too
    ok = np.isfinite(c).all(1) & full_rank
    ok &= (c[:, 0] >= 1) & (c[:, 0] <= w - 2) & (c[:, 1] >= 1) & (c[:, 1] <= h - 2)
    return c[ok], np.stack([A, Bc], -1)[ok], (known == 4)[ok]


def resolve_indices(nodes: np.ndarray, xy_level: np.ndarray, xy_full: np.ndarray, smooth: np.ndarray,
                    target: Target) -> IndexResult:
    """Map lattice nodes (a, b) to target corners (i, j) from the colours around them (see module docs).

    Args:
        nodes: (n, 2) integer lattice coordinates (right-handed in the image).
        xy_level: (n, 2) positions at the level of `smooth` (colour probes); xy_full: (n, 2) refined
            positions at full resolution (homography tie-break).
        smooth: the smoothed level image.
    """
    ny, nx = target.grid_shape
    # Probes: cell centres (half-integer lattice points) inside and up to two rings around the nodes, each
    # placed by a homography (an affine fit with fewer than 6) of the nodes within 2.6 of it.
    probe_xy, probe_ab, interior = _cell_probes(nodes, xy_level, smooth.shape)
    if not len(probe_xy):
        return IndexResult(None, "no cells to read colours from")
    val = _bilinear(smooth, probe_xy)
    ref = val[interior] if interior.sum() >= 2 else val
    lo, hi = np.percentile(ref, 10), np.percentile(ref, 90)
    if hi - lo <= 0:
        return IndexResult(None, "no contrast between cells")
    observed_dark = val < 0.5 * (lo + hi)

    hyps = []
    match = np.where(observed_dark, 1, -1)  # +1 where a probe is dark: score = Σ match · (±1 expected)
    for k in range(4):
        r = _rot(k, nodes)
        rmin, rmax = r.min(0), r.max(0)
        oi = np.arange(-rmin[0], nx - rmax[0])
        oj = np.arange(-rmin[1], ny - rmax[1])
        if oi.size == 0 or oj.size == 0:
            continue
        # cell (a, b) spans nodes a..a+1: its centre (a + 0.5, b + 0.5) maps to corner-index space; corner
        # index i sits at x_edges[i + 1], so the cell column is the mapped centre + 0.5. All placements
        # (offsets oi × oj) are scored at once: (n_oi, n_oj, n_probes).
        cc = _rot(k, probe_ab * 2 + 1) / 2.0
        col = np.round(cc[:, 0] + 0.5).astype(int)[None, None, :] + oi[:, None, None]
        row = np.round(cc[:, 1] + 0.5).astype(int)[None, None, :] + oj[None, :, None]
        score = np.where(target.is_dark(col, row), 1, -1) @ match
        for a in range(oi.size):
            for b in range(oj.size):
                hyps.append((int(score[a, b]), k, np.array([oi[a], oj[b]])))
    if not hyps:
        return IndexResult(None, f"the lattice ({len(nodes)} corners) does not fit on the "
                                 f"{nx}×{ny}-corner target in any orientation")
    best = max(s for s, _, _ in hyps)
    top = [(k, off) for s, k, off in hyps if s == best]
    scores = sorted([s for s, _, _ in hyps], reverse=True)
    note = ""
    if len(top) > MAX_TIED_PLACEMENTS:
        return IndexResult(None, f"{len(top)} placements of the corners on the target explain the image equally "
                                 f"well: show more of the board (its border)", scores)
    if len(top) > 1:
        # tie-break by the homography fit of the target coordinates (non-uniform rows)
        pts = target.feature_points()[:, :2]
        rss = []
        for k, off in top:
            ij = _rot(k, nodes) + off
            Hm = homography_dlt(pts[target.feature_index(ij[:, 0], ij[:, 1])], xy_full)
            res = np.inf if Hm is None else float(((apply_homography(Hm, pts[target.feature_index(ij[:, 0], ij[:, 1])])
                                                    - xy_full) ** 2).sum())
            rss.append(res)
        order = np.argsort(rss)
        if rss[order[1]] > 2.0 * rss[order[0]] + 1e-6 * len(nodes):
            top = [top[order[0]]]
        else:
            close = [top[o] for o in order if rss[o] <= 2.0 * rss[order[0]] + 1e-6 * len(nodes)]
            twin = _half_turn_pair(close, nodes, xy_full, target)
            if twin is None:
                why = "show more of the board (its border, or more rows of a non-uniform target)"
                return IndexResult(None, f"{len(top)} placements of the corners on the target explain the image "
                                         f"equally well: {why}", scores)
            top = [twin]
            note = HALF_TURN_NOTE
    k, off = top[0]
    return IndexResult(_rot(k, nodes) + off, note, scores)


# more equally good placements than this are not told apart by the homography fit either (a small patch of
# a large uniform board); bounds the work
MAX_TIED_PLACEMENTS = 64


HALF_TURN_NOTE = ("the target looks the same turned by 180°: labelled so that corner 0 is the one nearer the "
                  "image's top-left; either labelling is a valid pose")


def _half_turn_pair(hyps: list, nodes: np.ndarray, xy: np.ndarray, target: Target):
    """The labelling to use when the only ambiguity left is the board's 180° turn, else None.

    `hyps` are the (quarter turns, offset) placements that explain the image equally well. When they are
    exactly two, related by the half turn (i, j) -> (nx − 1 − i, ny − 1 − j), the image cannot tell them
    apart (a board with n_cols + n_rows even and symmetric edges, or nearly so). One is chosen by image
    geometry, so that every view of the board is labelled alike: the one whose diagonal from corner 0 to
    corner N − 1 points to the image's lower right, measured by an affine fit of the image positions to
    the corner indices (sign of (A · (nx − 1, ny − 1)) · (1, 1); the x component breaks an exact tie).
    """
    if len(hyps) != 2:
        return None
    ny, nx = target.grid_shape
    (k0, off0), (k1, off1) = hyps
    ij0, ij1 = _rot(k0, nodes) + off0, _rot(k1, nodes) + off1
    if not np.array_equal(ij1, np.array([nx - 1, ny - 1]) - ij0):
        return None
    return hyps[0] if _diagonal_points_down_right(ij0, xy, nx, ny) else hyps[1]


def _diagonal_points_down_right(ij: np.ndarray, xy: np.ndarray, nx: int, ny: int) -> bool:
    """Whether corner (nx−1, ny−1) lies to the lower right of corner (0, 0) in the image.

    Args:
        ij: (n, 2) corner indices of the seen corners; xy: (n, 2) their image positions, pixels.
    The diagonal's image direction d = A · (nx − 1, ny − 1) comes from a least-squares affine fit
    xy ≈ A ij + c (enough for its sign under perspective and lens distortion); the answer is
    d_x + d_y > 0 (d_x > 0 breaks an exact tie).
    """
    A = np.c_[ij.astype(np.float64), np.ones(len(ij))]
    coef, *_ = np.linalg.lstsq(A, xy.astype(np.float64), rcond=None)
    d = coef[:2].T @ np.array([nx - 1.0, ny - 1.0])
    s = d[0] + d[1]
    return bool(s > 0 or (s == 0 and d[0] > 0))
