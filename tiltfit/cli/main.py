"""Command line: `tiltfit detect`, `tiltfit calibrate`, `tiltfit reproduce`, `tiltfit stability`.

    tiltfit detect IMAGE --target T.json [--encoding srgb|linear] -o DET.json
    tiltfit calibrate IMAGE... --target T.json --pixel-pitch-mm P [--fit unified|tilt|joint]
                      [--init CALIB.json] [--encoding srgb|linear] -o CALIB.json
                      [--distortion auto|none|k1|k1k2|opencv5|rational5|rational] [--held-out K]
                      [--free-principal-point | --fixed-principal-point]
    tiltfit export CALIB.json --to opencv|mrcal -o camera.yml|camera.cameramodel
    tiltfit report CALIB.json -o DIR
    tiltfit compare A.json B.json [-o DIR]        (projection difference against the two σ' prediction)
    tiltfit reproduce [--quick] [--scale N] [--target-scale N] [--device cpu|cuda] [-o DIR]
    tiltfit stability [--quick] [-o DIR]
    tiltfit target design|print ...   (tiltfit.cli.target: the target designer and the printable)

`calibrate` also accepts DET.json files (written by `tiltfit detect`) in place of images; an image where no
board is found is skipped with a warning (listed under `skipped` in CALIB.json). `--init` accepts a CALIB.json
or an OpenCV camera file (`tiltfit export`'s, or any FileStorage with camera_matrix and image size), or an
mrcal .cameramodel (LENSMODEL_PINHOLE or OPENCV4/5/8).
Errors (bad or missing file, missing key, no board found, truncated image, a fit that does not converge)
print one line `tiltfit: <file>: <problem>` on stderr and exit with status 2, leaving no output file; an
interrupt (Ctrl-C, SIGTERM) prints `tiltfit: interrupted` and exits with 130. Input files are checked by
`camio.checks` (encoding, depth, numbers), `tiltfit.target.layout`, `tiltfit.files.det` and `tiltfit.files.calib`.
Progress goes to stderr; nothing but results goes to stdout.
"""
from __future__ import annotations

import signal
import sys
import warnings

from camio.errors import one_line
from camio.interrupts import interrupt_on_sigterm

from .errors import CliError
from .parser import build_parser

EXIT_ERROR = 2
EXIT_INTERRUPTED = 130


def cmd_reproduce(argv) -> int:
    """`tiltfit reproduce ...` is `tiltfit.experiments.reproduce.main` (its own options and help)."""
    from tiltfit.experiments import reproduce

    return int(reproduce.main(list(argv)) or 0)


def cmd_stability(argv) -> int:
    """`tiltfit stability ...` is `tiltfit.experiments.stability.main` (its own options and help)."""
    from tiltfit.experiments import stability

    return int(stability.main(list(argv)) or 0)


def main(argv=None) -> int:
    """`tiltfit COMMAND ...` (the console script): the exit status, 0, `EXIT_ERROR` after one line `tiltfit:
    <file>: <problem>` on stderr, or `EXIT_INTERRUPTED`."""
    argv = sys.argv[1:] if argv is None else [str(a) for a in argv]
    previous = interrupt_on_sigterm()
    try:
        if argv and argv[0] == "reproduce":
            return cmd_reproduce(argv[1:])
        if argv and argv[0] == "stability":
            return cmd_stability(argv[1:])
        if argv and argv[0] == "target":
            from tiltfit.cli import target as target_cli

            return target_cli.main(argv[1:])
        args = build_parser().parse_args(argv)
        with warnings.catch_warnings():
            # numpy's floating-point warnings would print before the one-line error; failures are reported once.
            warnings.simplefilter("ignore", RuntimeWarning)
            return args.func(args)
    except CliError as e:
        print(f"tiltfit: {e.file}: {one_line(e.problem)}", file=sys.stderr)
        return EXIT_ERROR
    except MemoryError:
        print("tiltfit: out of memory", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        print("tiltfit: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":
    sys.exit(main())
