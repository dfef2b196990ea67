"""DET.json, the detection file of `tiltfit detect`: what it records about itself, and the checks on reading.

Contract keys: `image_size_px` [W, H], `corners_px` ([x, y] or null per feature point, in the target's
feature-point order), `blur_px` (number or null per feature point), `grid_found`.
Self-description (written by `describe_detection`, optional on reading, so older and hand-made files work):
    format_version   DET_FORMAT_VERSION; a file of a newer version is refused
    image            the image the corners were found in, as given on the command line
    target           {file, n_points, x_edges_count, y_edges_count}: the target file and its size
    units            what each array holds and in which unit (pixels; x = column, y = row, (0, 0) the centre of
                     the top-left pixel; blur_px the diameter of the blur disc)
    created          UTC date and time, ISO 8601
    software         "tiltfit <version>"

Reading (`read_det`) refuses, with one line naming the file and the field: non-finite or huge numbers, a
negative blur width, corners outside the image, an image size beyond `MAX_IMAGE_SIDE`, and the wrong number of
entries. `check_views` then refuses sets of views no calibration should use: a view whose corners lie on one
line (no pose), a view that is a copy of another (the uncertainty would shrink as if it were independent), and
a mirrored board (a flipped image or a board seen from behind: no lens maps the target like that).
"""
from __future__ import annotations

import datetime

import numpy as np

from camio.files import software_version
from camio.checks import describe, is_finite_number, read_json

DET_FORMAT_VERSION = 1
MAX_IMAGE_SIDE = 1 << 17
# The largest photo detection reads (pixels): above the largest camera sensors (about 150 megapixels); the
# pyramid and saddle maps need tens of bytes a pixel, so larger files (or decompression bombs) are refused
# from their header.
MAX_IMAGE_PIXELS = 200_000_000
#: The fewest corners a view must have to enter a calibration, everywhere (`tiltfit calibrate`'s DET check, the
#: fit's `min_corners`, `tiltfit target design`): a pose takes 6 parameters and 3 corners fit it exactly; 6 corners
#: (12 residuals) leave as many again to say something about the lens, and PnP's start needs 4.
MIN_CORNERS = 6

UNITS = {
    "corners_px": "pixels; x = column, y = row, (0, 0) the centre of the top-left pixel",
    "blur_px": "pixels; the diameter of the blur disc (circle of confusion) at each feature point, from the "
               "edge profiles around it",
    "image_size_px": "pixels; [width, height]",
}


class DetFileError(ValueError):
    """A DET.json that cannot be used; one line `<file>: <field>: <problem>`."""


def software() -> str:
    return software_version("tiltfit")


def describe_detection(det: dict, image: str, target_file: str, target) -> dict:
    """`det` (the contract keys and the detector's extras) with the self-describing keys added."""
    return {
        "format_version": DET_FORMAT_VERSION,
        "image": image,
        "target": {"file": target_file, "n_points": int(target.n_points),
                   "x_edges_count": len(target.x_edges), "y_edges_count": len(target.y_edges)},
        "units": dict(UNITS),
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "software": software(),
        **det,
    }


def read_det(path: str, n_points: int) -> dict:
    """Read and validate a DET.json for a target of `n_points` feature points.

    Returns:
        The parsed dict (numbers as given; null entries kept).
    Raises:
        DetFileError: one line naming the file and the field.
    """

    def fail(field, problem):
        raise DetFileError(f"{path}: {field}: {problem}")

    det = read_json(path, DetFileError, "detection file")
    if not isinstance(det, dict):
        raise DetFileError(f"{path}: expected a JSON object (a detection file of `tiltfit detect`)")
    version = det.get("format_version", DET_FORMAT_VERSION)
    if not (isinstance(version, int) and not isinstance(version, bool) and 1 <= version <= DET_FORMAT_VERSION):
        fail("format_version", f"expected 1 to {DET_FORMAT_VERSION} (this tiltfit's), got {describe(version)}")
    for key in ("image_size_px", "corners_px", "blur_px"):
        if key not in det:
            fail(key, "missing key")
    size = det["image_size_px"]
    if not (isinstance(size, list) and len(size) == 2
            and all(isinstance(s, int) and not isinstance(s, bool) and 0 < s <= MAX_IMAGE_SIDE for s in size)):
        fail("image_size_px", f"expected [width, height], integers in 1..{MAX_IMAGE_SIDE}, got {describe(size)}")
    width, height = size
    diagonal = float(np.hypot(width, height))
    for key, per in (("corners_px", 2), ("blur_px", 1)):
        vals = det[key]
        if not isinstance(vals, list) or len(vals) != n_points:
            got = len(vals) if isinstance(vals, list) else type(vals).__name__
            fail(key, f"expected a list of {n_points} entries (one per feature point), got {got}")
        for i, v in enumerate(vals):
            if v is None:
                continue
            if per == 2:
                if not (isinstance(v, list) and len(v) == 2 and all(is_finite_number(x) for x in v)):
                    fail(f"{key}[{i}]", f"expected [x, y] (finite numbers) or null, got {describe(v)}")
                x, y = v
                if not (-1.5 <= x <= width + 0.5 and -1.5 <= y <= height + 0.5):
                    fail(f"{key}[{i}]", f"[{x}, {y}] lies outside the {width}x{height} image")
            else:
                if not is_finite_number(v):
                    fail(f"{key}[{i}]", f"expected a finite number or null, got {describe(v)}")
                if not 0 <= v <= diagonal:
                    fail(f"{key}[{i}]", f"expected a blur-disc diameter in [0, {diagonal:.0f}] pixels (the image "
                                        f"diagonal), got {v}")
    if "grid_found" in det and not isinstance(det["grid_found"], bool):
        fail("grid_found", f"expected true or false, got {describe(det['grid_found'])}")
    if not any(v is not None for v in det["corners_px"]):
        raise DetFileError(f"{path}: no board found")
    return det


