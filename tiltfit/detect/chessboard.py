"""Find the target's feature points in an image: saddle candidates, grid growth, indexing, sub-pixel refinement.

Pipeline (`detect`):
1. Grey linear image, and a pyramid of 2×2 box averages (level factor f: pixel x_f ↔ full-resolution
   (x_f + 0.5) f − 0.5).
2. At a coarse level (coarsest first, finer on failure): saddle candidates, the local minima of the Hessian
   determinant det H = Ixx Iyy − Ixy² of the Gaussian-smoothed image (kornia), below a threshold set from the
   measured noise, where the saddle is well formed (−det H / (½(Ixx² + Iyy²) + Ixy²) > 0.3) and the
   gradient is small (a saddle's centre is flat, a point on an edge is not). A checker corner stays a
   saddle under any symmetric blur, even when the blur is as wide as the square and the pattern is nearly
   a sinusoid, so this works where edge-based detectors give up. The two zero directions of the quadratic
   form vᵀHv are the edges through the corner.
3. Grid growth: a seed corner with neighbours along both edge directions, then predict-and-verify over the
   lattice (local affine prediction from known neighbours, the strongest candidate near the prediction or
   a local saddle search). Each accepted corner must look like an X-junction: the four cell centres around
   it alternate (diagonal pairs equal, pairs different), which rejects the board's outer L-corners.
4. Sub-pixel refinement at full resolution: a checker corner under any point-symmetric blur (disc, pixel
   box, Gaussian) is a centre of point symmetry, I(p + v) = I(p − v). Levenberg–Marquardt on p minimises
   Σ_v w(v) [I(p + v) − I(p − v)]² over a window of 0.4 of the local square (at most 20 px), on patches
   smoothed by a 1.4 px Gaussian (symmetric, so the optimum stays put; it damps aliasing of sharp edges)
   and interpolated with Keys' cubic, all corners batched. No edge or blur model, so no bias from the blur
   size, its shape or the contrast; measured bias < 0.015 px for blur ≥ 1 px, < 0.035 px for sharp edges.
5. Indexing: which target corner (i, j) each lattice node is. A checkerboard is ambiguous under 90°
   turns, 180° turns and shifts; each hypothesis (4 turns × shifts that keep the nodes on the board) is
   scored by the colours it predicts: the cells between detected corners (the parity of the dark cell),
   one ring of cells beyond them (board cells) and a second ring (board or white margin). A tie is broken
   by the fit of a homography from the target coordinates (non-uniform rows tell the turns apart). A tie
   left between exactly the two placements related by the board's 180° turn (n_cols + n_rows even,
   symmetric edges: the image cannot tell them apart, and either is a valid pose) is settled by image
   geometry, consistently across views: corner 0 is the one nearer the image's top-left (the labelling
   OpenCV's findChessboardCorners gives); the detection's message says so. Any other tie (a partial view
   that fits several places on the board) is reported (grid_found False) rather than guessed.
6. Completion: corners the growth missed, predicted by a local homography from the indexed ones within two
   indices (local, so curved rows under lens distortion are followed), refined coarse to fine and kept when
   they are clean X-junctions (`complete_corners`).
7. Blur per feature point (`tiltfit.detect.blur.measure_blur`).

Images are (H, W) or (H, W, C) linear float arrays (decode sRGB first: `camio.files.read_image` does).
Outputs are numpy float64 in pixels: x = column, y = row, (0, 0) the centre of the top-left pixel.
"""
from __future__ import annotations

import json
import math
import os
import tempfile
import time
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F

from tiltfit.detect.blur import measure_blur as _measure_blur
from tiltfit.files.det import MAX_IMAGE_PIXELS  # the largest photo detection reads (named there: no torch)
from tiltfit.detect.imaging import apply_homography, build_pyramid, homography_dlt, homography_dlt_batch, to_full, torch_threads
from tiltfit.solve.batched import BatchedOptions, batched_levenberg_marquardt, normal_from_residuals
from tiltfit.target.layout import MAX_FEATURE_POINTS, Target


class DetectionError(ValueError):
    """No usable board in an image; one-line message."""


@dataclass
class Detection:
    """Feature points found in one image, in the target's feature-point order.

    Attributes:
        image_size_px: (width, height).
        corners_px: (N, 2) float64 pixel positions, NaN where the point was not found.
        blur_px: (N,) blur-disc diameters, pixels, NaN where not measured.
        blur_sigma_px: (N,) one-standard-deviation uncertainty of blur_px, NaN where not measured.
        grid_found: True when a board was found and its corners indexed (a board that looks the same
            turned by 180° is labelled by image geometry, noted in `message`).
        message: why not, or notes.
        level: pyramid factor at which the grid was found.
        timings_s: seconds per stage.
    """

    image_size_px: tuple[int, int]
    corners_px: np.ndarray
    blur_px: np.ndarray
    blur_sigma_px: np.ndarray
    grid_found: bool
    message: str = ""
    level: int = 0
    timings_s: dict = field(default_factory=dict)

    @property
    def found(self) -> np.ndarray:
        """(N,) bool, the feature points that were found."""
        return np.isfinite(self.corners_px).all(-1)

    def to_json_dict(self) -> dict:
        """The `tiltfit detect` output: {image_size_px, corners_px, blur_px, grid_found} (+ extra keys)."""

        def num(v):
            return None if not np.isfinite(v) else float(round(float(v), 4))

        return {
            "image_size_px": [int(self.image_size_px[0]), int(self.image_size_px[1])],
            "corners_px": [None if not np.isfinite(c).all() else [num(c[0]), num(c[1])] for c in self.corners_px],
            "blur_px": [num(b) for b in self.blur_px],
            "grid_found": bool(self.grid_found),
            "blur_sigma_px": [num(b) for b in self.blur_sigma_px],
            "n_found": int(self.found.sum()),
            "message": self.message,
        }


