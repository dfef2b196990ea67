"""Experiments built on the tiltfit library (the library never imports them; `tests/tiltfit/test_package_layers.py`):

- `reproduce`: the tilt-lens paper's experiment end to end on a simulated camera (`tiltfit reproduce`), one
  module per stage, with `scenes` (its boxes scene and camera);
- `charuco_views`: the ChArUco board, camera and views of `tests/tiltfit/test_charuco.py` and
  `benchmarks/detection/bench_charuco.py`, and their constant-blur renders;
- `stability`: where each method fails, one module per study (`tiltfit stability`), and `cluster` (its studies
  as Ray tasks).
"""
