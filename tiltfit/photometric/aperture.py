"""A checkerboard seen through a thin lens's aperture disc, in closed form (no lens samples).

Every ray from one sensor point leaves a point L of the aperture disc and passes through the point's focus
point q (`renderer.ThinLensCamera.focus_geometry`), so it meets the board plane Z = 0 at the central
projection of L from q. A central projection maps lines to lines: the board's cell edge X = e is, on the
aperture, the line

    L_z (q_x − e s) − q_z (L_x − e) = 0          (q = (q_x, q_y, q_z, s) homogeneous, L = C + a A₁ + b A₂)

which is affine in the disc coordinates (a, b). The dark part of the board is a sum of products of half-planes
X > e_j and Y > f_l, so the fraction of the (uniformly weighted) aperture whose rays land on dark cells is a
sum of two closed-form areas: a disc cut by one line (a circular segment) and a disc cut by two (a wedge).
It is exact for the thin lens, whatever its tilt and however large the blur (past the square too): no
fixed-sample disc, so no sample pattern to bias d or θL, and much cheaper than tracing hundreds of samples.

Dark fraction, for the checker's telescoping sums B_x = Σ_j k_j H(X > e_j) (the column's ±1 parity sign on
the board, 0 off it) and I_x = H(X > e_0) − H(X > e_n) (on the board's columns), likewise in Y:
    D = ½ (E[I_x I_y] + p E[B_x B_y]),   E[H_j H_l] = wedge_jl,  E[H_j] = F_j
with p the parity of the dark cell. E[H_j H_l] = F_j F_l exactly unless both lines cut the disc, so only the
`near` lines of each family nearest to the disc's centre get a wedge (all lines that cut it, as long as
`near` is at least the number of lines one disc can span).
"""
from __future__ import annotations

import math

import torch

from tiltfit.target.layout import Target


def _cross(ax, ay, bx, by):
    return ax * by - ay * bx


def disc_halfplane_fraction(h: torch.Tensor) -> torch.Tensor:
    """Fraction of the unit disc on the positive side of a line at signed distance h from its centre:
    area of {x : n·x + h > 0} / π for a unit normal n; 1 for h ≥ 1, 0 for h ≤ −1 (circular segment)."""
    inside = h.abs() < 1
    hs = torch.where(inside, h, torch.zeros_like(h))
    cut = (torch.acos(hs) - hs * torch.sqrt(1 - hs * hs)) / math.pi
    return torch.where(inside, 1 - cut, (h > 0).to(h.dtype))


def _circle_triangle_area(ax, ay, bx, by):
    """Signed area of the unit disc ∩ the triangle (0, A, B) (positive when A→B turns counter-clockwise)."""
    dx, dy = bx - ax, by - ay
    qa = dx * dx + dy * dy
    qb = ax * dx + ay * dy
    qc = ax * ax + ay * ay - 1
    disc = qb * qb - qa * qc
    meets = (disc > 0) & (qa > 0)
    root = torch.sqrt(torch.where(meets, disc, torch.ones_like(disc)))
    qa_safe = torch.where(qa > 0, qa, torch.ones_like(qa))
    zero = torch.zeros_like(disc)
    s1 = torch.where(meets, ((-qb - root) / qa_safe).clamp(0, 1), zero)
    s2 = torch.where(meets, ((-qb + root) / qa_safe).clamp(0, 1), zero)
    p1x, p1y = ax + s1 * dx, ay + s1 * dy
    p2x, p2y = ax + s2 * dx, ay + s2 * dy
    sector_a = _angle(_cross(ax, ay, p1x, p1y), ax * p1x + ay * p1y)
    chord = _cross(p1x, p1y, p2x, p2y)
    sector_b = _angle(_cross(p2x, p2y, bx, by), p2x * bx + p2y * by)
    return 0.5 * (sector_a + chord + sector_b)


def _angle(sin, cos):
    """atan2(sin, cos), 0 where both vanish (a point at the disc's centre: atan2(−0, −0) would be −π)."""
    zero = (sin == 0) & (cos == 0)
    return torch.where(zero, torch.zeros_like(sin), torch.atan2(sin, torch.where(zero, torch.ones_like(cos), cos)))