def write_detection_json(detection: Detection, path: str) -> None:
    """Write the detection as JSON; written to a temporary file and renamed (no partial file on failure)."""
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=".json", dir=folder)
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(detection.to_json_dict(), f, indent=1)
            f.write("\n")
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def read_detection_json(path: str, n_points: int | None = None) -> Detection:
    """Read a `tiltfit detect` JSON back into a Detection."""
    with open(path) as f:
        d = json.load(f)
    corners = np.array([[np.nan, np.nan] if c is None else c for c in d["corners_px"]], dtype=np.float64)
    blur = np.array([np.nan if b is None else b for b in d["blur_px"]], dtype=np.float64)
    sig = np.array([np.nan if b is None else b for b in d.get("blur_sigma_px", [None] * len(blur))], np.float64)
    if n_points is not None and len(corners) != n_points:
        raise DetectionError(f"{path}: corners_px: expected {n_points} entries, got {len(corners)}")
    return Detection(tuple(d["image_size_px"]), corners, blur, sig, bool(d["grid_found"]), d.get("message", ""))


# --- image helpers -----------------------------------------------------------------------------------------
def to_gray(image) -> np.ndarray:
    """(H, W) float32 grey image from a (H, W) or (H, W, C) linear image (mean of the colour channels)."""
    img = np.asarray(image.detach().cpu() if hasattr(image, "detach") else image)
    if img.ndim == 3:
        img = ((img[..., 0] + img[..., 1] + img[..., 2]) * np.float32(1 / 3)) if img.shape[-1] >= 3 else img[..., 0]
    if img.ndim != 2:
        raise DetectionError(f"image: expected (H, W) or (H, W, C), got shape {img.shape}")
    return np.ascontiguousarray(img, dtype=np.float32)


def estimate_noise(img: np.ndarray) -> float:
    """Robust standard deviation of the pixel noise, from second differences (blind to smooth gradients).

    MAD of I[x−1] − 2 I[x] + I[x+1] along rows and columns (variance 6σ² for white noise); floored at 1e-4
    of the image's range, so noise-free synthetic images keep a finite threshold.
    """
    sub = img[::2, ::2] if img.size > 4_000_000 else img
    d = np.concatenate([(sub[:, :-2] - 2 * sub[:, 1:-1] + sub[:, 2:])[::2, ::2].ravel(),
                        (sub[:-2] - 2 * sub[1:-1] + sub[2:])[::2, ::2].ravel()])
    mad = float(1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(6.0))
    lo, hi = np.percentile(sub[::4, ::4], [1, 99])
    return max(mad, 1e-4 * float(hi - lo), 1e-6)


