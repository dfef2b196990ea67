"""The files tiltfit reads and writes: CALIB.json (`calib`), DET.json (`det`), a calibration read once into
one object (`calibrated`, through `calib_lens`), other libraries' formats (`export`), the scene-file components
(`scene_plugins`) and the generated format reference (`formats`)."""
