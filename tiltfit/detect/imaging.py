"""Image and plane-geometry helpers shared by corner detection (`tiltfit.detect.chessboard` and its stages) and
blur measurement (`tiltfit.detect.blur`): the 2×2 box pyramid and its pixel mapping, the normalised-DLT homography,
a guard that runs small-tensor work on one torch thread, the grey image of a photo (`to_gray`), its noise
(`estimate_noise`) and bilinear samples (`_bilinear`).

Library layer, bottom: imports only `tiltfit.detect.detection` (for DetectionError), so the detector's stages and
`blur` import it and the dependency runs one way (chessboard -> blur -> imaging). Pixel coordinates: x = column,
y = row, (0, 0) the centre of the top-left pixel.
"""
from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
import torch

from tiltfit.detect.detection import DetectionError


class torch_threads:
    """Run a block with `n` torch threads, then restore. The tensors here are small (patches, bands): extra
    threads only add synchronisation, and on a busy machine OpenMP spinning makes them many times slower."""

    def __init__(self, n: int = 1):
        self.n = n

    def __enter__(self):
        self.saved = torch.get_num_threads()
        if self.saved != self.n:
            torch.set_num_threads(self.n)

    def __exit__(self, *exc):
        if torch.get_num_threads() != self.saved:
            torch.set_num_threads(self.saved)


# --- image pyramid -----------------------------------------------------------------------------------------
def build_pyramid(gray: np.ndarray, min_size: int = 64) -> "Pyramid":
    """{factor: image} with factor 1, 2, 4, ...: each level the 2×2 box average of the previous one, down to the
    last whose halving would be under `min_size` px (a `Pyramid`: each level made when first read)."""
    return Pyramid(gray, min_size)


class Pyramid(Mapping):
    """`build_pyramid`'s levels as a read-only mapping {factor: (h, w) image}: its factors known at once, each level
    made when first read (from the one above it, the 2×2 box average), so that a detection that reads only the full
    resolution pays for no other. Iterates in increasing factor."""

    def __init__(self, gray: np.ndarray, min_size: int = 64):
        self._levels = {1: gray}
        self._factors = [1]
        h, w = gray.shape
        while min(h, w) // 2 >= min_size:
            h, w = h // 2, w // 2
            self._factors.append(2 * self._factors[-1])

    def __getitem__(self, f: int) -> np.ndarray:
        if f not in self._levels:
            if f not in self._factors:
                raise KeyError(f)
            img = self[f // 2]
            h, w = (img.shape[0] // 2) * 2, (img.shape[1] // 2) * 2
            self._levels[f] = 0.25 * (img[0:h:2, 0:w:2] + img[1:h:2, 0:w:2] + img[0:h:2, 1:w:2] + img[1:h:2, 1:w:2])
        return self._levels[f]

    def __iter__(self):
        return iter(self._factors)

    def __len__(self) -> int:
        return len(self._factors)


def to_full(xy_level: np.ndarray, factor: int) -> np.ndarray:
    """Pixel coordinates at a pyramid level -> full resolution."""
    return (xy_level + 0.5) * factor - 0.5


# --- plane homography --------------------------------------------------------------------------------------
def homography_dlt(src: np.ndarray, dst: np.ndarray) -> np.ndarray | None:
    """Least-squares homography dst ~ H src (normalised DLT), or None.

    Args:
        src, dst: (N, 2) corresponding points, N >= 4.
    Returns:
        (3, 3) H with H[2, 2] = 1, or None (fewer than 4 points, or H[2, 2] ≈ 0).
    """
    if src.shape[0] < 4:
        return None
    Hm = homography_dlt_batch(src[None], dst[None])[0]
    return Hm if np.isfinite(Hm).all() else None


def homography_dlt_batch(src: np.ndarray, dst: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """`homography_dlt` for K point sets at once (one batched SVD instead of K calls).

    Args:
        src, dst: (K, M, 2) corresponding points; valid: (K, M) bool, the points each set uses [all].
    Returns:
        (K, 3, 3) homographies with H[2, 2] = 1; NaN for a set with fewer than 4 valid points or H[2, 2] ≈ 0.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    K, M = src.shape[:2]
    w = np.ones((K, M)) if valid is None else np.asarray(valid, dtype=np.float64)
    n = np.maximum(w.sum(1), 1.0)

    def norm(p):
        """(K, 3, 3) similarity moving the valid points' centroid to 0 and their mean distance to √2."""
        m = (p * w[..., None]).sum(1) / n[:, None]
        s = math.sqrt(2) / np.maximum((np.sqrt(((p - m[:, None]) ** 2).sum(-1)) * w).sum(1) / n, 1e-12)
        T = np.zeros((K, 3, 3))
        T[:, 0, 0], T[:, 1, 1], T[:, 2, 2] = s, s, 1.0
        T[:, :2, 2] = -s[:, None] * m
        return T

    Ts, Td = norm(src), norm(dst)
    x, y = (Ts[:, None, 0, 0] * src[..., 0] + Ts[:, None, 0, 2]), (Ts[:, None, 1, 1] * src[..., 1] + Ts[:, None, 1, 2])
    u, v = (Td[:, None, 0, 0] * dst[..., 0] + Td[:, None, 0, 2]), (Td[:, None, 1, 1] * dst[..., 1] + Td[:, None, 1, 2])
    zero, one = np.zeros_like(x), np.ones_like(x)
    rows = np.stack([np.stack([-x, -y, -one, zero, zero, zero, u * x, u * y, u], -1),
                     np.stack([zero, zero, zero, -x, -y, -one, v * x, v * y, v], -1)], 2)  # (K, M, 2, 9)
    rows = (rows * w[..., None, None]).reshape(K, 2 * M, 9)  # a point left out gives zero rows
    if 2 * M < 9:  # the thin SVD below needs 9 rows for the null vector; zero rows change nothing
        rows = np.concatenate([rows, np.zeros((K, 9 - 2 * M, 9))], 1)
    _, _, vt = np.linalg.svd(rows, full_matrices=False)  # (not the 2M × 2M left factor)
    Hn = vt[:, -1].reshape(K, 3, 3)
    Hm = np.linalg.inv(Td) @ Hn @ Ts
    h22 = Hm[:, 2, 2]
    good = (np.abs(h22) > 1e-15) & (w.sum(1) >= 4)
    out = np.full((K, 3, 3), np.nan)
    out[good] = Hm[good] / h22[good, None, None]
    return out


def apply_homography(Hm: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(N, 2) points mapped by the (3, 3) homography Hm (with the perspective division)."""
    q = np.c_[p, np.ones(len(p))] @ Hm.T
    return q[:, :2] / q[:, 2:]


# --- grey images ------------------------------------------------------------------------------------------
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
