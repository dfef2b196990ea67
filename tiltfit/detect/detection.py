"""One image's detection: the `Detection` record (corners, blur widths, what was found), the error a photo
without a usable board raises, and the record's JSON file (`tiltfit detect`'s per-image output).

Pixels: x = column, y = row, (0, 0) the centre of the top-left pixel.
"""
from __future__ import annotations

import json
import os
import tempfile
from dataclasses import dataclass, field

import numpy as np


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
