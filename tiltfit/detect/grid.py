"""Stage 3 of the checkerboard detector (`tiltfit.detect.chessboard`): growing a lattice of saddles.

A seed corner with neighbours along both edge directions, then predict-and-verify over the lattice (local affine
prediction from known neighbours, the strongest candidate near the prediction or a local saddle search); each
accepted corner must look like an X-junction. Nodes are integer lattice coordinates (a, b) with no ids yet.
"""
from __future__ import annotations

import math

import numpy as np

from tiltfit.detect.imaging import _bilinear
from tiltfit.detect.saddles import SaddleMap, _quadratic_peak


_DIRS = ((1, 0), (-1, 0), (0, 1), (0, -1))


# half-angle of the cone around each Hessian edge direction in which a seed looks for its neighbours: the
# zero directions of a blurred, foreshortened corner can be ~18° off the true edges (small squares seen
# at a grazing angle); a diagonal neighbour is further off and the X-junction test rejects a wrong pick
SEED_CONE_DEG = 30.0


class _Grid:
    """Lattice nodes (a, b) -> level positions, grown from a seed by predict-and-verify."""

    def __init__(self, sm: SaddleMap, noise: float):
        self.sm = sm
        self.noise = noise
        self.pos: dict[tuple[int, int], np.ndarray] = {}
        self.used: set[int] = set()
        self.failed: set[tuple[int, int]] = set()

    def local_affine(self, n, max_dist=2):
        """Affine map index -> position fitted on known nodes near n; None when they are collinear."""
        a, b = n
        rng = range(-max_dist, max_dist + 1)
        pts = [((a + i, b + j), self.pos[(a + i, b + j)]) for i in rng for j in rng if (a + i, b + j) in self.pos]
        if len(pts) < 3:
            return None
        idx = np.array([k for k, _ in pts], dtype=np.float64)
        P = np.array([p for _, p in pts])
        A = np.concatenate([idx - np.array([a, b]), np.ones((len(pts), 1))], 1)
        if np.linalg.matrix_rank(A[:, :2] - A[:, :2].mean(0)) < 2:
            return None
        w = 1.0 / (1.0 + np.abs(A[:, :2]).sum(1))
        coef, *_ = np.linalg.lstsq(A * w[:, None], P * w[:, None], rcond=None)
        return coef[:2].T, coef[2]  # (2, 2) [u v], predicted position of n

    def predict(self, n, d):
        """Predicted position of node n (reached from n − d), with the lattice vectors there."""
        aff = self.local_affine(n)
        if aff is not None:
            UV, p = aff
            return p, UV[:, 0], UV[:, 1]
        prev = (n[0] - d[0], n[1] - d[1])
        prev2 = (n[0] - 2 * d[0], n[1] - 2 * d[1])
        if prev in self.pos and prev2 in self.pos:
            step = self.pos[prev] - self.pos[prev2]
            if d[0]:
                u = step * d[0]
                v = np.array([-u[1], u[0]])
            else:
                v = step * d[1]
                u = np.array([v[1], -v[0]])
            return self.pos[prev] + step, u, v
        return None

    def x_test(self, p, u, v) -> bool:
        """An X-junction: the four cell centres around p alternate in colour."""
        q = _bilinear(self.sm.smooth, np.stack([p + 0.5 * (u + v), p - 0.5 * (u + v), p + 0.5 * (u - v),
                                                p - 0.5 * (u - v)]))
        m1, m2 = 0.5 * (q[0] + q[1]), 0.5 * (q[2] + q[3])
        contrast = abs(m1 - m2)
        asym = max(abs(q[0] - q[1]), abs(q[2] - q[3]))
        return contrast > 8 * self.noise and asym < 0.4 * contrast

    def find_near(self, p, radius):
        """The strongest unused candidate within radius of p, else a local saddle search in det H."""
        sm = self.sm
        d = np.hypot(sm.xy[:, 0] - p[0], sm.xy[:, 1] - p[1])
        near = np.nonzero(d <= radius)[0]
        near = near[[k not in self.used for k in near]] if near.size else near
        if near.size:
            k = near[np.argmax(sm.strength[near])]
            return sm.xy[k], int(k)
        # local search: the most negative det H within the radius, if clearly above noise
        h, w = sm.det.shape
        r = max(1, int(math.ceil(radius)))
        x0, y0 = int(round(p[0])), int(round(p[1]))
        xa, xb, ya, yb = max(1, x0 - r), min(w - 2, x0 + r), max(1, y0 - r), min(h - 2, y0 + r)
        if xa > xb or ya > yb:
            return None
        win = sm.det[ya:yb + 1, xa:xb + 1]
        j = int(np.argmin(win))
        yy, xx = divmod(j, win.shape[1])
        if win[yy, xx] > -0.25 * sm.threshold:
            return None
        xs, ys = np.array([xx + xa]), np.array([yy + ya])
        q = np.array([xx + xa, yy + ya], dtype=np.float64) + _quadratic_peak(sm.det, xs, ys)[0]
        if np.hypot(*(q - p)) > radius:
            return None
        return q, -1

    def grow(self, seed: dict):
        self.pos = dict(seed)
        queue = list(self.pos)
        h, w = self.sm.det.shape
        while queue:
            node = queue.pop(0)
            for d in _DIRS:
                n = (node[0] + d[0], node[1] + d[1])
                if n in self.pos or n in self.failed:
                    continue
                pr = self.predict(n, d)
                if pr is None:
                    continue
                p, u, v = pr
                spacing = min(np.hypot(*u), np.hypot(*v))
                if not (2 <= p[0] <= w - 3 and 2 <= p[1] <= h - 3) or spacing < 3:
                    self.failed.add(n)
                    continue
                hit = self.find_near(p, 0.3 * spacing)
                if hit is None or not self.x_test(hit[0], u, v):
                    self.failed.add(n)
                    continue
                self.pos[n] = hit[0]
                if hit[1] >= 0:
                    self.used.add(hit[1])
                queue.append(n)
        return self.pos


