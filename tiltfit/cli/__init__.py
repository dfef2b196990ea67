"""The `tiltfit` command.

Modules:
    main         the entry point (`tiltfit.cli.main:main`): dispatch, one-line errors, exit statuses
    parser       the argument parser, one function a command
    errors       `CliError`, library messages in command-line terms, progress, checks of outputs and ranges
    detect       `tiltfit detect`, and the observations `calibrate` gathers from images or DET.json files
    calibrate    `tiltfit calibrate` (with --init, --cross-validate)
    photometric  `tiltfit calibrate --refine photometric`: the refinement adopted into the calibration
    report       `tiltfit report` and `tiltfit compare`
    export       `tiltfit export` (OpenCV, mrcal)
    target       `tiltfit target design|print`
"""