def _bilinear(img: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Bilinear samples of a 2-D image at (..., 2) positions (x, y), clamped to the image."""
    h, w = img.shape
    x = np.clip(xy[..., 0], 0, w - 1.001)
    y = np.clip(xy[..., 1], 0, h - 1.001)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    return ((1 - fy) * ((1 - fx) * img[y0, x0] + fx * img[y0, x0 + 1])
            + fy * ((1 - fx) * img[y0 + 1, x0] + fx * img[y0 + 1, x0 + 1]))


# --- stage 2: saddle candidates ----------------------------------------------------------------------------
@dataclass
class SaddleMap:
    """Hessian fields of the smoothed level image and its candidates.

    Attributes:
        smooth: (H, W) smoothed image; dxx, dxy, dyy: (H, W) second derivatives; det: (H, W) det H.
        xy: (M, 2) candidate positions (level pixels), strength: (M,) −det H, edges: (M, 2, 2) unit
            vectors along the two edges through each candidate.
        threshold: −det H above which a local minimum is a candidate.
    """

    smooth: np.ndarray
    dxx: np.ndarray
    dxy: np.ndarray
    dyy: np.ndarray
    det: np.ndarray
    xy: np.ndarray
    strength: np.ndarray
    edges: np.ndarray
    threshold: float


_NOISE_GAIN: dict[float, float] = {}


def _hessian(img_t: torch.Tensor, sigma: float):
    k = 2 * int(math.ceil(3 * sigma)) + 1
    import kornia

    sm = kornia.filters.gaussian_blur2d(img_t, (k, k), (sigma, sigma), border_type="replicate")
    g = kornia.filters.spatial_gradient(sm, mode="diff", order=2, normalized=False)  # (B, C, 3, H, W)
    return sm, g[:, 0, 0], g[:, 0, 1], g[:, 0, 2]


def _det_noise_gain(sigma: float) -> float:
    """Standard deviation of Ixy for unit white noise after smoothing with `sigma` (measured once)."""
    if sigma not in _NOISE_GAIN:
        gen = torch.Generator().manual_seed(1)
        n = torch.randn(1, 1, 96, 96, generator=gen, dtype=torch.float32)
        _, dxx, dxy, dyy = _hessian(n, sigma)
        c = slice(16, -16)
        _NOISE_GAIN[sigma] = float(torch.stack([dxx[0, c, c].std(), 2 * dxy[0, c, c].std(), dyy[0, c, c].std()]).max())
    return _NOISE_GAIN[sigma]


def saddle_map(img: np.ndarray, sigma: float = 1.0, noise: float | None = None, k_noise: float = 6.0,
               min_quality: float = 0.3, max_candidates: int = 4000) -> SaddleMap:
    """Saddle candidates of a level image: local minima of det H (5×5) with −det H > (k σ_H)²."""
    t = torch.from_numpy(np.ascontiguousarray(img))[None, None]
    sm, dxx, dxy, dyy = _hessian(t, sigma)
    det = dxx * dyy - dxy * dxy
    noise = estimate_noise(img) if noise is None else noise
    sd_h = max(noise, 1e-4) * _det_noise_gain(sigma)
    neg = -det
    # noise-based, and at least 1e-3 of the strongest saddle (blur varies across a tilted-lens image, but a
    # corner's response falls as (blur)^-4 only down to the smoothing scale)
    thr = max((k_noise * sd_h) ** 2, 1e-3 * float(neg.max()))
    pooled = F.max_pool2d(neg[None], 5, stride=1, padding=2)[0]
    # saddle quality: −det / (½(Ixx² + Iyy²) + Ixy²) is 1 where the edges cross at right angles, about 0.5 for
    # edges at 45°, and near 0 or below on straight edges, in blobs and on noise riding on either
    quality = neg / (0.5 * (dxx * dxx + dyy * dyy) + dxy * dxy + 1e-30)
    # a saddle's centre is flat: |∇I| ≤ |H| δ within δ ≈ 1 px of it, while a point on an edge is steep
    import kornia

    grad = kornia.filters.spatial_gradient(sm, mode="diff", order=1, normalized=False)[:, 0]
    flat = torch.sqrt(grad[:, 0] ** 2 + grad[:, 1] ** 2) < 1.5 * torch.sqrt(neg.clamp_min(0))
    is_min = (neg == pooled) & (neg > thr) & (quality > min_quality) & flat
    # ignore the outermost pixels, where the smoothing saw the replicated border
    b = int(math.ceil(2 * sigma)) + 1
    is_min[:, :b] = False
    is_min[:, -b:] = False
    is_min[:, :, :b] = False
    is_min[:, :, -b:] = False
    ys, xs = torch.nonzero(is_min[0], as_tuple=True)
    s = neg[0, ys, xs]
    if s.numel() > max_candidates:
        keep = torch.topk(s, max_candidates).indices
        ys, xs, s = ys[keep], xs[keep], s[keep]
    dxx_n, dxy_n, dyy_n, det_n = (a[0].numpy() for a in (dxx, dxy, dyy, det))
    xy = np.stack([xs.numpy(), ys.numpy()], -1).astype(np.float64)
    xy = xy + _quadratic_peak(det_n, xs.numpy(), ys.numpy())
    edges = edge_directions(dxx_n[ys, xs], dxy_n[ys, xs], dyy_n[ys, xs])
    return SaddleMap(sm[0, 0].numpy(), dxx_n, dxy_n, dyy_n, det_n, xy, s.numpy().astype(np.float64), edges, thr)


def _quadratic_peak(f: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Sub-pixel offset (M, 2) of an extremum from a separable 3-point parabola fit, clipped to ±0.5."""
    h, w = f.shape
    xs, ys = np.clip(xs, 1, w - 2), np.clip(ys, 1, h - 2)
    c = f[ys, xs]
    dx = f[ys, xs + 1] - f[ys, xs - 1]
    dy = f[ys + 1, xs] - f[ys - 1, xs]
    cxx = f[ys, xs + 1] + f[ys, xs - 1] - 2 * c
    cyy = f[ys + 1, xs] + f[ys - 1, xs] - 2 * c
    ox = np.where(np.abs(cxx) > 1e-20, -0.5 * dx / np.where(np.abs(cxx) > 1e-20, cxx, 1.0), 0.0)
    oy = np.where(np.abs(cyy) > 1e-20, -0.5 * dy / np.where(np.abs(cyy) > 1e-20, cyy, 1.0), 0.0)
    return np.clip(np.stack([ox, oy], -1), -0.5, 0.5)


def edge_directions(hxx, hxy, hyy) -> np.ndarray:
    """(M, 2, 2): the two unit directions v with vᵀ H v = 0 (the edges through a saddle)."""
    # eigenvector of the negative eigenvalue at angle a; edges at a ± atan(sqrt(−λ1/λ2))
    tr, det = hxx + hyy, hxx * hyy - hxy * hxy
    disc = np.sqrt(np.maximum(0.25 * tr * tr - det, 0.0))
    l1, l2 = 0.5 * tr - disc, 0.5 * tr + disc
    a = 0.5 * np.arctan2(2 * hxy, hxx - hyy)  # angle of the eigenvector of the larger eigenvalue
    a_neg = a + 0.5 * np.pi
    half = np.arctan(np.sqrt(np.clip(-l1, 0, None) / np.maximum(l2, 1e-30)))
    th1, th2 = a_neg + half, a_neg - half
    return np.stack([np.stack([np.cos(th1), np.sin(th1)], -1), np.stack([np.cos(th2), np.sin(th2)], -1)], -2)


# --- stage 3: grid growth ----------------------------------------------------------------------------------
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


# --- stage 4: sub-pixel refinement -------------------------------------------------------------------------
def _keys(x: torch.Tensor) -> torch.Tensor:
    """Keys' cubic convolution kernel with a = −1/2 (reproduces quadratics: third-order accurate)."""
    ax = x.abs()
    return torch.where(ax <= 1, (1.5 * ax - 2.5) * ax * ax + 1,
                       torch.where(ax < 2, ((-0.5 * ax + 2.5) * ax - 4) * ax + 2, torch.zeros_like(ax)))


def _dkeys(x: torch.Tensor) -> torch.Tensor:
    ax = x.abs()
    return torch.sign(x) * torch.where(ax <= 1, (4.5 * ax - 5) * ax,
                                       torch.where(ax < 2, (-1.5 * ax + 5) * ax - 4, torch.zeros_like(ax)))


def _shift_patches(patches: torch.Tensor, frac: torch.Tensor):
    """Cubic interpolant of (N, S, S) patches at every pixel + frac (N, 2), and its x and y derivatives.

    Every sample p ± v (v integer) of one corner has the same fractional part, so interpolation is one
    separable 4-tap filter per corner. Entry [n, y, x] of the outputs holds the value at (x + 1 + fx,
    y + 1 + fy) in patch coordinates, for x, y in [0, S − 4].
    """
    ks = torch.arange(-1, 3, dtype=patches.dtype)
    wx, wy = _keys(frac[:, 0:1] - ks), _keys(frac[:, 1:2] - ks)  # (N, 4): weight of tap at offset k
    dwx, dwy = _dkeys(frac[:, 0:1] - ks), _dkeys(frac[:, 1:2] - ks)
    S = patches.shape[-1]

    def along_x(img, w):
        return sum(w[:, k, None, None] * img[:, :, k:k + S - 3] for k in range(4))

    def along_y(img, w):
        return sum(w[:, k, None, None] * img[:, k:k + S - 3, :] for k in range(4))

    tx, tdx = along_x(patches, wx), along_x(patches, dwx)
    return along_y(tx, wy), along_y(tdx, wy), along_y(tx, dwy)


def refine_symmetric(gray: np.ndarray, xy: np.ndarray, radius: np.ndarray, iterations: int = 20,
                     presmooth: float = 1.4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Point-symmetry refinement of corners at full resolution.

    Minimises Σ_v w(v) [I(p + v) − I(p − v)]² over p (`tiltfit.solve.batched_levenberg_marquardt`, all
    corners at once), v over a half-disc of `radius` (integer offsets, weights (1 − |v|²/R²)²). I is the patch smoothed by a Gaussian of `presmooth` px
    (symmetric, so the optimum is unchanged; it damps the aliasing of sharp edges) and interpolated with
    Keys' cubic (a = −1/2), whose exact derivative gives the Jacobian. On synthetic disc-blurred corners
    the bias is under 0.015 px for blur ≥ 1 px and under 0.035 px for perfectly sharp edges.

    Args:
        gray: (H, W) linear image.
        xy: (N, 2) initial positions, pixels.
        radius: (N,) window radii, pixels (clipped so the window stays inside the image; < 2 fails).
    Returns:
        xy (N, 2), asymmetry (N,) = weighted RMS of I(p+v) − I(p−v) over that of I − mean (0 for a perfect
        X-junction), ok (N,) bool.
    """
    H, W = gray.shape
    N = xy.shape[0]
    if N == 0:
        return xy.copy(), np.zeros(0), np.zeros(0, bool)
    xy = xy.astype(np.float64).copy()
    ks = int(math.ceil(3 * presmooth)) if presmooth > 0 else 0
    border = np.minimum.reduce([xy[:, 0], W - 1 - xy[:, 0], xy[:, 1], H - 1 - xy[:, 1]]) - 4.0 - ks
    R = np.minimum(radius, border)
    ok = R >= 2.0
    R = np.maximum(R, 2.0)
    Rmax = int(math.ceil(R.max()))
    P = Rmax + 4 + ks  # patch half-size: window + room to move + cubic support + smoothing support
    S = 2 * P + 1
    oy, ox = np.mgrid[0:Rmax + 1, -Rmax:Rmax + 1]
    half = (oy > 0) | ((oy == 0) & (ox > 0))
    off = np.stack([ox[half], oy[half]], -1).astype(np.float64)  # (M, 2) half-disc offsets
    rr = np.hypot(off[:, 0], off[:, 1])
    c0 = np.round(xy).astype(int)
    c0[:, 0] = np.clip(c0[:, 0], 0, W - 1)
    c0[:, 1] = np.clip(c0[:, 1], 0, H - 1)
    ys = np.clip(c0[:, 1, None] + np.arange(-P, P + 1)[None], 0, H - 1)
    xs = np.clip(c0[:, 0, None] + np.arange(-P, P + 1)[None], 0, W - 1)
    # float32: the patches, weights and normal equations (errors ~1e-5 px); the positions accumulate in float64
    t = torch.from_numpy(gray[ys[:, :, None], xs[:, None, :]].astype(np.float32))[:, None]  # (N, 1, S, S)
    if presmooth > 0:
        import kornia

        t = kornia.filters.gaussian_blur2d(t, (2 * ks + 1, 2 * ks + 1), (presmooth, presmooth),
                                           border_type="replicate")
    t = t[:, 0]
    wgt = (torch.clamp(1 - (torch.from_numpy(rr)[None] / torch.from_numpy(R)[:, None]) ** 2, min=0.0) ** 2).float()
    offt = torch.from_numpy(off).long()
    loc = torch.from_numpy(xy - c0 + P)
    M = off.shape[0]
    Sr = S - 3

    def residuals(loc, idx, with_jacobian=True):
        """Values at p ± v of the patches idx (k, 2M) and, with_jacobian, the derivatives of
        I(p + v) − I(p − v) by p (k, M, 2)."""
        base = torch.floor(loc)
        frac = (loc - base).float()
        v, gx, gy = _shift_patches(t[idx], frac)
        # shifted entry [y, x] is the interpolant at (x + 1 + fx, y + 1 + fy): p + v sits at base + v − 1
        b = base.long() - 1
        ip = (b[:, None, 1] + offt[None, :, 1]) * Sr + (b[:, None, 0] + offt[None, :, 0])
        im = (b[:, None, 1] - offt[None, :, 1]) * Sr + (b[:, None, 0] - offt[None, :, 0])
        ix = torch.cat([ip, im], 1).clamp(0, Sr * Sr - 1)
        k = idx.numel()
        vv = torch.gather(v.reshape(k, -1), 1, ix)
        if not with_jacobian:
            return vv, None
        gxx = torch.gather(gx.reshape(k, -1), 1, ix)
        gyy = torch.gather(gy.reshape(k, -1), 1, ix)
        J = torch.stack([gxx[:, :M] - gxx[:, M:], gyy[:, :M] - gyy[:, M:]], -1)  # (k, M, 2)
        return vv, J

    def evaluate(loc, idx):
        vv, J = residuals(loc, idx)
        return normal_from_residuals(vv[:, :M] - vv[:, M:], J, wgt[idx])

    # Levenberg–Marquardt (Gauss–Newton's steps once the damping has fallen), steps capped at 1 px so a corner
    # cannot jump to a neighbouring junction; done when a corner moves by < 1e-4 px
    sol = batched_levenberg_marquardt(
        evaluate, loc, BatchedOptions(max_iterations=iterations, max_step=1.0),
        small_step=lambda step, x, idx: torch.linalg.vector_norm(step, dim=1) < 1e-4)
    loc = sol.x
    v, _ = residuals(loc, torch.arange(N), with_jacobian=False)
    r = v[:, :M] - v[:, M:]
    wt2 = torch.cat([wgt, wgt], 1)
    mean = (v * wt2).sum(1, keepdim=True) / wt2.sum(1, keepdim=True)
    asym = torch.sqrt((wgt * r * r).sum(1) / ((wt2 * (v - mean) ** 2).sum(1) + 1e-30))
    out = loc.numpy() + c0 - P
    moved = np.hypot(*(out - xy).T)
    ok &= np.isfinite(out).all(1) & (moved < np.maximum(2.0, 1.2 * R))
    return out, asym.numpy(), ok


# --- stage 5: indexing -------------------------------------------------------------------------------------
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


# --- the whole pipeline ------------------------------------------------------------------------------------
def detect_corners(gray: np.ndarray, target: Target, *, coarse_max_size: int = 400, sigma: float = 1.5,
                   refine_radius_max: float = 20.0, timings: dict | None = None, levels: dict | None = None):
    """Corners only (stages 1–5). Returns (corners_px (N, 2) with NaN, grid_found, message, level)."""
    timings = {} if timings is None else timings
    t0 = time.perf_counter()
    N = target.n_points
    corners = np.full((N, 2), np.nan)
    levels = build_pyramid(gray) if levels is None else levels
    timings["pyramid"] = time.perf_counter() - t0
    factors = sorted(levels)
    start = [f for f in factors if max(levels[f].shape) <= coarse_max_size]
    start_f = start[0] if start else factors[-1]
    message = "no checkerboard found"
    for f in [x for x in sorted(factors, reverse=True) if x <= start_f]:
        t1 = time.perf_counter()
        img = levels[f]
        noise = estimate_noise(img)
        sm = saddle_map(img, sigma, noise)
        grid = find_grid(sm, noise)
        timings[f"grid@{f}"] = time.perf_counter() - t1
        if len(grid) < 4:
            continue
        nodes = np.array(list(grid.keys()))
        xy_l = np.array([grid[tuple(n)] for n in nodes.tolist()])
        spacing = _median_spacing(nodes, xy_l)
        if spacing < 6 and f > 1:
            continue  # too small at this level: look finer
        t2 = time.perf_counter()
        xy_f = to_full(xy_l, f)
        radius = np.clip(0.4 * _min_neighbour_distance(nodes, xy_f), 3.0, refine_radius_max)
        xy_r, asym, ok = refine_symmetric(gray, xy_f, radius)
        ok &= asym < 0.35
        timings["refine"] = time.perf_counter() - t2
        if ok.sum() < 4:
            message = "corners found at a coarse level could not be refined"
            continue
        t3 = time.perf_counter()
        res = resolve_indices(nodes[ok], xy_l[ok], xy_r[ok], sm.smooth, target)
        timings["index"] = time.perf_counter() - t3
        if res.ij is None:
            return corners, False, res.message, f
        k = target.feature_index(res.ij[:, 0], res.ij[:, 1])
        corners[k] = xy_r[ok]
        t4 = time.perf_counter()
        complete_corners(gray, target, corners, refine_radius_max)
        timings["complete"] = time.perf_counter() - t4
        return corners, True, res.message, f
    return corners, False, message, 0


def complete_corners(gray: np.ndarray, target: Target, corners: np.ndarray, refine_radius_max: float = 20.0,
                     rounds: int = 2, max_asymmetry: float = 0.35, window: float = 0.4) -> int:
    """Look for the target's corners that the grid growth missed, where the found ones predict them.

    Once the corners are indexed, a local homography (target plane -> image) from found corners within two
    indices predicts each missing one; it is refined like the others and kept when it is a clean point-
    symmetric X-junction near the prediction. Recovers corners whose coarse saddle was too weak (very
    heavy blur, the board's outer ring). `window` is the refinement window's radius in squares (0.4; a
    ChArUco board's markers ask for less). Modifies `corners` in place; returns the number added.
    """
    H, W = gray.shape
    ny, nx = target.grid_shape
    pts = target.feature_points()[:, :2]
    xe, ye = target.x_edges, target.y_edges
    added = 0
    for _ in range(rounds):
        found = np.isfinite(corners).all(1)
        if found.all() or found.sum() < 4:
            break
        # only corners within two indices of a found one can be predicted: the work grows with the corners
        # seen, not with the size of the target
        grid = np.pad(found.reshape(ny, nx), 2)
        near_found = np.zeros((ny, nx), bool)
        for dj in range(5):
            for di in range(5):
                near_found |= grid[dj:dj + ny, di:di + nx]
        missing = np.nonzero(~found & near_found.ravel())[0]
        cand, pred, spacing = [], [], []
        for k in missing:
            j, i = divmod(int(k), nx)
            near = [jj * nx + ii for jj in range(max(0, j - 2), min(ny, j + 3))
                    for ii in range(max(0, i - 2), min(nx, i + 3)) if found[jj * nx + ii]]
            if len(near) < 4 or np.linalg.matrix_rank(pts[near] - pts[near].mean(0)) < 2:
                continue
            Hm = homography_dlt(pts[near], corners[near])
            if Hm is None or not np.isfinite(Hm).all():
                continue
            q = apply_homography(Hm, np.array([[xe[i + 1], ye[j + 1]], [xe[i], ye[j + 1]], [xe[i + 2], ye[j + 1]],
                                     [xe[i + 1], ye[j]], [xe[i + 1], ye[j + 2]]]))
            sp = float(np.min(np.hypot(*(q[1:] - q[0]).T)))
            if not (3 <= q[0, 0] <= W - 4 and 3 <= q[0, 1] <= H - 4) or sp < 6:
                continue
            cand.append(int(k))
            pred.append(q[0])
            spacing.append(sp)
        if not cand:
            break
        pred, spacing = np.array(pred), np.array(spacing)
        # coarse to fine: under strong lens distortion a local homography misses by up to ~0.1 of a square,
        # beyond the reach of the final window when squares are large; a first pass with a window of half
        # the square pulls the start in, the second uses the usual window
        start, _, ok0 = refine_symmetric(gray, pred, np.clip(1.125 * window * spacing, 3.0, 2.5 * refine_radius_max))
        start = np.where(ok0[:, None] & (np.hypot(*(start - pred).T) < 0.25 * spacing)[:, None], start, pred)
        xy, asym, ok = refine_symmetric(gray, start, np.clip(window * spacing, 3.0, refine_radius_max))
        keep = ok & (asym < max_asymmetry) & (np.hypot(*(xy - pred).T) < 0.25 * spacing)
        corners[np.array(cand)[keep]] = xy[keep]
        added += int(keep.sum())
        if not keep.any():
            break
    return added


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


def detect_file(path: str, target: Target, encoding: str | None = None, **options) -> Detection:
    """`detect` on an image file read through `camio.files.read_image` (8-bit files decoded from sRGB; at
    most MAX_IMAGE_PIXELS)."""
    from camio.files import read_image

    return detect(read_image(path, encoding, MAX_IMAGE_PIXELS), target, **options)


def detect_files(paths, target: Target, *, encoding: str | None = None, measure_blur: bool = True,
                 progress=None, **options) -> list[Detection | None]:
    """`detect` on several image files: one entry per path, None where the image shows no usable board.

    Args:
        paths: image files (read by `camio.files.read_image`; 8-bit files are decoded from sRGB).
        target: the Target.
        encoding: override the files' encoding ("srgb" or "linear").
        measure_blur: also measure the blur per point.
        progress: optional callable taking one line per file (e.g. `print` to stderr): the number of corners
            found and the time, or why the view has no board, plus the detection's note if it has one.
        options: passed to `detect_corners`.
    Returns:
        list of Detection (grid_found True) or None, in the order of `paths`.
    Raises:
        DetectionError: a target too large to detect; ValueError / OSError from `read_image` for a file
        that cannot be read (bad input is an error, not a view without a board).
    """
    from camio.files import read_image

    check_target_size(target)
    out: list[Detection | None] = []
    for path in paths:
        t0 = time.perf_counter()
        det = detect(read_image(path, encoding), target, measure_blur=measure_blur, **options)
        ok = det.grid_found and bool(det.found.any())
        out.append(det if ok else None)
        if progress is not None:
            if ok:
                line = (f"{path}: {int(det.found.sum())} of {target.n_points} corners in "
                        f"{time.perf_counter() - t0:.1f} s")
                progress(line + (f" ({det.message})" if det.message else ""))
            else:
                progress(f"{path}: no board ({det.message or 'no checkerboard found'}); skipped")
    return out


def detect(image, target: Target, *, measure_blur: bool = True, **options) -> Detection:
    """Find the target's feature points and their blur in a linear image.

    Args:
        image: (H, W) or (H, W, C) linear float image (decode sRGB first).
        target: the Target.
        measure_blur: also measure the blur diameter per point (`tiltfit.detect.blur.measure_blur`).
        options: passed to `detect_corners`.
    Returns:
        Detection; grid_found False (and all NaN) when no board was found or its placement is ambiguous.
    """
    if target.dark_rectangles():
        raise DetectionError("target: a ChArUco board; its corners are found by tiltfit.detect.charuco.detect_board")
    with torch_threads(1):
        return _detect(image, target, measure_blur, options)


def check_target_size(target: Target) -> None:
    """Raise DetectionError (one line) for a target too large to detect in bounded time."""
    ny, nx = target.grid_shape
    if target.n_points > MAX_FEATURE_POINTS:
        raise DetectionError(f"target: {nx} × {ny} = {target.n_points} corners; detection handles at most "
                             f"{MAX_FEATURE_POINTS} (200 × 200)")


# A labelling is contradicted when another labelling of the same corners fits the target's geometry (a plane
# homography) this many times better in RMS, and its own RMS exceeds MIN_CONTRADICTION_PX (lens distortion
# alone leaves a pixel or two); the factor is that of `tiltfit.files.det.mirrored`.
CONTRADICTION_FACTOR = 5.0
MIN_CONTRADICTION_PX = 1.0
# ... or when no labelling fits: the homography RMS above this fraction of the median corner spacing.
MAX_UNFIT_SPACING = 0.25
CONTRADICTS = "the photo contradicts the target file"


def _alternative_labellings(target: Target) -> dict:
    """{name: permutation} of the feature points under the target's symmetries that the colour reading can
    confuse: the half turn and the two mirror images (index arrays into feature order)."""
    ny, nx = target.grid_shape
    j, i = np.divmod(np.arange(nx * ny), nx)
    return {"turned by 180°": (ny - 1 - j) * nx + (nx - 1 - i),
            "mirrored left-right": j * nx + (nx - 1 - i),
            "mirrored top-bottom": (ny - 1 - j) * nx + i}


def _radial_unfit(XY: np.ndarray, corners_px: np.ndarray, grid_shape, image_size=None) -> float:
    """The smallest homography RMS over the corner spacing once a one-parameter radial distortion (the division
    model x_u = c + (x − c) / (1 + λ r²), r over the farthest corner's distance from c, c the image centre or
    the corners' centroid, λ in [−0.6, 0.6]) is undone: a wide-angle lens bends a close board's rows by a
    quarter of a cell, which no other labelling of its corners undoes, while a different board stays unfit.

    Args:
        XY: (N, 2) the target's feature points; corners_px: (N, 2) their image positions, NaN where missing;
        grid_shape: (ny, nx) with N = ny·nx, row by row (the spacing is the median step between grid neighbours,
        as in `labelling_problem`: memory linear in N); image_size: (W, H) or None.
    """
    from tiltfit.files.det import _homography_rms

    found = np.isfinite(corners_px).all(-1)
    uv = corners_px[found]
    c = np.asarray(image_size, dtype=np.float64) / 2 if image_size is not None else uv.mean(0)
    r0 = max(float(np.linalg.norm(uv - c, axis=1).max()), 1.0)
    d = (corners_px - c) / r0
    best = math.inf
    for lam in np.linspace(-0.6, 0.6, 25):
        u = c + r0 * d / (1.0 + lam * (d * d).sum(1, keepdims=True))  # NaN where missing
        rms = _homography_rms(XY[found], u[found])
        # the corner spacing in the undistorted points: the homography's scale, from the grid neighbours
        g = u.reshape(*grid_shape, 2)
        steps = np.concatenate([np.linalg.norm(np.diff(g, axis=1), axis=-1).ravel(),
                                np.linalg.norm(np.diff(g, axis=0), axis=-1).ravel()])
        spacing = float(np.nanmedian(steps)) if np.isfinite(steps).any() else 0.0
        best = min(best, rms / spacing if spacing > 0 else math.inf)
    return best


def labelling_problem(corners_px: np.ndarray, target: Target, image_size=None) -> str:
    """Why the labelled corners (N, 2, feature order, NaN where missing) contradict the target's geometry,
    or '' when they do not.

    The cell colours choose the labelling; the corner positions must then be a projective view of the
    target's feature points. A target file whose dark_cell parity (or dark and light) does not match the
    board, a mirrored photo, or a target with its rows and columns swapped gives a labelling that a plane
    homography does not fit, while (for the first two) a turned or mirrored labelling fits
    CONTRADICTION_FACTOR times better. A board that looks alike under the symmetry (uniform rows and
    columns) cannot be told apart and is not flagged.
    """
    from tiltfit.files.det import _homography_rms

    found = np.isfinite(corners_px).all(-1)
    if found.sum() < 8:
        return ""
    XY = target.feature_points()[:, :2]
    rms = _homography_rms(XY[found], corners_px[found])
    if not rms > MIN_CONTRADICTION_PX:
        return ""
    alternatives = {name: _homography_rms(XY[perm][found], corners_px[found])
                    for name, perm in _alternative_labellings(target).items()}
    name = min(alternatives, key=alternatives.get)
    if alternatives[name] * CONTRADICTION_FACTOR < rms:
        # The fitting labelling's handedness: target X, Y seen from the printed side map to image x right,
        # y down (det > 0, as in `tiltfit.files.det.mirrored`); det < 0 is a mirror image.
        P = XY[_alternative_labellings(target)[name]][found]
        A = np.linalg.lstsq(np.column_stack([P, np.ones(len(P))]), corners_px[found], rcond=None)[0][:2].T
        if np.linalg.det(A) < 0:
            why = ("a mirror image of the board: a mirrored photo, or a target file with x_edges/y_edges swapped "
                   "or reversed")
        else:
            why = ("the board turned by 180° with the other colour parity: dark_cell (or dark and light) swapped, or "
                   "a photo mirrored across uniform columns or rows")
        return (f"{CONTRADICTS}: the corners fit {why} (homography RMS {alternatives[name]:.2g} px), not the "
                f"labelling the cell colours give (RMS {rms:.2g} px)")
    ny, nx = target.grid_shape
    grid = corners_px.reshape(ny, nx, 2)
    steps = np.concatenate([np.linalg.norm(np.diff(grid, axis=1), axis=-1).ravel(),
                            np.linalg.norm(np.diff(grid, axis=0), axis=-1).ravel()])
    spacing = float(np.nanmedian(steps)) if np.isfinite(steps).any() else math.inf
    if rms > MAX_UNFIT_SPACING * spacing and _radial_unfit(XY, corners_px, (ny, nx), image_size) > MAX_UNFIT_SPACING:
        return (f"{CONTRADICTS}: no projective view of its {nx}×{ny} corners fits the photo's (homography RMS "
                f"{rms:.3g} px at a corner spacing of {spacing:.3g} px): a different board, or x_edges and "
                "y_edges swapped")
    return ""


def labelling_note(corners_px: np.ndarray, target: Target) -> str:
    """A note saying how the labelled corners (N, 2, feature order) lie when the target's columns (its X
    axis) run closer to the image's vertical than its horizontal: a board turned by 90° in the photo, or a
    target file with x_edges and y_edges swapped (on a board with uniform rows and columns both label the
    corners consistently, so only the note can tell); '' otherwise."""
    found = np.isfinite(corners_px).all(-1)
    if found.sum() < 3:
        return ""
    XY = target.feature_points()[found, :2]
    A = np.linalg.lstsq(np.column_stack([XY, np.ones(len(XY))]), corners_px[found], rcond=None)[0][:2].T
    if abs(A[1, 0]) <= abs(A[0, 0]):
        return ""
    ny, nx = target.grid_shape
    return (f"labelled with the target's {nx} corners a row (x_edges) running along the image's vertical: the "
            "board is turned by 90° in the photo, or the target file's x_edges and y_edges are swapped")



# --- colour checks of a labelling --------------------------------------------------------------------------
# What one photo of a checkerboard with uniform cells can tell about the target file (docs/charuco.md,
# "Inverted prints and mirror images"): every lattice symmetry changes a cell's parity i + j by a constant, so the
# colours fix the placement only up to that constant. A labelling is checked by (1) the cells' colours: the share
# of the cells next to found corners whose colour it predicts; 0 when no placement explains them (the target
# file's other dark_cell parity; or, on a board of even × even cells, a mirrored photo, which is the same
# picture); 1 when right. Below MIN_COLOUR_AGREEMENT, the midpoint, it is refused. (2) the margin: next to a light
# border cell, within the margin, the photo must stay light (one white sheet), read MARGIN_PROBE_SQUARES of a
# square out (at most half the margin) and normalised between the median dark (0) and light (1) cell; below
# 0.5 on most such probes the margin is dark: inverted colours (a white-on-black print, or an inverted photo).
# Blur spreads a cell's edge symmetrically, so a probe any distance out stays on its side of 0.5.
MIN_COLOUR_AGREEMENT = 0.5
MARGIN_PROBE_SQUARES = 0.15
# the least number of margin probes (inside the image) that decide, and the share of them that must be dark
MIN_MARGIN_PROBES = 3
DARK_MARGIN_SHARE = 0.75


def invert_photo(gray: np.ndarray) -> np.ndarray:
    """A photo of a white-on-black board as its dark-on-white counterpart: max − I (affine, so the corners and
    the blur widths stay where they are)."""
    return (np.float32(gray.max()) - gray).astype(np.float32)


def _cell_and_margin_samples(gray: np.ndarray, corners_px: np.ndarray, target: Target):
    """Grey levels at the centres of the cells next to found corners, and at margin probes beside the border
    cells, each placed by the local homography (`tiltfit.detect.blur._local_homographies`) of the nearest found corner.

    Returns:
        cells: (m, 3) [column, row, level]; margin: (p, 3) [column, row, level] of the border cell each probe
        is beside (probes outside the image left out).
    """
    import cv2

    from tiltfit.detect.blur import _local_homographies

    ny, nx = target.grid_shape
    found = np.isfinite(corners_px).all(-1)
    Hs = _local_homographies(target, corners_px, found)
    xe, ye = np.asarray(target.x_edges), np.asarray(target.y_edges)
    smooth = cv2.GaussianBlur(gray, (0, 0), 1.0)
    h, w = gray.shape
    cells, margin = {}, []
    for k, Hm in Hs.items():
        j, i = divmod(k, nx)
        for c, r in ((i, j), (i + 1, j), (i, j + 1), (i + 1, j + 1)):  # corner (i, j) touches cells i..i+1, j..j+1
            if (c, r) in cells:
                continue
            centre = np.array([[0.5 * (xe[c] + xe[c + 1]), 0.5 * (ye[r] + ye[r + 1])]])
            out = []
            s = min(xe[c + 1] - xe[c], ye[r + 1] - ye[r])
            d = min(MARGIN_PROBE_SQUARES * s, 0.5 * target.margin)
            if d > 0:
                if c == 0:
                    out.append([xe[0] - d, centre[0, 1]])
                if c == target.n_cols - 1:
                    out.append([xe[-1] + d, centre[0, 1]])
                if r == 0:
                    out.append([centre[0, 0], ye[0] - d])
                if r == target.n_rows - 1:
                    out.append([centre[0, 0], ye[-1] + d])
            xy = apply_homography(Hm, np.concatenate([centre, np.array(out).reshape(-1, 2)]))
            inside = (xy[:, 0] >= 2) & (xy[:, 0] <= w - 3) & (xy[:, 1] >= 2) & (xy[:, 1] <= h - 3)
            if not inside[0]:
                continue
            v = _bilinear(smooth, xy)
            cells[(c, r)] = v[0]
            margin += [[c, r, m] for m in v[1:][inside[1:]]]
    cells_a = np.array([[c, r, v] for (c, r), v in cells.items()]).reshape(-1, 3)
    return cells_a, np.array(margin).reshape(-1, 3)


def colour_problem(gray: np.ndarray, corners_px: np.ndarray, target: Target) -> str:
    """Why the labelled corners' colours contradict the target file (inverted colours, the other dark-cell
    parity or a mirrored photo), or '' when they do not or cannot be told (see the notes above
    MIN_COLOUR_AGREEMENT).

    Args:
        gray: (H, W) linear image, as detected (inverted already for an `inverted` target);
        corners_px: (N, 2) labelled corners, feature order, NaN where missing.
    """
    cells, margin = _cell_and_margin_samples(gray, corners_px, target)
    if len(cells) < 4:
        return ""
    lo, hi = np.percentile(cells[:, 2], [10, 90])
    if not hi > lo:
        return ""
    observed_dark = cells[:, 2] < 0.5 * (lo + hi)
    expected_dark = target.is_dark(cells[:, 0].astype(int), cells[:, 1].astype(int))
    if observed_dark.all() or not observed_dark.any():
        return ""
    dark_level = float(np.median(cells[observed_dark, 2]))
    light_level = float(np.median(cells[~observed_dark, 2]))
    # probes beside the border cells seen light: one white sheet with the margin, unless the colours are inverted
    light_cells = {(int(c), int(r)) for (c, r, _), d in zip(cells, observed_dark) if not d}
    beside_light = np.array([(int(c), int(r)) in light_cells for c, r, _ in margin], bool)
    probes = (margin[beside_light, 2] - dark_level) / (light_level - dark_level) if len(margin) else np.zeros(0)
    if len(probes) >= MIN_MARGIN_PROBES and np.mean(probes < 0.5) >= DARK_MARGIN_SHARE:
        if target.inverted:
            return (f"{CONTRADICTS}: inverted colours: the target file says \"inverted\": true, but the photo shows "
                    "dark cells on a light sheet (remove the key)")
        return (f"{CONTRADICTS}: inverted colours: the margin around the board is as dark as its dark cells "
                f"(median {np.median(probes):.2f} of the way from dark to light): a board printed white on black "
                "(add \"inverted\": true to the target file) or a colour-inverted photo")
    agreement = float(np.mean(observed_dark == expected_dark))
    if agreement < MIN_COLOUR_AGREEMENT:
        ny, nx = target.grid_shape
        mirror = (" or the photo is mirrored (on a board of an even number of cells each way a mirror image swaps "
                  "the colours)" if target.n_cols % 2 == 0 and target.n_rows % 2 == 0 else "")
        return (f"{CONTRADICTS}: the cells' colours match no placement of its {nx}×{ny} corners ({100 * agreement:.0f} % "
                f"of {len(cells)} cells agree with the best): its dark_cell has the other parity{mirror}")
    return ""


def _detect(image, target, measure_blur, options) -> Detection:
    check_target_size(target)
    timings: dict = {}
    t0 = time.perf_counter()
    gray = to_gray(image)
    if target.inverted:
        gray = invert_photo(gray)
    H, W = gray.shape
    levels = build_pyramid(gray)
    corners, found, message, level = detect_corners(gray, target, timings=timings, levels=levels, **options)
    problem = (colour_problem(gray, corners, target) or labelling_problem(corners, target, (W, H))) if found else ""
    if problem:
        corners, found, message = np.full_like(corners, np.nan), False, problem
    elif found:
        message = "; ".join(m for m in (message, labelling_note(corners, target)) if m)
    N = target.n_points
    blur, sigma = np.full(N, np.nan), np.full(N, np.nan)
    if found and measure_blur:
        t1 = time.perf_counter()
        blur, sigma = _measure_blur(gray, target, corners, levels=levels)
        timings["blur"] = time.perf_counter() - t1
    timings["total"] = time.perf_counter() - t0
    return Detection((W, H), corners, blur, sigma, found, message, level, timings)