def _seed(sm: SaddleMap, k: int, noise: float):
    """Seed lattice (5 nodes) around candidate k, or None."""
    p = sm.xy[k]
    d = sm.xy - p
    dist = np.hypot(d[:, 0], d[:, 1])
    near = np.argsort(dist)[1:13]
    near = near[(dist[near] > 2.0) & (sm.strength[near] > 0.1 * sm.strength[k])]
    if near.size < 4:
        return None
    found = {}
    for e_i, e in enumerate(sm.edges[k]):
        for sgn in (1.0, -1.0):
            t = sgn * e
            cosang = (d[near] @ t) / dist[near]
            ok = near[cosang > math.cos(math.radians(SEED_CONE_DEG))]
            if ok.size == 0:
                return None
            found[(e_i, sgn)] = ok[np.argmin(dist[ok])]
    u1, u2 = sm.xy[found[(0, 1.0)]] - p, p - sm.xy[found[(0, -1.0)]]
    v1, v2 = sm.xy[found[(1, 1.0)]] - p, p - sm.xy[found[(1, -1.0)]]
    for a, b in ((u1, u2), (v1, v2)):
        r = np.hypot(*a) / max(np.hypot(*b), 1e-9)
        if not 0.6 < r < 1.67:
            return None
    u, v = 0.5 * (u1 + u2), 0.5 * (v1 + v2)
    if u[0] * v[1] - u[1] * v[0] < 0:  # make (u, v) right-handed in the image (x right, y down)
        found = {(0, 1.0): found[(1, 1.0)], (0, -1.0): found[(1, -1.0)], (1, 1.0): found[(0, 1.0)],
                 (1, -1.0): found[(0, -1.0)]}
        u, v = v, u
    seed = {(0, 0): p, (1, 0): sm.xy[found[(0, 1.0)]], (-1, 0): sm.xy[found[(0, -1.0)]],
            (0, 1): sm.xy[found[(1, 1.0)]], (0, -1): sm.xy[found[(1, -1.0)]]}
    used = {k} | set(int(found[key]) for key in found)
    if len(used) != 5:
        return None
    return seed, used, u, v


def find_grid(sm: SaddleMap, noise: float, max_seeds: int = 12) -> dict:
    """The largest lattice grown from the strongest seeds: {(a, b): level position}, (a, b) right-handed."""
    if sm.xy.shape[0] < 5:
        return {}
    order = np.argsort(-sm.strength)
    best: dict = {}
    tried = 0
    claimed: set[int] = set()
    for k in order[: 20 * max_seeds]:
        if tried >= max_seeds or k in claimed:
            continue
        s = _seed(sm, int(k), noise)
        if s is None:
            continue
        seed, used, u, v = s
        g = _Grid(sm, noise)
        if not all(g.x_test(p, u, v) for p in seed.values()):
            continue
        tried += 1
        g.used = set(used)
        pos = g.grow(seed)
        claimed |= g.used
        if len(pos) > len(best):
            best = pos
        if len(best) >= 0.5 * len(sm.xy) and len(best) >= 9:
            break
    return best


def _median_spacing(nodes: np.ndarray, xy: np.ndarray) -> float:
    lut = {tuple(n): p for n, p in zip(nodes.tolist(), xy)}
    d = [np.hypot(*(lut[(a + 1, b)] - p)) for (a, b), p in lut.items() if (a + 1, b) in lut]
    d += [np.hypot(*(lut[(a, b + 1)] - p)) for (a, b), p in lut.items() if (a, b + 1) in lut]
    return float(np.median(d)) if d else 0.0


def _min_neighbour_distance(nodes: np.ndarray, xy: np.ndarray) -> np.ndarray:
    lut = {tuple(n): p for n, p in zip(nodes.tolist(), xy)}
    out = np.full(len(nodes), np.inf)
    for k, (n, p) in enumerate(zip(nodes.tolist(), xy)):
        for d in _DIRS:
            q = lut.get((n[0] + d[0], n[1] + d[1]))
            if q is not None:
                out[k] = min(out[k], float(np.hypot(*(q - p))))
    fallback = np.median(out[np.isfinite(out)]) if np.isfinite(out).any() else 10.0
    return np.where(np.isfinite(out), out, fallback)