def disc_wedge_fraction(n1x, n1y, h1, n2x, n2y, h2) -> torch.Tensor:
    """Fraction of the unit disc where n₁·x + h₁ > 0 and n₂·x + h₂ > 0 (unit normals n₁, n₂; all (...,)).

    Exact. Where the lines cross inside the disc: the wedge between them, cut to a parallelogram that holds
    its part of the disc, integrated against the circle edge by edge (`_circle_triangle_area`). Where they
    do not (parallel lines included), each chord lies wholly on one side of the other line and the answer is
    F₁ + F₂ − 1, F₁, F₂ or 0 (the segment fractions F), by those sides.
    """
    sin = _cross(n1x, n1y, n2x, n2y)
    sign = torch.where(sin >= 0, torch.ones_like(sin), -torch.ones_like(sin))
    sin_safe = sign * sin.abs().clamp_min(1e-6)
    vx = (-h1 * n2y + h2 * n1y) / sin_safe            # the lines' crossing
    vy = (-h2 * n1x + h1 * n2x) / sin_safe
    crossing = (vx * vx + vy * vy < 1) & (sin.abs() > 1e-6)
    # Within the disc n₂·x + h₂ ≤ 1 + |h₂| and n₂·(V + a u₁ + b u₂) + h₂ = a |sin|: a ≤ (1 + |h₂|) / |sin|.
    reach = (1 + torch.maximum(h1.abs(), h2.abs())) / sin_safe.abs() + 1
    u1x, u1y = -n1y * sign, n1x * sign                 # along line 1, into n₂·x + h₂ > 0
    u2x, u2y = n2y * sign, -n2x * sign                 # along line 2, into n₁·x + h₁ > 0
    xs = (vx, vx + reach * u1x, vx + reach * (u1x + u2x), vx + reach * u2x)
    ys = (vy, vy + reach * u1y, vy + reach * (u1y + u2y), vy + reach * u2y)
    area = sum(_circle_triangle_area(xs[i], ys[i], xs[(i + 1) % 4], ys[(i + 1) % 4]) for i in range(4))
    # Chords that do not cross in the disc: is each chord's midpoint on the other line's positive side?
    F1, F2 = disc_halfplane_fraction(h1), disc_halfplane_fraction(h2)
    chord1_in_2 = (-h1 * (n1x * n2x + n1y * n2y) + h2) > 0
    chord2_in_1 = (-h2 * (n1x * n2x + n1y * n2y) + h1) > 0
    apart = torch.where(chord1_in_2, torch.where(chord2_in_1, F1 + F2 - 1, F1),
                        torch.where(chord2_in_1, F2, torch.zeros_like(F1)))
    return torch.where(crossing, area.abs() / math.pi, apart.clamp_min(0))


def _edge_lines(q_h, centre, axes, edges, k: int):
    """Lines on the aperture of the board edges X_k = e (k = 0) or Y = e (k = 1): unit normals (nx, ny) and
    signed distances h (..., n_edges), oriented so that n·(a, b) + h > 0 is the side X_k > e."""
    qk, qz, s = q_h[..., k, None], q_h[..., 2, None], q_h[..., 3, None]
    e = edges
    # g(a, b) = L_z (q_k − e s) − q_z (L_k − e), L = C + a A₁ + b A₂; X_k − e = g / (L_z s − q_z).
    m = qk - e * s
    # centre (3,) and axes (2, 3) are one lens's, or (..., 3) and (..., 2, 3) one per point (the fit's Jacobian
    # differentiates each point's dark fraction with respect to its own copy).
    cz, ck = centre[..., 2, None], centre[..., k, None]
    gamma = cz * m - qz * (ck - e)
    alpha = axes[..., 0, 2, None] * m - qz * axes[..., 0, k, None]
    beta = axes[..., 1, 2, None] * m - qz * axes[..., 1, k, None]
    side = torch.where(cz * s - qz >= 0, 1.0, -1.0).to(m.dtype)
    norm = torch.sqrt(alpha * alpha + beta * beta).clamp_min(torch.finfo(alpha.dtype).tiny)
    f = side / norm
    return alpha * f, beta * f, gamma * f


def _family_lines(q_h, centre, axes, edges, k: int):
    """`_edge_lines` without the normals' products: (alpha, beta, f, h) with the unit normal (alpha f, beta f) and
    h = gamma f, the same numbers in the same order. Shapes broadcast: (..., n_edges) for `_edge_lines`'s inputs, or
    one line each for inputs gathered per line (q_h (K, 4), centre (K, 3), axes (K, 2, 3), edges (K,): pass
    them with a trailing axis of one, as `_cut_lines` does)."""
    qk, qz, s = q_h[..., k, None], q_h[..., 2, None], q_h[..., 3, None]
    m = qk - edges * s
    cz, ck = centre[..., 2, None], centre[..., k, None]
    gamma = cz * m - qz * (ck - edges)
    alpha = axes[..., 0, 2, None] * m - qz * axes[..., 0, k, None]
    beta = axes[..., 1, 2, None] * m - qz * axes[..., 1, k, None]
    side = torch.where(cz * s - qz >= 0, 1.0, -1.0).to(m.dtype)
    norm = torch.sqrt(alpha * alpha + beta * beta).clamp_min(torch.finfo(alpha.dtype).tiny)
    f = side / norm
    return alpha, beta, f, gamma * f