def too_few_corners(corners_px: np.ndarray) -> str | None:
    """Why a view (corners_px (N, 2) pixels, NaN where not found) has too few corners to calibrate, or None:
    fewer than `MIN_CORNERS`. `tiltfit calibrate` skips such a view (a partial detection) and goes on with the
    others."""
    n = int(np.isfinite(corners_px).all(-1).sum())
    return f"{n} corners found; a view needs at least {MIN_CORNERS} (not on one line)" if n < MIN_CORNERS else None


def check_view(name: str, corners_px: np.ndarray, points: np.ndarray) -> None:
    """Refuse one view whose found corners cannot calibrate: fewer than `tiltfit.calibrate.model.MIN_CORNERS` (6), all on one
    line (in the image or on the target), or a mirror image of the target.

    Args:
        corners_px: (N, 2) pixels, NaN where not found; points: (N, 3) target points, mm (Z = 0).
    """
    found = np.isfinite(corners_px).all(-1)
    n = int(found.sum())
    few = too_few_corners(corners_px)
    if few:
        raise DetFileError(f"{name}: corners_px: {few}")
    xy, XY = corners_px[found], points[found, :2]
    for what, p in (("in the image", xy), ("on the target", XY)):
        centred = p - p.mean(0)
        s = np.linalg.svd(centred, compute_uv=False)
        if not s[0] > 0 or s[1] / s[0] < 1e-6:
            raise DetFileError(f"{name}: corners_px: the {n} found corners lie on one line {what}; a view needs "
                               "corners in at least two rows and two columns")
    if mirrored(corners_px, points):
        raise DetFileError(f"{name}: corners_px: {MIRRORED}")


MIRRORED = "the board appears mirrored (a flipped image, or the target seen from behind); no lens maps the target " \
           "like this"


def mirrored(corners_px: np.ndarray, points: np.ndarray) -> bool:
    """Whether the found corners (N, 2) show the target's feature points (N, 3, in feature order) mirrored.

    Two signs, either suffices:
    - handedness: an affine fit image ≈ A · target + b has det A < 0. Target X (columns) and Y (rows) seen
      from the printed side map to image x right, y down, so det A > 0 for every real view;
    - a board with non-uniform rows or columns seen in a mirror is labelled by a detector with an
      orientation-preserving placement that does not fit: the plane homography leaves an RMS above 1 px while
      the same corners with their rows (or columns) read backwards fit at least 5 times better. (A uniform
      board's mirror image is indistinguishable from a turned board, and is not flagged.)
    """
    found = np.isfinite(corners_px).all(-1)
    n = int(found.sum())
    if n < 3:
        return False
    XY = points[:, :2]
    M = np.column_stack([XY[found], np.ones(n)])
    A = np.linalg.lstsq(M, corners_px[found], rcond=None)[0][:2].T
    if np.linalg.det(A) < 0:
        return True
    if n < 8:
        return False
    nx = len(np.unique(XY[:, 0]))
    ny = len(XY) // nx
    if nx * ny != len(XY):
        return False
    k = np.arange(len(XY))
    i, j = k % nx, k // nx
    fit = _homography_rms(XY[found], corners_px[found])
    if not fit > 1.0:
        return False
    backwards = [XY[j * nx + (nx - 1 - i)], XY[(ny - 1 - j) * nx + i]]
    return min(_homography_rms(P[found], corners_px[found]) for P in backwards) < fit / 5


def _homography_rms(src: np.ndarray, dst: np.ndarray) -> float:
    """RMS residual, pixels, of the least-squares plane homography src (N, 2) -> dst (N, 2)."""
    import cv2

    H, _ = cv2.findHomography(src.astype(np.float64), dst.astype(np.float64), 0)
    if H is None or not np.isfinite(H).all():
        return float("inf")
    p = np.column_stack([src, np.ones(len(src))]) @ H.T
    if not (np.abs(p[:, 2]) > 1e-12).all():
        return float("inf")
    return float(np.sqrt((((p[:, :2] / p[:, 2:3]) - dst) ** 2).sum(1).mean()))


def check_views(names: list[str], corners_px: np.ndarray) -> None:
    """Refuse views that repeat another view's detections (within 1e-6 px).

    Args:
        corners_px: (V, N, 2) pixels, NaN where not found.
    """
    seen: dict[bytes, str] = {}
    for name, c in zip(names, corners_px):
        key = np.round(np.nan_to_num(c, nan=-1e9) * 1e6).astype(np.int64).tobytes()
        if key in seen:
            raise DetFileError(f"{name}: corners_px: the same detections as {seen[key]}; a repeated view would "
                               "shrink the uncertainties as if it were independent evidence")
        seen[key] = name
