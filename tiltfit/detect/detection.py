"""One image's detection: the `Detection` record (corners, blur widths, what was found), the error a photo
without a usable board raises, and the record's JSON file (`tiltfit detect`'s per-image output).

Pixels: x = column, y = row, (0, 0) the centre of the top-left pixel.
"""
from __future__ import annotations

import json
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

        num = det_number
        return {
            "image_size_px": [int(self.image_size_px[0]), int(self.image_size_px[1])],
            "corners_px": [None if not np.isfinite(c).all() else [num(c[0]), num(c[1])] for c in self.corners_px],
            "blur_px": [num(b) for b in self.blur_px],
            "grid_found": bool(self.grid_found),
            "blur_sigma_px": [num(b) for b in self.blur_sigma_px],
            "n_found": int(self.found.sum()),
            "message": self.message,
        }


#: DET.json's pixel values are rounded to this many decimals (1e-4 px, far below any detector's precision).
DET_DECIMALS = 4


def det_number(v) -> float | None:
    """A pixel value as DET.json holds it: rounded to `DET_DECIMALS`, None where not finite."""
    return None if not np.isfinite(v) else float(round(float(v), DET_DECIMALS))


def write_det_json(data: dict, path: str) -> None:
    """Write a DET.json dict: the one writer of `tiltfit detect`'s files, atomic with umask permissions like every
    other output (`camio.files.write_text`)."""
    from camio.files import write_text

    write_text(path, json.dumps(data, indent=1, allow_nan=False) + "\n")


def write_detection_json(detection: Detection, path: str) -> None:
    """Write the detection as DET.json (`write_det_json`; no partial file on failure)."""
    write_det_json(detection.to_json_dict(), path)


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
