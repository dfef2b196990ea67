"""Tilt-lens calibration from photographs of a checkerboard: corners, blur widths, a camera model, fits.

Folders, one concept each (bottom to top; `tests/tiltfit/test_package_layers.py` checks the layers and that nothing forms
an import cycle; docs/architecture.md walks a photo through them):
- `target/`: the board (`layout`) and the printed board's fitted shape (`shape`);
- `detect/`: corners (chessboard, ChArUco, OpenCV's as a peer) and blur widths in an image;
- `solve/`: the one least-squares solver and the one robust linear solve;
- `calibrate/`: the camera model, its fit, the starting camera and the calibration as a sequence of stages;
- `select/`: which model the data support (held-out error, nested-model tests, the board shape);
- `uncertainty/`: covariances, projection uncertainty, two calibrations compared;
- `photometric/`: the photo against the rendering (profiles, the photometric refinement, the aperture closed form);
- `files/`: CALIB.json, DET.json, the calibration read once (`files.calibrated.Calibration`), other libraries'
  formats, the scene-file components and the generated format reference;
- `report/`: the calibration report, real against rendered, CG composited into photos;
- `experiments/`: the paper's experiment (`reproduce`), the stability studies and synthetic observations;
  the library never imports them;
- `cli/`: the `tiltfit` command (also `python -m tiltfit`).
`tiltfit` builds on `renderer`'s public API and on `camio` (files, checks, errors, progress); `renderer` never
imports `tiltfit`.
"""

__all__ = ["Calibration", "calibrate_photos"]


def __getattr__(name: str):
    """`tiltfit.calibrate_photos` and `tiltfit.Calibration` (`tiltfit.calibrate.photos`), imported on first use so that
    `import tiltfit` stays light."""
    if name in __all__:
        from tiltfit.calibrate import photos

        return getattr(photos, name)
    raise AttributeError(f"module 'tiltfit' has no attribute {name!r}")
