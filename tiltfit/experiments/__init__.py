"""Experiments built on the tiltfit library (the library never imports them; `tests/tiltfit/test_layers.py`):

- `reproduce`: the tilt-lens paper's experiment end to end on a simulated camera (`tiltfit reproduce`), with
  `scenes` (its boxes scene and camera);
- `stability`: where each method fails, one module per study (`tiltfit stability`), and `cluster` (its studies
  as Ray tasks).
"""
