"""Image and plane-geometry helpers shared by corner detection (`tiltfit.detect`) and blur measurement
(`tiltfit.blur`): the 2×2 box pyramid and its pixel mapping, the normalised-DLT homography, and a guard that
runs small-tensor work on one torch thread.

Library layer, bottom: imports neither `detect` nor `blur`, so both import it and the dependency runs one way
(detect -> blur -> imaging). Pixel coordinates: x = column, y = row, (0, 0) the centre of the top-left pixel.
"""
from __future__ import annotations

import math

import numpy as np
import torch


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
def build_pyramid(gray: np.ndarray, min_size: int = 64) -> dict[int, np.ndarray]:
    """{factor: image} with factor 1, 2, 4, ...: each level the 2×2 box average of the previous one."""
    levels = {1: gray}
    f, img = 1, gray
    while min(img.shape) // 2 >= min_size:
        h, w = (img.shape[0] // 2) * 2, (img.shape[1] // 2) * 2
        img = 0.25 * (img[0:h:2, 0:w:2] + img[1:h:2, 0:w:2] + img[0:h:2, 1:w:2] + img[1:h:2, 1:w:2])
        f *= 2
        levels[f] = img
    return levels


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

    def norm(p):
        m = p.mean(0)
        s = math.sqrt(2) / max(np.sqrt(((p - m) ** 2).sum(1)).mean(), 1e-12)
        return np.array([[s, 0, -s * m[0]], [0, s, -s * m[1]], [0, 0, 1]])

    Ts, Td = norm(src), norm(dst)
    s = np.c_[src, np.ones(len(src))] @ Ts.T
    d = np.c_[dst, np.ones(len(dst))] @ Td.T
    rows = []
    for (x, y, _), (u, v, _) in zip(s, d):
        rows.append([-x, -y, -1, 0, 0, 0, u * x, u * y, u])
        rows.append([0, 0, 0, -x, -y, -1, v * x, v * y, v])
    _, sv, vt = np.linalg.svd(np.asarray(rows))
    Hn = vt[-1].reshape(3, 3)
    Hm = np.linalg.inv(Td) @ Hn @ Ts
    return Hm / Hm[2, 2] if abs(Hm[2, 2]) > 1e-15 else None


def apply_homography(Hm: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(N, 2) points mapped by the (3, 3) homography Hm (with the perspective division)."""
    q = np.c_[p, np.ones(len(p))] @ Hm.T
    return q[:, :2] / q[:, 2:]