def _pair_lines(h: torch.Tensor, near: int) -> torch.Tensor:
    """(P, n) bool: the lines given a two-line term, those of the `near` nearest the disc's centre that cut it."""
    cut = h.abs() < 1
    if near >= h.shape[-1]:
        return cut
    idx = torch.topk(h.abs(), near, dim=-1, largest=False).indices
    return torch.zeros_like(cut).scatter_(-1, idx, True) & cut


def _checker_coefficients(n: int, dtype, device):
    """The checker's coefficients over a family's n + 1 edges: of I (inside the board: 1, 0, …, 0, −1) and of B
    (the parity sign: 1, −2, 2, …, (−1)ⁿ)."""
    j = torch.arange(n + 1, device=device)
    parity = torch.where(j % 2 == 0, 1.0, -1.0).to(dtype)
    k_b = torch.where((j > 0) & (j < n), 2 * parity, parity)
    k_i = torch.zeros(n + 1, dtype=dtype, device=device)
    k_i[0], k_i[n] = 1.0, -1.0
    return k_i, k_b


class _CutLines:
    """One family's lines that cut a point's disc (|h| < 1), as a flat list: the only entries whose half-plane
    fraction F is not 0 or 1, so the only ones through which D has a derivative. Their lines are formed again
    from the points' inputs, with gradients; the dense pass over every point and line runs without them.

    Attributes: point, edge (K,) the entries; alpha, beta, scale, h (K,) their lines (`_family_lines`, its f as
    scale); F (K,) their circular segments; step (K,) what F is at the same entry once the line no longer cuts (0
    or 1); position (P · n_edges,) each dense entry's index in the list (−1 where the line does not cut)."""

    def __init__(self, q, c, a, h_dense, edges, k: int):
        P, n = h_dense.shape
        at = (h_dense.abs() < 1).reshape(-1).nonzero().squeeze(1)
        self.point, self.edge = at // n, at % n
        self.alpha, self.beta, self.scale, h = (t.squeeze(-1) for t in _family_lines(
            q.index_select(0, self.point), c.index_select(0, self.point), a.index_select(0, self.point),
            edges[self.edge][:, None], k))
        self.h = h
        hc = h.clamp(-1, 1)   # the dense pass said |h| < 1; the same numbers again, so the clamp only guards acos
        self.F = 1 - (torch.acos(hc) - hc * torch.sqrt(1 - hc * hc)) / math.pi
        self.step = (h_dense.reshape(-1)[at] > 0).to(q.dtype)
        self.position = torch.full((P * n,), -1, dtype=torch.long, device=q.device)
        self.position[at] = torch.arange(at.shape[0], device=q.device)
        self.n_points = P

    def sum_with(self, step_dense: torch.Tensor, coefficients: torch.Tensor) -> torch.Tensor:
        """(P,) Σ_j F_j c_j: the lines that do not cut (0 or 1, no derivative) in the dense sum, the cut ones'
        segments added from the list."""
        return (step_dense * coefficients).sum(-1).index_add(0, self.point, (self.F - self.step)
                                                             * coefficients[self.edge])


