"""`tiltfit export`: a calibration written for another library (OpenCV FileStorage, mrcal .cameramodel;
`tiltfit.files.opencv_file`, `tiltfit.files.mrcal_file`)."""
from __future__ import annotations

from .errors import CliError, as_cli_error, check_output, progress_printer


def cmd_export(args) -> int:
    """`tiltfit export CALIB.json --to opencv|mrcal -o FILE`."""
    from tiltfit.files.calib import read_calib
    from tiltfit.files.export import ExportError, check_exportable
    from tiltfit.files.mrcal_file import MRCAL_EXTENSION, write_mrcal
    from tiltfit.files.opencv_file import write_opencv

    check_output(args.output)
    if (args.to == "mrcal") != args.output.lower().endswith(MRCAL_EXTENSION):
        raise CliError(args.output, f"--to {args.to}: expected "
                       + (f"a {MRCAL_EXTENSION} file" if args.to == "mrcal" else "a .yml, .xml or .json file"))
    try:
        data = read_calib(args.calib)
        if args.to == "opencv":
            check_exportable(data)
    except ValueError as e:
        raise as_cli_error(args.calib, e) from None
    try:
        (write_mrcal if args.to == "mrcal" else write_opencv)(data, args.output)
    except (ExportError, OSError) as e:
        raise as_cli_error(args.output, e) from None
    progress_printer(args.quiet)(f"wrote {args.output}")
    return 0
