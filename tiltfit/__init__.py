"""Tilt-lens calibration from photographs of a checkerboard: corners, blur widths, a camera model, fits.

Layers (bottom to top; `tests/tiltfit/test_layers.py` checks them, and that nothing forms an import cycle):
- library: `target` (the board), `imaging` (pyramid, homography), `blur`, `detect`, `charuco` (ChArUco boards, and
  `detect_board` for any target), `model`, `fit`, `validate`,
  `photos` (calibration from photographs, the Python entry point), `photometric`, the file formats (`calibfile`, `detfile`, `formats`, `export`), `report`, `evaluate` (photo
  against rendering), `calibrated` (a calibration file as one object) with `scene_plugins` (its scene-file camera
  and target shape) and `composite` (CG rendered into calibrated photos, and the board-alignment check), `synth`
  (synthetic observations and images), `opencv_corners`, `runlog`, `target_cli`;
- experiments built on the library, in `experiments/`: `reproduce` (the paper's experiment) with `scenes`,
  `stability/` (where each method fails, one module per study) and `cluster`; the library never imports them;
- front end: `cli` (`tiltfit ...`, also `python -m tiltfit`).
`tiltfit` builds on `renderer`'s public API; `renderer` never imports `tiltfit`.
"""

__all__ = ["Calibration", "calibrate_photos"]


def __getattr__(name: str):
    """`tiltfit.calibrate_photos` and `tiltfit.Calibration` (`tiltfit.calibrate.photos`), imported on first use so that
    `import tiltfit` stays light."""
    if name in __all__:
        from tiltfit.calibrate import photos

        return getattr(photos, name)
    raise AttributeError(f"module 'tiltfit' has no attribute {name!r}")
