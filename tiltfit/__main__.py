"""`python -m tiltfit ...`: the same as the `tiltfit` command."""
import sys

try:
    from tiltfit.cli.main import main

    sys.exit(main())
except KeyboardInterrupt:  # a Ctrl-C while the modules load, or after the command's own handler
    print("tiltfit: interrupted", file=sys.stderr)
    sys.exit(130)
