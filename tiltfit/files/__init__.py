"""The files tiltfit reads and writes.

Modules:
    calib          CALIB.json: written from a fit (`calib_dict`), read and checked (`read_calib`, `validate_calib`)
    det            DET.json: a view's detected corners and blur widths
    calibrated     a calibration read once into one object (`Calibration`), through `calib_lens`
    calib_lens     the lens of a CALIB.json dict (`lens_from_calib`: the one place it becomes a `renderer.Lens`)
    export         a calibration in other libraries' terms (OpenCV's camera, kornia) and what the readers share
    opencv_file    OpenCV FileStorage camera files (`write_opencv`, `read_opencv`)
    mrcal_file     mrcal .cameramodel files (`write_mrcal`, `read_mrcal`)
    scene_plugins  the scene-file components for the renderer (the `calibrated` camera, the `target` shape)
    formats        the generated format reference (docs/file_formats.md) and JSON schemas
"""