def checker_dark_fraction_disc(q_h: torch.Tensor, centre: torch.Tensor, axes: torch.Tensor, target: Target,
                               near: int = 2) -> torch.Tensor:
    """Fraction of the aperture whose rays through the focus points `q_h` land on the board's dark cells.

    Every line of each family is placed on the disc without gradients; the few that cut it (its segment, its
    pairs) are formed again with them (`_CutLines`), so the reverse pass runs over those only.

    Args:
        q_h: (..., 4) homogeneous focus points, target frame (board plane Z = 0), as
            `ThinLensCamera.focus_geometry` returns them; centre: (3,) lens centre; axes: (2, 3) the aperture's
            half-diameter vectors (or (..., 3) and (..., 2, 3), one copy per point, or broadcast to the points).
        target: the board (cell edges `x_edges`, `y_edges`, mm; `dark_cell`).
        near: lines of each family given an exact two-line term: at least the number one blur disc can cut
            (`lines_cut` counts them for given points); more costs nothing (only lines that cut the disc are
            integrated in pairs).
    Returns:
        (...,) in [0, 1]: the mean of the checker's darkness (1 dark cell, 0 white or margin) over the disc.
    """
    xe = torch.as_tensor(target.x_edges, dtype=q_h.dtype, device=q_h.device)
    ye = torch.as_tensor(target.y_edges, dtype=q_h.dtype, device=q_h.device)
    shape = q_h.shape[:-1]
    n_points = math.prod(shape)
    with torch.no_grad():
        hx = _family_lines(q_h, centre, axes, xe, 0)[3].reshape(n_points, -1)
        hy = _family_lines(q_h, centre, axes, ye, 1)[3].reshape(n_points, -1)
        step_x, step_y = (hx > 0).to(q_h.dtype), (hy > 0).to(q_h.dtype)
        both = _pair_lines(hx, near)[:, :, None] & _pair_lines(hy, near)[:, None, :]
    q = q_h.reshape(n_points, 4)
    c = centre.expand(*shape, 3).reshape(n_points, 3)
    a = axes.expand(*shape, 2, 3).reshape(n_points, 2, 3)
    lx, ly = _CutLines(q, c, a, hx, xe, 0), _CutLines(q, c, a, hy, ye, 1)
    kix, kbx = _checker_coefficients(xe.shape[0] - 1, q_h.dtype, q_h.device)
    kiy, kby = _checker_coefficients(ye.shape[0] - 1, q_h.dtype, q_h.device)
    # Wedges minus their product part, zero unless both lines cut the disc: computed for those pairs only (a few
    # of every point's lines x lines), gathered from the cut lines into one flat list of (point, i, j).
    nx_, ny_ = hx.shape[-1], hy.shape[-1]
    sel = both.reshape(-1).nonzero().squeeze(1)
    point, pair = sel // (nx_ * ny_), sel % (nx_ * ny_)
    ix, iy = pair // ny_, pair % ny_
    px, py = lx.position[point * nx_ + ix], ly.position[point * ny_ + iy]
    fx, fy = lx.scale[px], ly.scale[py]
    wedge = disc_wedge_fraction(lx.alpha[px] * fx, lx.beta[px] * fx, lx.h[px], ly.alpha[py] * fy, ly.beta[py] * fy,
                                ly.h[py])
    excess = wedge - lx.F[px] * ly.F[py]

    def expect(cx, cy):
        pairs = cx[ix] * cy[iy] * excess
        return (lx.sum_with(step_x, cx) * ly.sum_with(step_y, cy)).index_add(0, point, pairs).reshape(shape)

    parity = 1.0 if (target.dark_cell[0] + target.dark_cell[1]) % 2 == 0 else -1.0
    return 0.5 * (expect(kix, kiy) + parity * expect(kbx, kby))


def lines_cut(q_h: torch.Tensor, centre: torch.Tensor, axes: torch.Tensor, target: Target) -> int:
    """The most cell edges of one family that any of these points' aperture discs cuts (what `near` must
    cover for `checker_dark_fraction_disc` to be exact)."""
    with torch.no_grad():
        counts = []
        for k, edges in enumerate((target.x_edges, target.y_edges)):
            e = torch.as_tensor(edges, dtype=q_h.dtype, device=q_h.device)
            h = _edge_lines(q_h, centre, axes, e, k)[2]
            counts.append(int((h.abs() < 1).sum(-1).max()) if h.numel() else 0)
    return max(counts)


def disc_within(q_h: torch.Tensor, centre: torch.Tensor, axes: torch.Tensor, x_range, y_range) -> torch.Tensor:
    """(...,) True where every ray through the focus point `q_h` from the aperture disc meets the board plane
    inside the rectangle x_range × y_range (mm): each of its four sides is a line on the aperture, and the disc
    is inside where it lies wholly on the inner side of all four (signed distance at least its radius)."""
    out = None
    for k, (lo, hi) in enumerate((x_range, y_range)):
        e = torch.tensor([float(lo), float(hi)], dtype=q_h.dtype, device=q_h.device)
        h = _edge_lines(q_h, centre, axes, e, k)[2]
        inside = (h[..., 0] >= 1) & (h[..., 1] <= -1)
        out = inside if out is None else out & inside
    return out
