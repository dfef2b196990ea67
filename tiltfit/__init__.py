"""Tilt-lens calibration from photographs of a checkerboard: corners, blur widths, a camera model, fits.

Layers (bottom to top; `tests/tiltfit/test_layers.py` checks them, and that nothing forms an import cycle):
- library: `target` (the board), `imaging` (pyramid, homography), `blur`, `detect`, `model`, `fit`, `validate`,
  `photometric`, the file formats (`calibfile`, `detfile`, `formats`, `export`), `report`, `evaluate` (photo
  against rendering), `synth` (synthetic observations and images), `opencv_corners`, `runlog`, `target_cli`;
- experiments built on the library: `reproduce` (the paper's experiment) with `scenes`, and `stability/`
  (where each method fails, one module per study); the library never imports them;
- front end: `cli` (`tiltfit ...`, also `python -m tiltfit`).
`tiltfit` builds on `renderer`'s public API; `renderer` never imports `tiltfit`.
"""
